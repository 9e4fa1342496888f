"""The HTTP-only body models (the resource models are :mod:`service.app.schemas`)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field


class Problem(BaseModel):
    """An error (RFC 9457 ``application/problem+json``)."""

    type: str = Field(examples=["urn:facesynth:problem:invalid-input"])
    title: str = Field(examples=["Unprocessable Content"])
    status: int = Field(examples=[422])
    detail: str = Field(examples=["clip frame 12 has 40000 vertices, the neutral has 40962"])
    errors: list[dict[str, Any]] | None = Field(
        default=None, description="Per-field errors `{loc, msg, type}` of a validation failure.")
    instance: str | None = Field(default=None, examples=["/v1/actors/act_…/clips"])
    request_id: str | None = Field(default=None, examples=["5f0c2a9e4b6d4c1f8e2a7b3c9d0e1f2a"])

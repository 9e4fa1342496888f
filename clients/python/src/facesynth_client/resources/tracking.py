"""``client.tracking``: performance-flow tracking jobs (``/v1/actors/{actor_id}/tracking-jobs``)."""

from __future__ import annotations

import json as jsonlib
from typing import Any, Mapping, Sequence

from .._core import Call
from ..types import JobAccepted
from ._base import Resource, file_part

__all__ = ["Tracking"]


class Tracking(Resource):
    """``/v1/actors/{actor_id}/tracking-jobs``: performance-flow tracking (a job).

    Provisional: API.md names the inputs (static scans, cameras, per-view video frames,
    params) but not their encoding yet; this sends them as multipart file parts plus a
    ``params`` JSON field.
    """

    def submit(self, actor_id: str, files: Mapping[str, Any] | Sequence[tuple[str, Any]],
               params: Mapping[str, Any] | None = None) -> JobAccepted:
        """Queue a tracking job.

        Parameters
        ----------
        files : mapping or sequence of (part name, value)
            a value is a path, bytes, a ``(filename, bytes, media type)`` tuple, or a list
            of them (several parts of that name, in order)
        params : dict, optional   sent as the JSON field ``params``
        """
        pairs = files.items() if isinstance(files, Mapping) else files
        parts = []
        for name, value in pairs:
            for item in (value if isinstance(value, list) else [value]):
                parts.append((name, file_part(item, name, "application/octet-stream")))
        data = {"params": jsonlib.dumps(dict(params))} if params is not None else None
        return self._run(self._core.call_accepted(
            Call("POST", f"/v1/actors/{actor_id}/tracking-jobs", files=parts, data=data),
            JobAccepted.from_json))

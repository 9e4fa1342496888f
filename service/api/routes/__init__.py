"""The API's routers, one module per resource; each route parses, calls one function, and
serializes. Shared here: OpenAPI fragments for problem responses and binary bodies."""

from __future__ import annotations

from typing import Any, Iterable

from fastapi import Response

from service.api.errors import PROBLEM_JSON
from service.api.schemas import Problem

_DESCRIPTIONS = {
    400: "Malformed body (broken JSON or multipart).",
    401: "Missing or invalid bearer token.",
    404: "Unknown id.",
    406: "No acceptable response media type.",
    409: "The resource's state forbids it (e.g. model not ready).",
    413: "Over a configured limit (named in `detail`).",
    415: "Unsupported request media type.",
    422: "Well-formed but invalid (the problem is named in `detail`).",
    503: "Overloaded; retry after `Retry-After` seconds.",
}


def problems(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for problem+json errors with these status codes."""
    return {code: {"model": Problem, "description": _DESCRIPTIONS[code],
                   "content": {PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/Problem"}}}}
            for code in codes}


def body(media_types: Iterable[str], json_schema: dict[str, Any] | None = None,
         multipart: dict[str, Any] | None = None, description: str = "") -> dict[str, Any]:
    """An OpenAPI ``requestBody`` for a route that reads its body itself.

    Parameters
    ----------
    media_types : binary media types (``application/x-npz``, ``model/obj``, ...)
    json_schema : the schema of an ``application/json`` alternative
    multipart : the properties of a ``multipart/form-data`` alternative
    """
    content: dict[str, Any] = {m: {"schema": {"type": "string", "format": "binary"}}
                               for m in media_types}
    if json_schema is not None:
        content["application/json"] = {"schema": json_schema}
    if multipart is not None:
        content["multipart/form-data"] = {"schema": {"type": "object", "properties": multipart}}
    return {"requestBody": {"required": True, "content": content, "description": description}}


def binary_response(*media_types: str, description: str) -> dict[int | str, dict[str, Any]]:
    """An OpenAPI 200 response with binary content of these media types."""
    return {200: {"description": description,
                  "content": {m: {"schema": {"type": "string", "format": "binary"}}
                              for m in media_types}}}


def set_job_location(response: Response, job_id: str) -> None:
    """``Location: /v1/jobs/{job_id}`` on a 202 answer."""
    response.headers["Location"] = f"/v1/jobs/{job_id}"


def inline_schema(model: type) -> dict[str, Any]:
    """A pydantic model's JSON schema with its ``$defs`` inlined (for ``openapi_extra``,
    where ``#/$defs/...`` would resolve against the whole OpenAPI document)."""
    schema = model.model_json_schema()
    defs = schema.pop("$defs", {})

    def resolve(node: Any) -> Any:
        if isinstance(node, dict):
            ref = node.get("$ref", "")
            if ref.startswith("#/$defs/"):
                return resolve(defs[ref.removeprefix("#/$defs/")])
            return {key: resolve(value) for key, value in node.items()}
        if isinstance(node, list):
            return [resolve(item) for item in node]
        return node

    return resolve(schema)


def etag_matches(header: str | None, etag: str) -> bool:
    """Whether an ``If-None-Match`` header matches ``etag`` (``*``, lists, weak tags)."""
    if not header:
        return False
    tags = [t.strip().removeprefix("W/") for t in header.split(",")]
    return "*" in tags or etag in tags

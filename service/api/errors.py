"""Every error the API answers, as RFC 9457 ``application/problem+json``, from one handler.

The service raises errors by meaning, never by status code: the store's
:class:`~models_store.errors.NotFound` and :class:`~models_store.errors.Conflict`, the
methods' :class:`~service.methods.inputs.InvalidInput`, the readers'
:class:`~service.io.errors.FormatError` and :class:`~service.io.errors.SizeLimitError`, and
the few errors only HTTP has (:class:`ApiProblem` below: a malformed body, an unsupported
media type, a missing token, an overloaded server). :func:`install` maps them all:

======================================  ======  ======================
error                                   status  ``type``
======================================  ======  ======================
malformed JSON / multipart body         400     ``…:malformed-body``
missing or invalid bearer token         401     ``…:unauthorized``
``NotFound``, ``InvalidId``             404     ``…:not-found``
no acceptable response media type       406     ``…:not-acceptable``
``Conflict`` (e.g. model not ready)     409     ``…:conflict``
``SizeLimitError``, body over the limit 413     ``…:too-large``
unsupported request media type          415     ``…:unsupported-media-type``
``InvalidInput``, ``FormatError``,      422     ``…:invalid-input``
request validation (with ``errors``)
overloaded (with ``Retry-After``)       503     ``…:overloaded``
``BlobCorrupt``, anything unexpected    500     ``…:internal``
======================================  ======  ======================

A problem body is ``{type, title, status, detail, errors?, instance, request_id}``; ``errors``
lists per-field validation errors as ``{loc, msg, type}``.
"""

from __future__ import annotations

import logging
from http import HTTPStatus
from typing import Any, Iterable, Mapping

from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from models_store.errors import BlobCorrupt, Conflict, InvalidId, NotFound
from service.io.errors import FormatError, SizeLimitError
from service.methods.inputs import InvalidInput

log = logging.getLogger("facesynth.api")

PROBLEM_JSON = "application/problem+json"
#: prefix of every problem ``type`` (a URN: stable, not meant to be dereferenced)
TYPE_PREFIX = "urn:facesynth:problem:"

#: status → the problem slug of the generic answer for that status
_SLUGS = {400: "malformed-body", 401: "unauthorized", 403: "forbidden", 404: "not-found",
          405: "method-not-allowed", 406: "not-acceptable", 409: "conflict", 413: "too-large",
          415: "unsupported-media-type", 416: "range-not-satisfiable", 422: "invalid-input",
          503: "overloaded"}


class ApiProblem(HTTPException):
    """An error only HTTP has; subclasses fix the status.

    It is a :class:`fastapi.HTTPException`, so it passes through FastAPI's body parsing
    untouched (e.g. a body-size error raised while FastAPI reads a JSON body).

    Parameters
    ----------
    detail : str                    what is wrong, for a person
    errors : list of dict, optional per-field errors ``{loc, msg, type}``
    headers : dict, optional        extra response headers
    """

    status: int = 500

    def __init__(self, detail: str, *, errors: list[dict[str, Any]] | None = None,
                 headers: Mapping[str, str] | None = None):
        super().__init__(self.status, detail, dict(headers) if headers else None)
        self.errors = errors


class MalformedBody(ApiProblem):
    """The body cannot be parsed at all (broken JSON, a broken multipart stream)."""

    status = 400


class Unauthorized(ApiProblem):
    """No valid ``Authorization: Bearer`` token."""

    status = 401

    def __init__(self, detail: str):
        super().__init__(detail, headers={"WWW-Authenticate": 'Bearer realm="facesynth"'})


class NotAcceptable(ApiProblem):
    """None of the media types in ``Accept`` can be produced."""

    status = 406


class PayloadTooLarge(ApiProblem):
    """The request body, or what it declares, is over a configured limit."""

    status = 413


class UnsupportedMediaType(ApiProblem):
    """The request's ``Content-Type`` is not one the route reads."""

    status = 415


class Unprocessable(ApiProblem):
    """A body that fails its schema, with per-field ``errors`` (as FastAPI's own request
    validation, for bodies a route parses itself)."""

    status = 422

    @classmethod
    def from_validation(cls, error: ValidationError, prefix: tuple = ("body",)) -> "Unprocessable":
        """The 422 for a pydantic :class:`ValidationError` of a request body."""
        errors = validation_errors(error.errors(include_url=False, include_input=False), prefix)
        return cls(_summary(errors), errors=errors)


class Overloaded(ApiProblem):
    """The server cannot take the request now; retry after ``retry_after`` seconds."""

    status = 503

    def __init__(self, detail: str, retry_after: int = 1):
        super().__init__(detail, headers={"Retry-After": str(retry_after)})


def problem(request: Request | None, status: int, detail: str, *, slug: str | None = None,
            errors: list[dict[str, Any]] | None = None,
            headers: Mapping[str, str] | None = None) -> JSONResponse:
    """A problem+json response.

    Parameters
    ----------
    request : the request answered (for ``instance`` and ``request_id``), or None
    status : HTTP status
    detail : str   what is wrong
    slug : str     last part of ``type`` (default: the generic one of the status)
    errors : list of ``{loc, msg, type}``
    headers : extra response headers
    """
    body: dict[str, Any] = {
        "type": TYPE_PREFIX + (slug or _SLUGS.get(status, "internal" if status >= 500 else "error")),
        "title": _title(status),
        "status": status,
        "detail": detail,
    }
    if errors:
        body["errors"] = errors
    if request is not None:
        body["instance"] = request.url.path
        request_id = request.scope.get("state", {}).get("request_id")
        if request_id:
            body["request_id"] = request_id
    return JSONResponse(body, status_code=status, headers=dict(headers or {}),
                        media_type=PROBLEM_JSON)


#: RFC 9110 names where Python's ``HTTPStatus`` still has the older ones
_TITLES = {413: "Content Too Large", 422: "Unprocessable Content", 416: "Range Not Satisfiable"}


def _title(status: int) -> str:
    if status in _TITLES:
        return _TITLES[status]
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


def validation_errors(errors: Iterable[Mapping[str, Any]], prefix: tuple = ()) -> list[dict]:
    """Pydantic errors as ``{loc, msg, type}`` (JSON-safe: no inputs, no exception objects)."""
    return [{"loc": [*prefix, *(e.get("loc") or ())], "msg": str(e.get("msg", "")),
             "type": str(e.get("type", ""))} for e in errors]


def _summary(errors: list[dict]) -> str:
    """One line naming the first error and how many there are."""
    first = errors[0]
    where = ".".join(str(part) for part in first["loc"])
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{where}: {first['msg']}{more}" if where else first["msg"] + more


# ---------------------------------------------------------------------------- handlers
async def _request_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    raw = list(exc.errors())
    errors = validation_errors(raw)
    if any(e["type"] == "json_invalid" for e in errors):
        ctx = next((e.get("ctx") or {} for e in raw if e.get("type") == "json_invalid"), {})
        reason = ctx.get("error", "")
        return problem(request, 400, f"the body is not valid JSON{': ' + reason if reason else ''}",
                       errors=errors)
    return problem(request, 422, _summary(errors), errors=errors)


async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    errors = getattr(exc, "errors", None)
    detail = exc.detail if isinstance(exc.detail, str) else _title(exc.status_code)
    return problem(request, exc.status_code, detail, errors=errors, headers=exc.headers)


def _mapped(status: int, slug: str):
    async def handler(request: Request, exc: Exception) -> JSONResponse:
        return problem(request, status, str(exc), slug=slug)
    return handler


async def _internal(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path,
                  exc_info=exc)
    detail = ("stored data failed its checksum; the operator has been told (see the server log)"
              if isinstance(exc, BlobCorrupt) else
              "internal error (see the server log for this request id)")
    return problem(request, 500, detail, slug="internal")


def install(app: FastAPI) -> None:
    """Register the problem+json handlers of the module docstring on ``app``."""
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(NotFound, _mapped(404, "not-found"))
    app.add_exception_handler(InvalidId, _mapped(404, "not-found"))
    app.add_exception_handler(Conflict, _mapped(409, "conflict"))
    app.add_exception_handler(SizeLimitError, _mapped(413, "too-large"))
    app.add_exception_handler(FormatError, _mapped(422, "invalid-input"))
    app.add_exception_handler(InvalidInput, _mapped(422, "invalid-input"))
    app.add_exception_handler(BlobCorrupt, _internal)
    app.add_exception_handler(Exception, _internal)

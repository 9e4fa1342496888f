"""Every error the API answers, as RFC 9457 ``application/problem+json``, from one handler.

The service raises errors by meaning (:mod:`service.errors`, one root
:class:`~service.errors.FacesynthError`); :data:`STATUS` maps each meaning to its status
once, the most specific class in an error's MRO winning. The few errors only HTTP has
(:class:`ApiProblem` below: a missing token, a body over the limit while FastAPI reads it)
carry their status themselves.

======================================  ======  ======================
error                                   status  ``type``
======================================  ======  ======================
``MalformedInput``, broken JSON         400     ``…:malformed-body``
missing or invalid bearer token         401     ``…:unauthorized``
``NotFound`` (``InvalidId``)            404     ``…:not-found``
``NotAcceptable``                       406     ``…:not-acceptable``
``Conflict`` (e.g. model not ready)     409     ``…:conflict``
``PayloadTooLarge`` (``SizeLimitError``) 413    ``…:too-large``
``UnsupportedFormat``                   415     ``…:unsupported-media-type``
``InvalidInput`` (``FormatError``),     422     ``…:invalid-input``
request validation (with ``errors``)
``Unavailable`` (with ``Retry-After``)  503     ``…:overloaded``
``InsufficientStorage``                 507     ``…:insufficient-storage``
``OSError`` ENOSPC / EDQUOT             507     ``…:insufficient-storage``
``OSError`` EROFS / EACCES              503     ``…:storage-unavailable``
``Corrupt``, anything unexpected        500     ``…:internal``
======================================  ======  ======================

A problem body is ``{type, title, status, detail, errors?, instance, request_id}``; ``errors``
lists per-field validation errors as ``{loc, msg, type}``.
"""

from __future__ import annotations

import logging
from http import HTTPStatus
from typing import Any, Mapping

from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from models_store.errors import storage_error
from service.errors import (
    Conflict, Corrupt, FacesynthError, InsufficientStorage, InvalidInput, MalformedInput,
    NotAcceptable, NotFound, PayloadTooLarge, Unavailable, UnsupportedFormat, field_errors, summary,
)

log = logging.getLogger("facesynth.api")

PROBLEM_JSON = "application/problem+json"
#: prefix of every problem ``type`` (a URN: stable, not meant to be dereferenced)
TYPE_PREFIX = "urn:facesynth:problem:"

#: status → the problem slug of the generic answer for that status
_SLUGS = {400: "malformed-body", 401: "unauthorized", 403: "forbidden", 404: "not-found",
          405: "method-not-allowed", 406: "not-acceptable", 409: "conflict", 413: "too-large",
          415: "unsupported-media-type", 416: "range-not-satisfiable", 422: "invalid-input",
          503: "overloaded", 507: "insufficient-storage"}

#: each meaning of :mod:`service.errors` → its HTTP status (the most specific class wins)
STATUS: dict[type[FacesynthError], int] = {
    InvalidInput: 422, MalformedInput: 400, UnsupportedFormat: 415, NotAcceptable: 406,
    NotFound: 404, Conflict: 409, PayloadTooLarge: 413, Corrupt: 500, Unavailable: 503,
    InsufficientStorage: 507,
}


def status_of(error: FacesynthError) -> tuple[int, dict[str, str]]:
    """The HTTP status of ``error`` by meaning (500 for the bare root) and its extra headers
    (``Retry-After`` for :class:`~service.errors.Unavailable`)."""
    status = next((STATUS[c] for c in type(error).__mro__ if c in STATUS), 500)
    headers = ({"Retry-After": str(error.retry_after)} if isinstance(error, Unavailable) else {})
    return status, headers


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


class Unauthorized(ApiProblem):
    """No valid ``Authorization: Bearer`` token."""

    status = 401

    def __init__(self, detail: str):
        super().__init__(detail, headers={"WWW-Authenticate": 'Bearer realm="facesynth"'})


class BodyTooLarge(ApiProblem):
    """The request body, or what it declares, is over a configured limit."""

    status = 413


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


# ---------------------------------------------------------------------------- handlers
async def _request_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    raw = list(exc.errors())
    errors = field_errors(raw)
    if any(e["type"] == "json_invalid" for e in errors):
        ctx = next((e.get("ctx") or {} for e in raw if e.get("type") == "json_invalid"), {})
        reason = ctx.get("error", "")
        return problem(request, 400, f"the body is not valid JSON{': ' + reason if reason else ''}",
                       errors=errors)
    return problem(request, 422, summary(errors), errors=errors)


async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    errors = getattr(exc, "errors", None)
    detail = exc.detail if isinstance(exc.detail, str) else _title(exc.status_code)
    return problem(request, exc.status_code, detail, errors=errors, headers=exc.headers)


async def _meaning(request: Request, exc: FacesynthError) -> JSONResponse:
    fault = storage_error(exc.__cause__ or exc.__context__) if not isinstance(
        exc, (Unavailable, InsufficientStorage)) else None
    if fault is not None:                # e.g. a store error caused by a full disk
        exc = fault
    status, headers = status_of(exc)
    if status >= 500 and not isinstance(exc, Unavailable):
        return await _internal(request, exc)
    return problem(request, status, str(exc), errors=getattr(exc, "errors", None),
                   headers=headers)


async def _os_error(request: Request, exc: OSError) -> JSONResponse:
    """A full disk (ENOSPC, EDQUOT) is 507, a read-only or unwritable one (EROFS, EACCES) 503
    with Retry-After, without the file name (a server path); any other OSError is a 500."""
    meaning = storage_error(exc)
    if meaning is None:
        return await _internal(request, exc)
    log.warning("storage fault on %s %s: %s", request.method, request.url.path, meaning)
    status, headers = status_of(meaning)
    slug = "insufficient-storage" if status == 507 else "storage-unavailable"
    return problem(request, status, str(meaning), slug=slug, headers=headers)


async def _internal(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path,
                  exc_info=exc)
    detail = ("stored data failed its checksum; the operator has been told (see the server log)"
              if isinstance(exc, Corrupt) else
              "internal error (see the server log for this request id)")
    return problem(request, 500, detail, slug="internal")


def install(app: FastAPI) -> None:
    """Register the problem+json handlers of the module docstring on ``app``."""
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(FacesynthError, _meaning)
    app.add_exception_handler(OSError, _os_error)
    app.add_exception_handler(Exception, _internal)

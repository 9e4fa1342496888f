"""The errors the SDK raises, one hierarchy to catch by meaning.

``FacesynthError`` is the root. An answer of the server that is an error (an RFC 9457
``application/problem+json`` body) becomes an :class:`ApiError` subclass chosen by its
status (:class:`NotFound`, :class:`Conflict`, :class:`Unprocessable`, ...), carrying the
problem's ``status``, ``title``, ``detail`` and the raw ``problem`` dict. A server that cannot
be reached (after the retries) is a :class:`TransportError`; a job that ended badly is a
:class:`JobFailed` or :class:`JobCancelled`.

Examples
--------
>>> try:                                                   # doctest: +SKIP
...     client.actors.get("act_unknown")
... except NotFound as error:
...     print(error.status, error.detail)
404 actor 'act_unknown' not found
"""

from __future__ import annotations

from typing import Any, Mapping

__all__ = [
    "FacesynthError", "ApiError", "BadRequest", "Unauthorized", "Forbidden", "NotFound",
    "MethodNotAllowed", "NotAcceptable", "Conflict", "PayloadTooLarge", "UnsupportedMediaType",
    "RangeNotSatisfiable", "Unprocessable", "ServerError", "Overloaded", "TransportError",
    "JobError", "JobFailed", "JobCancelled", "WaitTimeout", "IntegrityError", "error_for_status",
]


class FacesynthError(Exception):
    """Base of every error raised by :mod:`facesynth_client`."""


class ApiError(FacesynthError):
    """The server answered with an error status (a problem+json body).

    Attributes
    ----------
    status : int            HTTP status
    title : str             short name of the status, e.g. ``"Unprocessable Content"``
    detail : str            what is wrong, for a person (e.g. ``"model expects 150 markers,
                            got 149"``)
    type : str              the problem's type URN (``urn:facesynth:problem:invalid-input``)
    errors : list of dict   per-field validation errors ``{loc, msg, type}`` (may be empty)
    problem : dict          the raw problem body (as sent, or synthesized for a non-problem
                            error body)
    headers : dict          the response headers (e.g. ``Retry-After``)
    """

    #: the status this class stands for (None: any)
    status_code: int | None = None

    def __init__(self, problem: Mapping[str, Any], headers: Mapping[str, str] | None = None):
        self.problem: dict[str, Any] = dict(problem)
        self.status: int = int(self.problem.get("status") or self.status_code or 0)
        self.title: str = str(self.problem.get("title") or "")
        self.detail: str = str(self.problem.get("detail") or "")
        self.type: str = str(self.problem.get("type") or "about:blank")
        self.errors: list[dict[str, Any]] = list(self.problem.get("errors") or [])
        self.request_id: str | None = self.problem.get("request_id")
        self.headers: dict[str, str] = dict(headers or {})
        super().__init__(f"{self.status} {self.title}: {self.detail}".strip())


class BadRequest(ApiError):
    """400: a malformed body (broken JSON or multipart)."""
    status_code = 400


class Unauthorized(ApiError):
    """401: no valid bearer token (``token=`` / ``FACESYNTH_TOKEN``)."""
    status_code = 401


class Forbidden(ApiError):
    """403: the token may not do this."""
    status_code = 403


class NotFound(ApiError):
    """404: an unknown id."""
    status_code = 404


class MethodNotAllowed(ApiError):
    """405: the route does not take this method."""
    status_code = 405


class NotAcceptable(ApiError):
    """406: none of the asked response media types can be produced."""
    status_code = 406


class Conflict(ApiError):
    """409: the resource's state forbids it (e.g. the model is not ready)."""
    status_code = 409


class PayloadTooLarge(ApiError):
    """413: over a configured limit, named in ``detail`` (submit a job instead)."""
    status_code = 413


class UnsupportedMediaType(ApiError):
    """415: the request's Content-Type is not accepted by the route."""
    status_code = 415


class RangeNotSatisfiable(ApiError):
    """416: a download range outside the file."""
    status_code = 416


class Unprocessable(ApiError):
    """422: well-formed but invalid (e.g. a wrong marker count, NaN in a mesh)."""
    status_code = 422


class ServerError(ApiError):
    """5xx: the server failed (not the request's fault)."""


class Overloaded(ServerError):
    """503: the server is overloaded; ``retry_after`` seconds (or None) were asked.

    Raised only once the client's retries are used up.
    """
    status_code = 503

    @property
    def retry_after(self) -> float | None:
        value = self.headers.get("retry-after") or self.headers.get("Retry-After")
        try:
            return float(value) if value is not None else None
        except ValueError:
            return None


_BY_STATUS: dict[int, type[ApiError]] = {
    cls.status_code: cls for cls in (BadRequest, Unauthorized, Forbidden, NotFound,
                                     MethodNotAllowed, NotAcceptable, Conflict, PayloadTooLarge,
                                     UnsupportedMediaType, RangeNotSatisfiable, Unprocessable,
                                     Overloaded)}


def error_for_status(status: int) -> type[ApiError]:
    """The :class:`ApiError` subclass of an HTTP error status."""
    if status in _BY_STATUS:
        return _BY_STATUS[status]
    return ServerError if status >= 500 else ApiError


class TransportError(FacesynthError):
    """The server could not be reached or the connection broke (after the retries); the
    underlying :mod:`httpx` error is the ``__cause__``."""


class JobError(FacesynthError):
    """A job did not succeed; ``job`` is its last state (a :class:`~facesynth_client.Job`)."""

    def __init__(self, message: str, job: Any):
        super().__init__(message)
        self.job = job


class JobFailed(JobError):
    """The job failed; ``code`` and ``message`` are the job's ``error`` record."""

    def __init__(self, job: Any):
        error = getattr(job, "error", None)
        self.code: str = getattr(error, "code", None) or "unknown"
        self.message: str = getattr(error, "message", None) or ""
        super().__init__(f"job {job.id} failed: {self.code}: {self.message}", job)


class JobCancelled(JobError):
    """The job was cancelled (``DELETE /v1/jobs/{id}``) before it finished."""

    def __init__(self, job: Any):
        super().__init__(f"job {job.id} was cancelled", job)


class WaitTimeout(FacesynthError, TimeoutError):
    """:meth:`~facesynth_client.Client.wait` gave up after its ``timeout``; ``job`` is the last
    state seen (or None), the job itself goes on."""

    def __init__(self, message: str, job: Any = None):
        super().__init__(message)
        self.job = job


class IntegrityError(FacesynthError):
    """A downloaded file does not match its checksum (the server's ETag / sha256)."""

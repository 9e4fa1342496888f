"""The error root of the whole server: every error raised on purpose is a
:class:`FacesynthError`, subclassed by *meaning*, so callers catch by meaning and each
transport maps the meanings once (``service/api/errors.py`` to problem+json,
``service/grpc/server.py`` to gRPC status codes).

The root lives here, in the lowest package of the distribution, because ``models_store``
imports nothing of ``service`` while every layer of ``service`` may import ``models_store``;
:mod:`service.errors` re-exports it with the file-format errors added.

=========================  ===========================================  ====  ==================
class                      meaning                                      HTTP  gRPC
=========================  ===========================================  ====  ==================
:class:`InvalidInput`      well-formed input that cannot be used        422   INVALID_ARGUMENT
:class:`MalformedInput`    a body that cannot be parsed at all          400   INVALID_ARGUMENT
:class:`UnsupportedFormat` a payload format this operation does not read 415  INVALID_ARGUMENT
:class:`NotAcceptable`     no asked-for result format can be produced   406   INVALID_ARGUMENT
:class:`NotFound`          no record of that kind with that id          404   NOT_FOUND
:class:`Conflict`          contradicts the current state                409   FAILED_PRECONDITION
:class:`PayloadTooLarge`   over a configured size limit                 413   RESOURCE_EXHAUSTED
:class:`Corrupt`           stored data failed its checks (server fault) 500   DATA_LOSS
:class:`Unavailable`       cannot take the work now; retry later        503   UNAVAILABLE
:class:`InsufficientStorage`  the data disk is full                     507   RESOURCE_EXHAUSTED
=========================  ===========================================  ====  ==================
"""

from __future__ import annotations


class FacesynthError(Exception):
    """Base class of every error the server raises on purpose."""


class InvalidInput(FacesynthError, ValueError):
    """Input that is well-formed but cannot be used (a clip of the wrong vertex count, a
    parameter out of bounds, markers too few to solve for a frame).

    Attributes
    ----------
    errors : list of dict or None   per-field errors ``{loc, msg, type}`` where the input was
                                    validated against a schema
    """

    def __init__(self, message: str, errors: list[dict] | None = None):
        super().__init__(message)
        self.errors = errors


class MalformedInput(InvalidInput):
    """A payload that cannot be parsed at all (broken JSON, a broken multipart stream, an
    empty body)."""


class UnsupportedFormat(InvalidInput):
    """A payload in a format (media type) this operation does not read."""


class NotAcceptable(FacesynthError):
    """None of the result formats asked for can be produced."""


class NotFound(FacesynthError, LookupError):
    """No record (or blob) of that kind with that id.

    Attributes
    ----------
    kind : str    what was looked up, e.g. ``"actor"``
    id : str      the id (or blob key) that was not found
    """

    def __init__(self, kind: str, id: str, detail: str = ""):
        message = f"{kind} {id!r} not found" + (f": {detail}" if detail else "")
        super().__init__(message)
        self.kind = kind
        self.id = id


class InvalidId(NotFound, ValueError):
    """A string is not a well-formed id or blob key (ids become path components, so anything
    off the exact pattern is refused, and answered like an unknown id)."""

    def __init__(self, message: str):
        Exception.__init__(self, message)
        self.kind = "id"
        self.id = ""


class Conflict(FacesynthError):
    """The operation contradicts the current state (a ready model changed, an actor deleted
    while it has models, a model not ready, a job lease lost, ...)."""


class PayloadTooLarge(FacesynthError):
    """A body, a file or what it declares is over a configured limit."""


class Corrupt(FacesynthError):
    """Stored data failed its checksum or structure checks: a server-side fault, never the
    client's."""


class BlobCorrupt(Corrupt):
    """A blob's content does not match its recorded sha256.

    Attributes
    ----------
    key : str        blob key
    expected : str   recorded sha256 hex digest
    actual : str     sha256 of what is on disk
    """

    def __init__(self, key: str, expected: str, actual: str):
        super().__init__(f"blob {key!r} is corrupt: sha256 {actual} on disk, {expected} recorded")
        self.key = key
        self.expected = expected
        self.actual = actual


class Unavailable(FacesynthError):
    """The server cannot take the work now (overloaded, queue down, storage read-only).

    Attributes
    ----------
    retry_after : int   seconds after which a retry may succeed
    """

    def __init__(self, message: str, retry_after: int = 1):
        super().__init__(message)
        self.retry_after = retry_after


class InsufficientStorage(FacesynthError):
    """The data disk (or quota) is full."""


# -- storage faults ------------------------------------------------------------------------
import errno as _errno  # noqa: E402
import os as _os  # noqa: E402

#: errno values meaning "the disk (or the user's quota) is full"
FULL_ERRNOS = frozenset({_errno.ENOSPC, _errno.EDQUOT})
#: errno values meaning "the storage cannot be written now" (read-only, lost permission)
UNWRITABLE_ERRNOS = frozenset({_errno.EROFS, _errno.EACCES})
#: Retry-After of a read-only or unwritable store, seconds
STORAGE_RETRY_AFTER = 30


def storage_fault(error: BaseException) -> tuple[str, str] | None:
    """Classify an exception (or one in its ``__cause__``/``__context__`` chain) that comes
    from the server's storage being full or unwritable.

    Returns
    -------
    (code, reason) | None   ``("insufficient_storage", strerror)`` for ENOSPC/EDQUOT,
                            ``("storage_unavailable", strerror)`` for EROFS/EACCES, None for
                            anything else. The reason is the OS's text for the errno alone:
                            never the file name, which is a server path.
    """
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno is not None:
            reason = os_reason(current.errno)
            if current.errno in FULL_ERRNOS:
                return "insufficient_storage", reason
            if current.errno in UNWRITABLE_ERRNOS:
                return "storage_unavailable", reason
        current = current.__cause__ or current.__context__
    return None


def os_reason(number: int) -> str:
    """The OS's message for an errno (``"No space left on device"``), without any path."""
    return _os.strerror(number)


def storage_error(error: BaseException) -> FacesynthError | None:
    """The :class:`InsufficientStorage` or :class:`Unavailable` (retry after 30 s) meaning
    of a storage fault (:func:`storage_fault`), with no server path in its message; None
    for anything else."""
    fault = storage_fault(error)
    if fault is None:
        return None
    code, reason = fault
    if code == "insufficient_storage":
        return InsufficientStorage(f"the server's storage is full ({reason}); try again once "
                                   "space has been freed")
    return Unavailable(f"the server's storage cannot be written now ({reason}); try again "
                       "later", retry_after=STORAGE_RETRY_AFTER)

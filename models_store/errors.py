"""Errors of the model store, one hierarchy so that callers catch by meaning.

The API maps :class:`NotFound` (and :class:`InvalidId` in a URL path) to 404, :class:`Conflict`
to 409; :class:`BlobCorrupt` is a server-side fault (500), never the client's.
"""

from __future__ import annotations


class StoreError(Exception):
    """Base class of every error raised by :mod:`models_store`."""


class NotFound(StoreError, LookupError):
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


class Conflict(StoreError):
    """The operation contradicts the current state (a ready model changed, an actor deleted
    while it has models, a job lease lost, ...)."""


class InvalidId(StoreError, ValueError):
    """A string is not a well-formed id or blob key (ids become path components, so anything
    off the exact pattern is refused)."""


class BlobCorrupt(StoreError):
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


# -- storage faults ------------------------------------------------------------------------
import errno as _errno  # noqa: E402

#: errno values meaning "the disk (or the user's quota) is full"
FULL_ERRNOS = frozenset({_errno.ENOSPC, _errno.EDQUOT})
#: errno values meaning "the storage cannot be written now" (read-only, lost permission)
UNWRITABLE_ERRNOS = frozenset({_errno.EROFS, _errno.EACCES})


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
    import os

    return os.strerror(number)

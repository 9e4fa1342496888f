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

"""What every resource shares: the client it runs on, and small request-building helpers.

A resource method builds an operation of :mod:`facesynth_client._core` (a generator that
yields effects) and hands it to its client's ``_run``: :class:`~facesynth_client.Client` runs
it synchronously and returns the result, :class:`~facesynth_client.AsyncClient` returns an
awaitable of it. So each resource is written once for both clients.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from .. import arrays as A
from .._core import Core, Op

if TYPE_CHECKING:  # pragma: no cover
    from ..client import _Api

__all__ = ["Resource", "outputs_param", "file_part"]


class Resource:
    """A group of routes of the API, bound to the client that runs its operations."""

    def __init__(self, client: "_Api"):
        self._client = client

    @property
    def _core(self) -> Core:
        return self._client._core

    def _run(self, op: Op) -> Any:
        return self._client._run(op)


def outputs_param(outputs: str | Sequence[str] | None) -> str | None:
    """``outputs`` as the comma-separated query parameter (None: the server's default)."""
    if outputs is None:
        return None
    return outputs if isinstance(outputs, str) else ",".join(outputs)


def file_part(source: Any, default_name: str, media_type: str) -> tuple[str, bytes, str]:
    """A multipart file part ``(filename, bytes, media type)`` from a path or bytes."""
    if A.is_path(source):
        path = Path(source)
        return path.name, path.read_bytes(), A.MARKER_FILE_SUFFIXES.get(path.suffix.lower(),
                                                                         media_type)
    if isinstance(source, tuple):
        return source  # (filename, bytes, media type) already
    return default_name, bytes(source), media_type

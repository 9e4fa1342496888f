"""Motion-capture marker files (JSON, CSV, TRC, C3D) and the marker layout JSON.

The public marker API in one place: :class:`MarkerSequence` (:mod:`service.io.marker_sequence`),
:class:`MarkerLayout` (:mod:`service.geometry.marker_layout`), the per-format readers and
writers (:mod:`service.io.marker_json`, :mod:`service.io.marker_csv`, :mod:`service.io.trc`,
:mod:`service.io.c3d`) and :func:`read_markers`, which chooses the reader by file suffix.

Every marker reader returns a :class:`MarkerSequence`: positions (F,M,3) float64 with NaN for an
occluded marker (all three coordinates), the marker names and the frame rate when the file has
one. TRC and C3D files carry a unit and are converted to millimetres; JSON and CSV carry none and
are returned as written (API.md: lengths in the actor's own unit). Row f of the positions is the
f-th frame of the file, whatever frame numbers the file writes.

Readers take a path, bytes or a binary file object, bound the frame and marker counts before
allocating (``max_frames``, ``max_markers``) and raise
:class:`~service.io.errors.MarkerFormatError` (or :class:`~service.io.errors.SizeLimitError`).
"""

from __future__ import annotations

import os
from pathlib import Path

from service.geometry.marker_layout import BARYCENTRIC_TOLERANCE, MarkerLayout
from service.io.c3d import read_markers_c3d, write_markers_c3d
from service.io.errors import MarkerFormatError
from service.io.marker_csv import read_markers_csv, write_markers_csv
from service.io.marker_json import (
    read_marker_layout,
    read_markers_json,
    write_marker_layout,
    write_markers_json,
)
from service.io.marker_sequence import MAX_FRAMES, MAX_MARKERS, MarkerSequence
from service.io.sources import Source, Target
from service.io.trc import read_markers_trc, write_markers_trc

__all__ = [
    "BARYCENTRIC_TOLERANCE", "MAX_FRAMES", "MAX_MARKERS", "MarkerLayout", "MarkerSequence",
    "Source", "Target", "read_marker_layout", "read_markers", "read_markers_c3d",
    "read_markers_csv", "read_markers_json", "read_markers_trc", "write_marker_layout",
    "write_markers_c3d", "write_markers_csv", "write_markers_json", "write_markers_trc",
]  # fmt: skip

# ---------------------------------------------------------------------------- dispatch

_READERS = {
    ".json": read_markers_json,
    ".csv": read_markers_csv,
    ".trc": read_markers_trc,
    ".c3d": read_markers_c3d,
}


def read_markers(
    source: Source,
    suffix: str | None = None,
    *,
    max_frames: int = MAX_FRAMES,
    max_markers: int = MAX_MARKERS,
) -> MarkerSequence:
    """Read marker frames, choosing the reader by suffix (``.json``, ``.csv``, ``.trc``, ``.c3d``).

    Parameters
    ----------
    source : path, bytes or binary file
    suffix : str, optional
        e.g. ``".c3d"``; taken from the path when omitted (required for bytes and streams).
    max_frames, max_markers : int

    Returns
    -------
    MarkerSequence

    Raises
    ------
    MarkerFormatError
        For an unsupported or missing suffix, or malformed content.
    SizeLimitError
    """
    if suffix is None and isinstance(source, (str, os.PathLike)):
        suffix = Path(source).suffix
    reader = _READERS.get((suffix or "").lower())
    if reader is None:
        raise MarkerFormatError(
            f"unsupported marker file type '{suffix}'; expected .json, .csv, .trc or .c3d"
        )
    return reader(source, max_frames=max_frames, max_markers=max_markers)

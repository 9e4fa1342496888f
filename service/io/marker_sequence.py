"""The marker sequence that every marker reader returns, and the helpers the readers share.

A :class:`MarkerSequence` holds positions (F,M,3) float64 with NaN for an occluded marker (all
three coordinates), the marker names and the frame rate when the file has one. Row f of the
positions is the f-th frame of the file, whatever frame numbers the file writes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.io.errors import MarkerFormatError, SizeLimitError

MAX_FRAMES = 1_000_000
"""Default bound on the frame count a reader accepts."""
MAX_MARKERS = 10_000
"""Default bound on the marker count a reader accepts."""
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
"""Millimetres per unit of the length units TRC and C3D files may declare."""


@dataclass(frozen=True, eq=False)
class MarkerSequence:
    """Marker positions over a performance.

    Attributes
    ----------
    positions : (F,M,3) float64
        Positions (mm for TRC and C3D; as written for JSON and CSV); a NaN row is an occluded
        marker.
    names : tuple of M str, or None
        Marker names in column order; None when the file has none (frames JSON without names).
    fps : float or None
        Frame rate in frames per second, when the file records one.
    notes : tuple of str
        What the reader accepted but the caller should tell the user, as the mesh readers
        record polygon splits in ``Mesh.quad_split`` (e.g. a TRC ``NumFrames`` that disagrees
        with the rows read). Empty for a file read exactly as it declares itself.
    """

    positions: np.ndarray
    names: tuple[str, ...] | None = None
    fps: float | None = None
    notes: tuple[str, ...] = ()

    def __post_init__(self):
        positions = np.asarray(self.positions, dtype=np.float64)
        if positions.ndim != 3 or positions.shape[2] != 3:
            raise MarkerFormatError(
                f"marker positions must have shape (F,M,3), got {positions.shape}"
            )
        if np.isinf(positions).any():
            f, m, _ = np.argwhere(np.isinf(positions))[0]
            raise MarkerFormatError(f"frame {f} marker {m} has an infinite coordinate")
        positions = np.where(np.isnan(positions).any(axis=2, keepdims=True), np.nan, positions)
        names = None if self.names is None else tuple(str(name) for name in self.names)
        if names is not None and len(names) != positions.shape[1]:
            raise MarkerFormatError(
                f"{len(names)} marker names for {positions.shape[1]} markers per frame"
            )
        fps = None if self.fps is None else float(self.fps)
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise MarkerFormatError(f"frame rate must be a positive number, got {self.fps}")
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "fps", fps)
        object.__setattr__(self, "notes", tuple(str(note) for note in self.notes))


def decode_text(data: bytes, what: str) -> str:
    """``data`` decoded as UTF-8 (a BOM dropped), or a MarkerFormatError naming ``what``."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise MarkerFormatError(f"{what} is not UTF-8 text: {error}") from None


def check_counts(frames: int, markers: int, max_frames: int, max_markers: int) -> None:
    """Raise SizeLimitError for a declared frame or marker count beyond its bound."""
    if frames > max_frames:
        raise SizeLimitError("frames", frames, max_frames)
    if markers > max_markers:
        raise SizeLimitError("markers", markers, max_markers)


def cells_to_float(cells: np.ndarray, names: list[str], what: str) -> np.ndarray:
    """Parse (F, 3M) text cells (x, y, z of marker after marker); empty or ``nan`` is NaN."""
    stripped = np.char.strip(cells)
    stripped[stripped == ""] = "nan"
    try:
        return stripped.astype(np.float64)
    except ValueError:
        flat = stripped.ravel()
        for k, cell in enumerate(flat):
            try:
                float(cell)
            except ValueError:
                frame, column = np.unravel_index(k, stripped.shape)
                raise MarkerFormatError(
                    f"{what} frame {frame} marker '{names[column // 3]}' {'xyz'[column % 3]}: "
                    f"'{cell}' is not a number"
                ) from None
        raise


def number_text(values: np.ndarray) -> list[list[str]]:
    """repr-exact text of every value, empty for NaN, as nested lists (rows of cells)."""
    return [["" if v != v else repr(v) for v in row] for row in values.tolist()]


def require_names(markers: MarkerSequence) -> tuple[str, ...]:
    """The sequence's marker names, or ValueError for the writers of formats that need them."""
    if markers.names is None:
        raise ValueError("this format needs marker names; the sequence has none")
    return markers.names

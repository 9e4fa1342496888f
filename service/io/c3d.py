"""C3D motion-capture files: the 3-D points, converted to millimetres."""

from __future__ import annotations

import io
import warnings

import c3d
import numpy as np

from service.io.errors import MarkerFormatError
from service.io.marker_sequence import (
    MAX_FRAMES,
    MAX_MARKERS,
    MM_PER_UNIT,
    MarkerSequence,
    check_counts,
    require_names,
)
from service.io.sources import Source, Target, read_source, write_target


def read_markers_c3d(
    source: Source, *, max_frames: int = MAX_FRAMES, max_markers: int = MAX_MARKERS
) -> MarkerSequence:
    """Read the 3-D points of a C3D file (via the ``c3d`` package), converting to mm.

    A point with a negative residual (the C3D "invalid" flag) is occluded. ``POINT:UNITS`` of
    ``mm``, ``cm`` or ``m`` is honoured (mm when absent); analog channels are ignored.

    Parameters
    ----------
    source : path, bytes or binary file
    max_frames, max_markers : int

    Returns
    -------
    MarkerSequence
        Positions in mm (float32 in the file), names from ``POINT:LABELS`` (and ``LABELS2``;
        ``M<k>`` for unlabelled points), fps from ``POINT:RATE``.

    Raises
    ------
    MarkerFormatError, SizeLimitError
    """
    data = read_source(source)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            reader = c3d.Reader(io.BytesIO(data))
            frames, count = int(reader.frame_count), int(reader.point_used)
            names = []
            for key in ("POINT:LABELS", "POINT:LABELS2"):  # LABELS2 continues past 255 points
                labels = reader.get(key)
                names += [] if labels is None else [n.strip() for n in labels.string_array]
            units = reader.get("POINT:UNITS")
            units = "mm" if units is None else units.string_value.strip().lower()
            fps = float(reader.point_rate)
        except Exception as error:  # the c3d package raises anything on malformed bytes
            raise MarkerFormatError(f"not a readable C3D file: {error!r}") from None
        if frames < 0:
            raise MarkerFormatError(f"C3D header gives a negative frame count {frames}")
        check_counts(frames, count, max_frames, max_markers)
        if units not in MM_PER_UNIT:
            raise MarkerFormatError(
                f"C3D POINT:UNITS '{units}' is not one of {sorted(MM_PER_UNIT)}"
            )
        if len(names) < count:
            names += [f"M{k + 1}" for k in range(len(names), count)]
        rows = []  # grows with the frames actually present, not with the header's claim
        try:
            for _, points, _ in reader.read_frames(copy=False):
                rows.append(np.where(points[:, 3:4] >= 0, points[:, :3], np.nan))
                if len(rows) > frames:
                    break
        except Exception as error:  # as above
            raise MarkerFormatError(f"C3D frame data is unreadable: {error!r}") from None
    if len(rows) != frames:
        raise MarkerFormatError(f"C3D file declares {frames} frames but holds {len(rows)}")
    positions = np.array(rows, dtype=np.float64).reshape(frames, count, 3)
    return MarkerSequence(
        positions * MM_PER_UNIT[units], names[:count], fps if fps > 0 else None
    )


def write_markers_c3d(target: Target, markers: MarkerSequence, *, fps: float | None = None) -> None:
    """Write a C3D file of float32 points in mm (occluded markers flagged invalid).

    Parameters
    ----------
    target : path or binary file
    markers : MarkerSequence
        Positions taken as mm; needs names.
    fps : float, optional
        Frame rate; defaults to ``markers.fps``. C3D requires one.

    Raises
    ------
    ValueError
        Without names, without a frame rate, or with no frames.
    """
    names = require_names(markers)
    fps = fps if fps is not None else markers.fps
    if fps is None:
        raise ValueError("C3D needs a frame rate: pass fps or set markers.fps")
    if len(markers.positions) == 0:
        raise ValueError("C3D needs at least one frame")
    writer = c3d.Writer(point_rate=float(fps), point_units="mm")
    writer.set_point_labels(list(names))
    no_analog = np.zeros((0, 0), np.float32)
    for frame in markers.positions:
        points = np.zeros((len(names), 5), np.float32)
        occluded = np.isnan(frame).any(axis=1)
        points[:, :3] = np.where(occluded[:, None], 0.0, frame)
        points[occluded, 3] = -1.0
        writer.add_frames([(points, no_analog)])
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No analog data found in file."
        writer.write(buffer)
    write_target(target, buffer.getvalue())

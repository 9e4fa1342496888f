"""Marker CSV files: a header ``frame,<name>_x,<name>_y,<name>_z,...``, one row per frame.

CSV carries no unit or frame rate: positions are returned as written (the actor's own unit).
"""

from __future__ import annotations

import csv
import io
import re

import numpy as np

from service.io.errors import MarkerFormatError
from service.io.marker_sequence import (
    MAX_FRAMES,
    MAX_MARKERS,
    MarkerSequence,
    cells_to_float,
    check_counts,
    decode_text,
    number_text,
    require_names,
)
from service.io.sources import Source, Target, read_source, write_target

_CSV_META = {"frame", "frame#", "time"}
_CSV_AXIS = re.compile(r"^(.+?)[_.:]([xyzXYZ])$")


def read_markers_csv(
    source: Source, *, max_frames: int = MAX_FRAMES, max_markers: int = MAX_MARKERS
) -> MarkerSequence:
    """Read a marker CSV: header ``frame,<name>_x,<name>_y,<name>_z,...``, one row per frame.

    Axis columns may be written ``<name>_x``, ``<name>.x`` or ``<name>:X``; optional ``frame``,
    ``frame#`` and ``time`` columns are skipped. Empty cells or ``nan`` mark an occluded marker
    (one missing coordinate occludes the whole marker).

    Parameters
    ----------
    source : path, bytes or binary file
    max_frames, max_markers : int

    Returns
    -------
    MarkerSequence
        Without fps (CSV records none).

    Raises
    ------
    MarkerFormatError, SizeLimitError
    """
    text = decode_text(read_source(source), "marker CSV")
    rows = [row for row in csv.reader(io.StringIO(text, newline="")) if any(map(str.strip, row))]
    if not rows:
        raise MarkerFormatError("marker CSV is empty")
    header = [cell.strip() for cell in rows[0]]
    check_counts(len(rows) - 1, len(header) // 3, max_frames, max_markers)
    names, columns = [], {}
    for k, title in enumerate(header):
        if title.lower() in _CSV_META:
            continue
        match = _CSV_AXIS.match(title)
        if match is None:
            raise MarkerFormatError(
                f"CSV column {k + 1} '{title}' is neither frame/time nor <name>_x, <name>_y, "
                "<name>_z (or <name>.x, <name>:X)"
            )
        name, axis = match.group(1), "xyz".index(match.group(2).lower())
        if name not in columns:
            names.append(name)
            columns[name] = [None, None, None]
        if columns[name][axis] is not None:
            raise MarkerFormatError(f"CSV has two '{'xyz'[axis]}' columns for marker '{name}'")
        columns[name][axis] = k
    for name in names:
        if None in columns[name]:
            missing = [axis for axis, k in zip("xyz", columns[name]) if k is None]
            raise MarkerFormatError(f"CSV marker '{name}' lacks the column(s) {missing}")
    if not names:
        raise MarkerFormatError("marker CSV has no marker columns")
    for r, row in enumerate(rows[1:], 2):
        if len(row) != len(header):
            raise MarkerFormatError(
                f"CSV row {r} has {len(row)} cells, the header has {len(header)}"
            )
    order = np.array([columns[name] for name in names]).ravel()
    cells = np.array(rows[1:], dtype=str).reshape(len(rows) - 1, len(header))[:, order]
    values = cells_to_float(cells, names, "CSV")
    return MarkerSequence(values.reshape(len(rows) - 1, len(names), 3), names)


def write_markers_csv(target: Target, markers: MarkerSequence) -> None:
    """Write a marker CSV ``frame,<name>_x,<name>_y,<name>_z,...`` (frames numbered from 1).

    Occluded markers are empty cells; numbers are repr-exact.

    Raises
    ------
    ValueError
        If the sequence has no marker names.
    """
    names = require_names(markers)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["frame"] + [f"{name}_{axis}" for name in names for axis in "xyz"])
    cells = number_text(markers.positions.reshape(len(markers.positions), -1))
    writer.writerows([str(f)] + row for f, row in enumerate(cells, 1))
    write_target(target, buffer.getvalue().encode("utf-8"))

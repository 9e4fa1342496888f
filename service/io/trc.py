"""TRC marker files (OpenSim / Motion Analysis, tab-separated), converted to millimetres."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from service.io.errors import MarkerFormatError
from service.io.marker_sequence import (
    MAX_FRAMES,
    MAX_MARKERS,
    MM_PER_UNIT,
    MarkerSequence,
    cells_to_float,
    check_counts,
    decode_text,
    number_text,
    require_names,
)
from service.io.sources import Source, Target, read_source, write_target


def read_markers_trc(
    source: Source, *, max_frames: int = MAX_FRAMES, max_markers: int = MAX_MARKERS
) -> MarkerSequence:
    """Read a TRC file (OpenSim / Motion Analysis, tab-separated), converting to mm.

    Five header lines: ``PathFileType``, the keys ``DataRate ... NumFrames NumMarkers Units
    ...``, their values, ``Frame#  Time  M1  <tab><tab>  M2 ...`` and ``X1 Y1 Z1 ...``; then one
    row per frame (blank lines skipped). Empty cells are occluded markers. Units ``mm``, ``cm``
    or ``m``.

    As OpenSim's ``TRCFileAdapter`` does, header keys and values are separated by one or more
    tabs (empty fields are dropped before keys and values are paired), and the frames are the
    rows the file holds: a ``NumFrames`` that disagrees is reported in
    :attr:`MarkerSequence.notes`, not refused (5 of OpenSim's own 22 example files disagree).

    Parameters
    ----------
    source : path, bytes or binary file
    max_frames, max_markers : int
        Bounds on the rows and on ``NumMarkers``.

    Returns
    -------
    MarkerSequence
        Positions in mm, fps from ``DataRate``, a note when ``NumFrames`` is not the row count.

    Raises
    ------
    MarkerFormatError
        For a malformed header (naming the key and the value it quotes), an unknown unit, a
        marker count that disagrees with the names, or a row longer than the markers need.
    SizeLimitError
    """
    lines = decode_text(read_source(source), "TRC file").splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise MarkerFormatError(
            "not a TRC file: it needs 5 header lines starting with 'PathFileType'"
        )
    keys = [cell.strip() for cell in lines[1].split("\t") if cell.strip()]
    values = [cell.strip() for cell in lines[2].split("\t") if cell.strip()]
    if len(keys) != len(values):
        raise MarkerFormatError(
            f"TRC header has {len(keys)} keys {keys} but {len(values)} values {values}"
        )
    settings = dict(zip(keys, values))
    frames = _setting(settings, "NumFrames", int, "a whole number")
    count = _setting(settings, "NumMarkers", int, "a whole number")
    units = _setting(settings, "Units", str, "a unit")
    fps = _setting(settings, "DataRate", float, "a number") if "DataRate" in settings else None
    if units not in MM_PER_UNIT:
        raise MarkerFormatError(f"TRC unit '{units}' is not one of {sorted(MM_PER_UNIT)}")
    check_counts(0, count, max_frames, max_markers)
    names = [cell.strip() for cell in lines[3].split("\t")[2:] if cell.strip()]
    if len(names) != count:
        raise MarkerFormatError(f"TRC header says {count} markers but names {len(names)}")
    rows = [line.split("\t") for line in lines[5:] if line.strip()]
    check_counts(len(rows), count, max_frames, max_markers)
    notes = ()
    if len(rows) != frames:
        notes = (
            f"the TRC header says NumFrames {frames} but the file has {len(rows)} frame rows; "
            f"the {len(rows)} rows were read",
        )
    width = 2 + 3 * count
    for r, row in enumerate(rows):
        if len(row) > width and any(cell.strip() for cell in row[width:]):
            raise MarkerFormatError(
                f"TRC frame row {r + 1} has {len(row)} cells, {count} markers need {width}"
            )
        rows[r] = row[:width] + [""] * (width - len(row))
    cells = np.array(rows, dtype=str).reshape(len(rows), width)[:, 2:]
    values = cells_to_float(cells, names, "TRC") * MM_PER_UNIT[units]
    return MarkerSequence(values.reshape(len(rows), count, 3), names, fps, notes)


def _setting(settings: dict[str, str], key: str, parse, expected: str):
    """One TRC header value, parsed, or a MarkerFormatError quoting it."""
    if key not in settings:
        raise MarkerFormatError(f"TRC header lacks the key {key} (it has {sorted(settings)})")
    try:
        return parse(settings[key])
    except ValueError:
        raise MarkerFormatError(
            f"TRC header gives {key} '{settings[key]}', expected {expected}"
        ) from None


def write_markers_trc(target: Target, markers: MarkerSequence, *, fps: float | None = None) -> None:
    """Write a TRC file in mm (occluded markers as empty cells, numbers repr-exact).

    Parameters
    ----------
    target : path or binary file
    markers : MarkerSequence
        Positions taken as mm; needs names.
    fps : float, optional
        Frame rate; defaults to ``markers.fps``. TRC requires one.

    Raises
    ------
    ValueError
        Without names, with a blank name or one holding a tab or newline, or without a frame
        rate.
    """
    names = require_names(markers)
    fps = fps if fps is not None else markers.fps
    if fps is None:
        raise ValueError("TRC needs a frame rate: pass fps or set markers.fps")
    awkward = [name for name in names if not name.strip() or set(name) & set("\t\r\n")]
    if awkward:
        raise ValueError(f"TRC marker names cannot be blank or hold tabs or newlines: {awkward}")
    frames, count = markers.positions.shape[:2]
    name = Path(target).name if isinstance(target, (str, os.PathLike)) else "markers.trc"
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame"
        "\tOrigNumFrames",
        f"{fps!r}\t{fps!r}\t{frames}\t{count}\tmm\t{fps!r}\t1\t{frames}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names),
        "\t\t" + "\t".join(f"X{k}\tY{k}\tZ{k}" for k in range(1, count + 1)),
        "",
    ]
    cells = number_text(markers.positions.reshape(frames, -1))
    lines += [
        "\t".join([str(f + 1), repr(f / fps)] + row) for f, row in enumerate(cells)
    ]
    write_target(target, ("\n".join(lines) + "\n").encode("utf-8"))

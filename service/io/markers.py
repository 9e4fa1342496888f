"""Motion-capture marker files (JSON, CSV, TRC, C3D) and the marker layout JSON.

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

import csv
import io
import json
import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Union

import c3d
import numpy as np

from service.io.errors import MarkerFormatError, SizeLimitError

MAX_FRAMES = 1_000_000
"""Default bound on the frame count a reader accepts."""
MAX_MARKERS = 10_000
"""Default bound on the marker count a reader accepts."""
BARYCENTRIC_TOLERANCE = 1e-6
"""How far the barycentric coordinates of a layout marker may sum from 1."""

Source = Union[str, os.PathLike, bytes, bytearray, memoryview, BinaryIO]
Target = Union[str, os.PathLike, BinaryIO]

_MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


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
    """

    positions: np.ndarray
    names: tuple[str, ...] | None = None
    fps: float | None = None

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


@dataclass(frozen=True, eq=False)
class MarkerLayout:
    """Where the markers sit on the actor's neutral (API.md ``PUT /markers``).

    Each marker is given one way: on a vertex, at barycentric coordinates in a triangle, or as a
    free position (to be snapped to the surface by the caller; kept as given here).

    Attributes
    ----------
    names : tuple of M str          unique marker names, in layout order
    kinds : tuple of M str          ``"vertex"``, ``"triangle"`` or ``"position"`` per marker
    vertex : (M,) int64             vertex index, -1 where the kind is not ``vertex``
    triangle : (M,) int64           triangle index, -1 where the kind is not ``triangle``
    barycentric : (M,3) float64     non-negative, summing to 1; NaN where not ``triangle``
    position : (M,3) float64        in the actor's unit; NaN where not ``position``
    """

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    vertex: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    position: np.ndarray


# ---------------------------------------------------------------------------- sources


def _read_source(source: Source) -> bytes:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source)
    if isinstance(source, (str, os.PathLike)):
        return Path(source).read_bytes()
    return source.read()


def _write_target(target: Target, data: bytes) -> None:
    if isinstance(target, (str, os.PathLike)):
        Path(target).write_bytes(data)
    else:
        target.write(data)


def _text(data: bytes, what: str) -> str:
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise MarkerFormatError(f"{what} is not UTF-8 text: {error}") from None


def _check_counts(frames: int, markers: int, max_frames: int, max_markers: int) -> None:
    if frames > max_frames:
        raise SizeLimitError("frames", frames, max_frames)
    if markers > max_markers:
        raise SizeLimitError("markers", markers, max_markers)


def _cells_to_float(cells: np.ndarray, names: list[str], what: str) -> np.ndarray:
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


def _number_text(values: np.ndarray) -> list[list[str]]:
    """repr-exact text of every value, empty for NaN, as nested lists (rows of cells)."""
    return [["" if v != v else repr(v) for v in row] for row in values.tolist()]


# ---------------------------------------------------------------------------- JSON frames


def read_markers_json(
    source: Source, *, max_frames: int = MAX_FRAMES, max_markers: int = MAX_MARKERS
) -> MarkerSequence:
    """Read marker frames from API.md's JSON body ``{"markers": [[[x,y,z], ...], ...]}``.

    ``null`` (or ``[null, null, null]``) is an occluded marker. Optional ``"names"`` (M strings)
    and ``"fps"`` are read too; other keys (``outputs``, ``map_resolution``...) are ignored.

    Parameters
    ----------
    source : path, bytes or binary file
    max_frames, max_markers : int

    Returns
    -------
    MarkerSequence

    Raises
    ------
    MarkerFormatError, SizeLimitError
    """
    try:
        body = json.loads(_text(_read_source(source), "marker JSON"))
    except json.JSONDecodeError as error:
        raise MarkerFormatError(f"marker JSON is not valid JSON: {error}") from None
    if not isinstance(body, dict) or not isinstance(body.get("markers"), list):
        raise MarkerFormatError('marker JSON must be an object with a "markers" list of frames')
    frames = body["markers"]
    if not frames or not all(isinstance(frame, list) for frame in frames):
        raise MarkerFormatError(
            '"markers" must be a non-empty list of frames, each a list of markers'
        )
    _check_counts(len(frames), max(map(len, frames)), max_frames, max_markers)
    count = len(frames[0])
    rows = []
    for f, frame in enumerate(frames):
        if len(frame) != count:
            raise MarkerFormatError(f"frame {f} has {len(frame)} markers, frame 0 has {count}")
        for m, marker in enumerate(frame):
            if marker is None:
                rows.append((None, None, None))
            elif (
                isinstance(marker, list) and len(marker) == 3
                and all(c is None or type(c) in (int, float) for c in marker)
                and (all(c is None for c in marker) or not any(c is None for c in marker))
            ):  # fmt: skip
                rows.append(marker)
            else:
                raise MarkerFormatError(
                    f"frame {f} marker {m} is {json.dumps(marker)[:60]}, "
                    "expected [x, y, z] numbers or null"
                )
    positions = np.array(rows, dtype=np.float64).reshape(len(frames), count, 3)
    names = body.get("names")
    if names is not None and not (
        isinstance(names, list) and all(isinstance(n, str) for n in names)
    ):
        raise MarkerFormatError('"names" must be a list of strings')
    fps = body.get("fps")
    if fps is not None and type(fps) not in (int, float):
        raise MarkerFormatError(f'"fps" must be a number, got {json.dumps(fps)}')
    return MarkerSequence(positions, names, fps)


def write_markers_json(target: Target, markers: MarkerSequence) -> None:
    """Write marker frames as ``{"markers": [[[x,y,z] | null, ...], ...], "names"?, "fps"?}``.

    Numbers are written repr-exact, so float64 values read back bit-identical.
    """
    frames = [
        [None if x != x else [x, y, z] for x, y, z in frame]
        for frame in markers.positions.tolist()
    ]
    body = {"markers": frames}
    if markers.names is not None:
        body["names"] = list(markers.names)
    if markers.fps is not None:
        body["fps"] = markers.fps
    _write_target(target, json.dumps(body, allow_nan=False).encode("utf-8"))


# ---------------------------------------------------------------------------- layout JSON


def read_marker_layout(
    source: Source,
    *,
    vertex_count: int | None = None,
    triangle_count: int | None = None,
    max_markers: int = MAX_MARKERS,
) -> MarkerLayout:
    """Read and validate API.md's marker layout JSON.

    ``{"markers": [{"name": "FH1", "vertex": 812} | {"name": "FH2", "triangle": 9912,
    "barycentric": [0.2, 0.3, 0.5]} | {"name": "FH3", "position": [x, y, z]}, ...]}``

    Parameters
    ----------
    source : path, bytes or binary file
    vertex_count, triangle_count : int, optional
        When given, vertex and triangle indices are checked against them.
    max_markers : int

    Returns
    -------
    MarkerLayout

    Raises
    ------
    MarkerFormatError
        For a missing or duplicate name, unknown keys, not exactly one placement per marker,
        negative or out-of-range indices, barycentrics that are negative or do not sum to 1
        within :data:`BARYCENTRIC_TOLERANCE`, or a non-finite position.
    SizeLimitError
    """
    try:
        body = json.loads(_text(_read_source(source), "marker layout"))
    except json.JSONDecodeError as error:
        raise MarkerFormatError(f"marker layout is not valid JSON: {error}") from None
    if not (isinstance(body, dict) and isinstance(body.get("markers"), list) and body["markers"]):
        raise MarkerFormatError('marker layout must be an object with a non-empty "markers" list')
    entries = body["markers"]
    if len(entries) > max_markers:
        raise SizeLimitError("markers", len(entries), max_markers)
    count = len(entries)
    names, kinds = [], []
    vertex = np.full(count, -1, np.int64)
    triangle = np.full(count, -1, np.int64)
    barycentric = np.full((count, 3), np.nan)
    position = np.full((count, 3), np.nan)
    for m, entry in enumerate(entries):
        if not (isinstance(entry, dict) and isinstance(entry.get("name"), str) and entry["name"]):
            raise MarkerFormatError(f'marker {m} needs a non-empty string "name"')
        name = entry["name"]
        keys = set(entry) - {"name"}
        label = f"marker {m} ('{name}')"
        if keys == {"vertex"}:
            kind = "vertex"
            vertex[m] = _layout_index(entry["vertex"], vertex_count, label, "vertex", "vertices")
        elif keys == {"triangle", "barycentric"}:
            kind = "triangle"
            triangle[m] = _layout_index(
                entry["triangle"], triangle_count, label, "triangle", "triangles"
            )
            barycentric[m] = _layout_vector(entry["barycentric"], label, "barycentric")
            total = float(barycentric[m].sum())
            if (barycentric[m] < 0).any() or abs(total - 1) > BARYCENTRIC_TOLERANCE:
                raise MarkerFormatError(
                    f"{label} has barycentric {entry['barycentric']}; they must be non-negative "
                    f"and sum to 1 (within {BARYCENTRIC_TOLERANCE:g}), the sum is {total!r}"
                )
        elif keys == {"position"}:
            kind = "position"
            position[m] = _layout_vector(entry["position"], label, "position")
        else:
            raise MarkerFormatError(
                f"{label} has keys {sorted(keys)}; expected exactly one of "
                "['vertex'], ['barycentric', 'triangle'] or ['position'] besides 'name'"
            )
        names.append(name)
        kinds.append(kind)
    seen = set()
    for name in names:
        if name in seen:
            raise MarkerFormatError(f"marker name '{name}' appears more than once")
        seen.add(name)
    return MarkerLayout(tuple(names), tuple(kinds), vertex, triangle, barycentric, position)


def _layout_index(value, count: int | None, label: str, what: str, plural: str) -> int:
    if type(value) is not int or value < 0:
        raise MarkerFormatError(f"{label} has {what} {json.dumps(value)}, expected an index >= 0")
    if count is not None and value >= count:
        raise MarkerFormatError(
            f"{label} references {what} {value} but the neutral has {count} {plural}"
        )
    return value


def _layout_vector(value, label: str, what: str) -> np.ndarray:
    if not (
        isinstance(value, list) and len(value) == 3
        and all(type(c) in (int, float) and math.isfinite(c) for c in value)
    ):  # fmt: skip
        raise MarkerFormatError(
            f"{label} has {what} {json.dumps(value)[:60]}, expected 3 finite numbers"
        )
    return np.array(value, dtype=np.float64)


def write_marker_layout(target: Target, layout: MarkerLayout) -> None:
    """Write a marker layout as API.md's JSON (numbers repr-exact)."""
    entries = []
    for m, (name, kind) in enumerate(zip(layout.names, layout.kinds)):
        if kind == "vertex":
            entries.append({"name": name, "vertex": int(layout.vertex[m])})
        elif kind == "triangle":
            entries.append(
                {
                    "name": name,
                    "triangle": int(layout.triangle[m]),
                    "barycentric": layout.barycentric[m].tolist(),
                }
            )
        else:
            entries.append({"name": name, "position": layout.position[m].tolist()})
    _write_target(target, json.dumps({"markers": entries}, allow_nan=False).encode("utf-8"))


# ---------------------------------------------------------------------------- CSV

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
    text = _text(_read_source(source), "marker CSV")
    rows = [row for row in csv.reader(io.StringIO(text, newline="")) if any(map(str.strip, row))]
    if not rows:
        raise MarkerFormatError("marker CSV is empty")
    header = [cell.strip() for cell in rows[0]]
    _check_counts(len(rows) - 1, len(header) // 3, max_frames, max_markers)
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
    values = _cells_to_float(cells, names, "CSV")
    return MarkerSequence(values.reshape(len(rows) - 1, len(names), 3), names)


def write_markers_csv(target: Target, markers: MarkerSequence) -> None:
    """Write a marker CSV ``frame,<name>_x,<name>_y,<name>_z,...`` (frames numbered from 1).

    Occluded markers are empty cells; numbers are repr-exact.

    Raises
    ------
    ValueError
        If the sequence has no marker names.
    """
    names = _require_names(markers)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["frame"] + [f"{name}_{axis}" for name in names for axis in "xyz"])
    cells = _number_text(markers.positions.reshape(len(markers.positions), -1))
    writer.writerows([str(f)] + row for f, row in enumerate(cells, 1))
    _write_target(target, buffer.getvalue().encode("utf-8"))


def _require_names(markers: MarkerSequence) -> tuple[str, ...]:
    if markers.names is None:
        raise ValueError("this format needs marker names; the sequence has none")
    return markers.names


# ---------------------------------------------------------------------------- TRC


def read_markers_trc(
    source: Source, *, max_frames: int = MAX_FRAMES, max_markers: int = MAX_MARKERS
) -> MarkerSequence:
    """Read a TRC file (OpenSim / Motion Analysis, tab-separated), converting to mm.

    Five header lines: ``PathFileType``, the keys ``DataRate ... NumFrames NumMarkers Units
    ...``, their values, ``Frame#  Time  M1  <tab><tab>  M2 ...`` and ``X1 Y1 Z1 ...``; then one
    row per frame (blank lines skipped). Empty cells are occluded markers. Units ``mm``, ``cm``
    or ``m``.

    Parameters
    ----------
    source : path, bytes or binary file
    max_frames, max_markers : int

    Returns
    -------
    MarkerSequence
        Positions in mm, fps from ``DataRate``.

    Raises
    ------
    MarkerFormatError
        For a malformed header, an unknown unit, or a frame or marker count that disagrees with
        the header.
    SizeLimitError
    """
    lines = _text(_read_source(source), "TRC file").splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise MarkerFormatError(
            "not a TRC file: it needs 5 header lines starting with 'PathFileType'"
        )
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    settings = {k.strip(): v.strip() for k, v in zip(keys, values)}
    try:
        frames, count = int(settings["NumFrames"]), int(settings["NumMarkers"])
        units = settings["Units"]
        fps = float(settings["DataRate"]) if settings.get("DataRate") else None
    except (KeyError, ValueError) as error:
        raise MarkerFormatError(
            f"TRC header lacks or garbles NumFrames, NumMarkers, Units or DataRate ({error})"
        ) from None
    if units not in _MM_PER_UNIT:
        raise MarkerFormatError(f"TRC unit '{units}' is not one of {sorted(_MM_PER_UNIT)}")
    _check_counts(frames, count, max_frames, max_markers)
    names = [cell.strip() for cell in lines[3].split("\t")[2:] if cell.strip()]
    if len(names) != count:
        raise MarkerFormatError(f"TRC header says {count} markers but names {len(names)}")
    rows = [line.split("\t") for line in lines[5:] if line.strip()]
    if len(rows) != frames:
        raise MarkerFormatError(
            f"TRC header says {frames} frames but the file has {len(rows)} rows"
        )
    width = 2 + 3 * count
    for r, row in enumerate(rows):
        if len(row) > width and any(cell.strip() for cell in row[width:]):
            raise MarkerFormatError(
                f"TRC frame row {r + 1} has {len(row)} cells, {count} markers need {width}"
            )
        rows[r] = row[:width] + [""] * (width - len(row))
    cells = np.array(rows, dtype=str).reshape(frames, width)[:, 2:]
    values = _cells_to_float(cells, names, "TRC") * _MM_PER_UNIT[units]
    return MarkerSequence(values.reshape(frames, count, 3), names, fps)


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
    names = _require_names(markers)
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
    cells = _number_text(markers.positions.reshape(frames, -1))
    lines += [
        "\t".join([str(f + 1), repr(f / fps)] + row) for f, row in enumerate(cells)
    ]
    _write_target(target, ("\n".join(lines) + "\n").encode("utf-8"))


# ---------------------------------------------------------------------------- C3D


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
    data = _read_source(source)
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
        _check_counts(frames, count, max_frames, max_markers)
        if units not in _MM_PER_UNIT:
            raise MarkerFormatError(
                f"C3D POINT:UNITS '{units}' is not one of {sorted(_MM_PER_UNIT)}"
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
        positions * _MM_PER_UNIT[units], names[:count], fps if fps > 0 else None
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
    names = _require_names(markers)
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
    _write_target(target, buffer.getvalue())


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

"""Marker frames as API.md's JSON body, and the marker layout JSON.

Frames: ``{"markers": [[[x,y,z] | null, ...], ...], "names"?, "fps"?}``, returned as written
(JSON carries no unit: lengths are in the actor's own unit). Layout: ``{"markers": [{"name",
"vertex"} | {"name", "triangle", "barycentric"} | {"name", "position"}, ...]}``.
"""

from __future__ import annotations

import json
import math

import numpy as np

from service.geometry.marker_layout import BARYCENTRIC_TOLERANCE, MarkerLayout
from service.io.errors import MarkerFormatError, SizeLimitError
from service.io.marker_sequence import (
    MAX_FRAMES,
    MAX_MARKERS,
    MarkerSequence,
    check_counts,
    decode_text,
)
from service.io.sources import Source, Target, read_source, write_target


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
        body = json.loads(decode_text(read_source(source), "marker JSON"))
    except json.JSONDecodeError as error:
        raise MarkerFormatError(f"marker JSON is not valid JSON: {error}") from None
    if not isinstance(body, dict) or not isinstance(body.get("markers"), list):
        raise MarkerFormatError('marker JSON must be an object with a "markers" list of frames')
    frames = body["markers"]
    if not frames or not all(isinstance(frame, list) for frame in frames):
        raise MarkerFormatError(
            '"markers" must be a non-empty list of frames, each a list of markers'
        )
    check_counts(len(frames), max(map(len, frames)), max_frames, max_markers)
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
    write_target(target, json.dumps(body, allow_nan=False).encode("utf-8"))


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
        body = json.loads(decode_text(read_source(source), "marker layout"))
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
            if ((barycentric[m] < -BARYCENTRIC_TOLERANCE).any()
                    or abs(total - 1) > BARYCENTRIC_TOLERANCE):
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
    write_target(target, json.dumps({"markers": entries}, allow_nan=False).encode("utf-8"))

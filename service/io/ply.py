"""PLY meshes (ASCII or binary, either endianness), read and written without re-indexing.

See :mod:`service.io.triangle_mesh` for what a :class:`~service.io.triangle_mesh.Mesh` keeps.
"""

from __future__ import annotations

import itertools
import struct
from dataclasses import dataclass

import numpy as np

from service.io.errors import MeshFormatError, SizeLimitError
from service.io.sources import Source, Target, read_source, write_target
from service.io.triangle_mesh import (
    MAX_FACES,
    MAX_VERTICES,
    NO_UV,
    Mesh,
    mesh_from_polygons,
    size_runs,
)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_UV_NAMES = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"))
_PLY_FACE_LISTS = ("vertex_indices", "vertex_index")
_PLY_FACE_UV = "texcoord"


@dataclass(frozen=True)
class _PlyProperty:
    name: str
    code: str  # numpy type code of the value (or of the list items)
    count_code: str | None  # numpy type code of a list's length, None for a scalar


@dataclass(frozen=True)
class _PlyElement:
    name: str
    count: int
    properties: tuple[_PlyProperty, ...]


def _ply_header(data: bytes) -> tuple[str, list[_PlyElement], int]:
    """Parse a PLY header; return the format, the elements and the offset of the body."""
    if not data.startswith(b"ply"):
        raise MeshFormatError("not a PLY file: it does not start with 'ply'")
    end = data.find(b"end_header", 0, 1 << 16)
    newline = data.find(b"\n", end)
    if end < 0 or newline < 0:
        raise MeshFormatError("PLY header has no 'end_header' line within its first 64 KiB")
    fmt, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            if words[1] in {e.name for e in elements}:
                raise MeshFormatError(f"PLY header declares element '{words[1]}' twice")
            elements.append(_PlyElement(words[1], int(words[2]), ()))
        elif words[0] == "property" and elements:
            if len(words) == 3 and words[1] in _PLY_TYPES:
                prop = _PlyProperty(words[2], _PLY_TYPES[words[1]], None)
            elif (
                len(words) == 5 and words[1] == "list" and words[3] in _PLY_TYPES
                and _PLY_TYPES.get(words[2], "f")[0] in "iu"
            ):  # fmt: skip
                prop = _PlyProperty(words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]])
            else:
                raise MeshFormatError(f"PLY header line '{line}' is not a valid property")
            last = elements[-1]
            if prop.name in {q.name for q in last.properties}:
                raise MeshFormatError(
                    f"PLY element '{last.name}' declares property '{prop.name}' twice"
                )
            elements[-1] = _PlyElement(last.name, last.count, last.properties + (prop,))
        else:
            raise MeshFormatError(f"PLY header line '{line}' is not understood")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshFormatError(
            f"PLY format '{fmt}' is not ascii, binary_little_endian or binary_big_endian"
        )
    return fmt, elements, newline + 1


def _ply_binary_element(
    data: bytes, pos: int, element: _PlyElement, endian: str
) -> tuple[dict, int]:
    """Read one binary element; scalars as (N,) arrays, lists as ((N,) lengths, flat values)."""
    props, count = element.properties, element.count
    smallest = sum(np.dtype(p.count_code or p.code).itemsize for p in props)
    if count * smallest > len(data) - pos:
        raise MeshFormatError(
            f"PLY data ends inside element '{element.name}' ({count} declared)"
        )
    if not props:
        return {}, pos
    # Guess that every record has the list lengths of the first one (all triangles, say).
    layout, cursor = [], pos
    for p in props:
        if p.count_code is None:
            layout.append((p.name, endian + p.code))
            cursor += np.dtype(p.code).itemsize
            continue
        if count == 0 or cursor + np.dtype(p.count_code).itemsize > len(data):
            return _ply_binary_records(data, pos, element, endian)
        length = int(np.frombuffer(data, endian + p.count_code, 1, cursor)[0])
        cursor += np.dtype(p.count_code).itemsize + length * np.dtype(p.code).itemsize
        if length <= 0 or cursor > len(data):
            return _ply_binary_records(data, pos, element, endian)
        layout += [(p.name + "#", endian + p.count_code), (p.name, endian + p.code, (length,))]
    dtype = np.dtype(layout)
    if pos + count * dtype.itemsize > len(data):
        return _ply_binary_records(data, pos, element, endian)
    records = np.frombuffer(data, dtype, count, pos)
    out = {}
    for p in props:
        if p.count_code is None:
            out[p.name] = records[p.name]
            continue
        length = dtype[p.name].shape[0]
        if not (records[p.name + "#"] == length).all():
            return _ply_binary_records(data, pos, element, endian)
        out[p.name] = (np.full(count, length, np.int64), records[p.name].reshape(-1))
    return out, pos + count * dtype.itemsize


_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}


def _ply_binary_records(
    data: bytes, pos: int, element: _PlyElement, endian: str
) -> tuple[dict, int]:
    """Read a binary element record by record (lists of varying length)."""
    props = element.properties
    starts = {p.name: np.empty(element.count, np.int64) for p in props}
    lengths = {p.name: np.ones(element.count, np.int64) for p in props}
    sizes = {p.name: np.dtype(p.code).itemsize for p in props}
    counts = {
        p.name: struct.Struct(endian + _STRUCT_CODES[p.count_code]) for p in props if p.count_code
    }
    for i in range(element.count):
        for p in props:
            if p.count_code is not None:
                if pos + counts[p.name].size > len(data):
                    pos = len(data) + 1
                    break
                length = counts[p.name].unpack_from(data, pos)[0]
                if length < 0:
                    raise MeshFormatError(
                        f"PLY {element.name} {i} has a list '{p.name}' of length {length}"
                    )
                pos += counts[p.name].size
                lengths[p.name][i] = length
            starts[p.name][i] = pos
            pos += lengths[p.name][i] * sizes[p.name]
        if pos > len(data):
            raise MeshFormatError(
                f"PLY data ends inside {element.name} {i} of the {element.count} declared"
            )
    raw = np.frombuffer(data, np.uint8)
    out = {}
    for p in props:
        n = lengths[p.name]
        first = np.repeat(starts[p.name], n)
        item = np.arange(first.size) - np.repeat(np.cumsum(n) - n, n)
        offsets = first + item * sizes[p.name]
        values = raw[offsets[:, None] + np.arange(sizes[p.name])].view(endian + p.code).ravel()
        out[p.name] = values if p.count_code is None else (n, values)
    return out, pos


def _ply_ascii_element(lines: list[str], element: _PlyElement) -> dict:
    """Read one ASCII element from its `count` lines."""
    props = element.properties
    if all(p.count_code is None for p in props):
        split = list(map(str.split, lines))
        widths = np.fromiter(map(len, split), np.int64, len(split))
        wrong = np.flatnonzero(widths != len(props))
        if len(wrong):
            raise MeshFormatError(
                f"PLY {element.name} {wrong[0]} has {widths[wrong[0]]} values, "
                f"expected {len(props)}"
            )
        values = _ply_numbers(itertools.chain.from_iterable(split), element.name)
        values = values.reshape(len(lines), len(props))
        return {p.name: values[:, k] for k, p in enumerate(props)}
    tokens = {p.name: [] for p in props}
    lengths = {p.name: np.ones(len(lines), np.int64) for p in props}
    for i, line in enumerate(lines):
        words, k = line.split(), 0
        for p in props:
            if p.count_code is None:
                tokens[p.name].append(words[k : k + 1])
                k += 1
                continue
            length = int(words[k]) if k < len(words) and words[k].isdigit() else -1
            if length < 0 or k + 1 + length > len(words):
                raise MeshFormatError(
                    f"PLY {element.name} {i} has a malformed list '{p.name}': '{line.strip()}'"
                )
            tokens[p.name].append(words[k + 1 : k + 1 + length])
            lengths[p.name][i] = length
            k += 1 + length
        if k != len(words):
            raise MeshFormatError(
                f"PLY {element.name} {i} has {len(words)} values, its properties take {k}"
            )
    out = {}
    for p in props:
        values = _ply_numbers(itertools.chain.from_iterable(tokens[p.name]), element.name)
        out[p.name] = values if p.count_code is None else (lengths[p.name], values)
    return out


def _ply_numbers(tokens, element_name: str) -> np.ndarray:
    try:
        return np.fromiter(map(float, tokens), np.float64)
    except ValueError as error:
        raise MeshFormatError(
            f"PLY {element_name} has a value that is not a number: {error}"
        ) from None


def read_ply(
    source: Source, *, max_vertices: int = MAX_VERTICES, max_faces: int = MAX_FACES
) -> Mesh:
    """Read a PLY mesh (ASCII or binary, either endianness) without re-indexing it.

    The ``vertex`` element needs ``x, y, z``; per-vertex uv is read from ``s, t``, ``u, v`` or
    ``texture_u, texture_v``. The ``face`` element needs a list ``vertex_indices`` (or
    ``vertex_index``) of 0-based indices; polygons are fan-split. Without per-vertex uv, a face
    list ``texcoord`` (as MeshLab/VCG write: ``u, v`` of every corner in turn) is read as
    per-corner uv, one `uv` row per file corner; a face with an empty list has no uv (its
    `uv_faces` rows are -1). Other elements and properties are skipped.

    Parameters
    ----------
    source : path, bytes or binary file
    max_vertices, max_faces : int
        Bounds on the declared vertex and face counts and on the triangle count.

    Returns
    -------
    Mesh
        `uv` per vertex (no `uv_faces`), or per corner with `uv_faces` from a face
        ``texcoord`` list; `quad_split` when polygons were split.

    Raises
    ------
    MeshFormatError, SizeLimitError
    """
    data = read_source(source)
    fmt, elements, pos = _ply_header(data)
    by_name = {e.name: e for e in elements}
    if "vertex" not in by_name or "face" not in by_name:
        raise MeshFormatError("PLY file needs a 'vertex' and a 'face' element")
    if by_name["vertex"].count > max_vertices:
        raise SizeLimitError("vertices", by_name["vertex"].count, max_vertices)
    if by_name["face"].count > max_faces:
        raise SizeLimitError("faces", by_name["face"].count, max_faces)
    if fmt == "ascii":
        lines = [line for line in data[pos:].decode("ascii", "replace").split("\n") if line.strip()]
        if sum(e.count for e in elements) > len(lines):
            raise MeshFormatError(
                f"PLY header declares {sum(e.count for e in elements)} records but the file has "
                f"{len(lines)} data lines"
            )
    read = {}
    for element in elements:
        if fmt == "ascii":
            read[element.name] = _ply_ascii_element(lines[: element.count], element)
            lines = lines[element.count :]
        else:
            endian = "<" if fmt == "binary_little_endian" else ">"
            read[element.name], pos = _ply_binary_element(data, pos, element, endian)
    return _ply_mesh(read["vertex"], read["face"], by_name["vertex"].count, max_faces)


def _ply_mesh(vertex: dict, face: dict, vertex_count: int, max_faces: int) -> Mesh:
    missing = [axis for axis in "xyz" if axis not in vertex or isinstance(vertex[axis], tuple)]
    if missing:
        raise MeshFormatError(f"PLY vertex element lacks the scalar properties {missing}")
    vertices = np.stack([vertex[axis] for axis in "xyz"], axis=1).astype(np.float64)
    uv = None
    for u, v in _PLY_UV_NAMES:
        if u in vertex and v in vertex:
            uv = np.stack([vertex[u], vertex[v]], axis=1).astype(np.float64)
            break
    lists = [name for name in _PLY_FACE_LISTS if isinstance(face.get(name), tuple)]
    if not lists:
        raise MeshFormatError("PLY face element lacks a list property 'vertex_indices'")
    sizes, corners = face[lists[0]]
    short = np.flatnonzero(sizes < 3)
    if len(short):
        raise MeshFormatError(
            f"face {short[0]} has {sizes[short[0]]} corners; a face needs at least 3"
        )
    bad = np.flatnonzero((corners < 0) | (corners >= vertex_count) | (corners != np.floor(corners)))
    if len(bad):
        polygon = np.searchsorted(np.cumsum(sizes), bad[0], side="right")
        raise MeshFormatError(
            f"face {polygon} references vertex {corners[bad[0]]:g} but the file has "
            f"{vertex_count} vertices (indices are 0-based)"
        )
    uv_corners = None
    if uv is None and isinstance(face.get(_PLY_FACE_UV), tuple):  # MeshLab/VCG per-corner uv
        uv_counts, uv_values = face[_PLY_FACE_UV]
        textured = uv_counts == 2 * sizes
        wrong = np.flatnonzero(~textured & (uv_counts != 0))
        if len(wrong):
            raise MeshFormatError(
                f"PLY face {wrong[0]} has {uv_counts[wrong[0]]} {_PLY_FACE_UV} values for its "
                f"{sizes[wrong[0]]} corners; expected 2 per corner (u, v), or none"
            )
        if textured.any():
            uv = uv_values.reshape(-1, 2).astype(np.float64)
            uv_corners = np.full(len(corners), NO_UV, np.int64)  # faces without texcoord
            uv_corners[np.repeat(textured, sizes)] = np.arange(len(uv))
    return mesh_from_polygons(vertices, sizes, corners.astype(np.int64), uv, uv_corners, max_faces)


def write_ply(target: Target, mesh: Mesh, *, dtype=np.float64) -> None:
    """Write a mesh as binary little-endian PLY, polygons rebuilt from `quad_split`.

    Parameters
    ----------
    target : path or binary file
    mesh : Mesh
        Per-vertex uv is written as ``s, t``.
    dtype : np.float32 or np.float64
        ``float`` or ``double`` properties for positions and uv.

    Raises
    ------
    ValueError
        If the mesh has per-corner uv (`uv_faces`), which PLY vertex properties cannot hold;
        write OBJ or NPZ instead.
    """
    if mesh.uv_faces is not None:
        raise ValueError("PLY holds per-vertex uv only; this mesh has uv_faces (write OBJ or NPZ)")
    code = np.dtype(dtype).newbyteorder("<")
    ply_type = {np.dtype("<f4"): "float", np.dtype("<f8"): "double"}.get(code)
    if ply_type is None:
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    sizes, corners, _ = mesh.polygons()
    count_type, count_code = ("uchar", "u1") if sizes.max() <= 255 else ("int", "<i4")
    names = ["x", "y", "z"] + (["s", "t"] if mesh.uv is not None else [])
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by facesynth",
        f"element vertex {len(mesh.vertices)}",
        *(f"property {ply_type} {name}" for name in names),
        f"element face {len(sizes)}",
        f"property list {count_type} int vertex_indices",
        "end_header",
    ]
    columns = [mesh.vertices] + ([mesh.uv] if mesh.uv is not None else [])
    parts = ["\n".join(header).encode("ascii") + b"\n"]
    parts.append(np.concatenate(columns, axis=1).astype(code).tobytes())
    for start, end, first, size in size_runs(sizes):
        records = np.empty(end - start, [("n", count_code), ("i", "<i4", (size,))])
        records["n"] = size
        records["i"] = corners[first : first + (end - start) * size].reshape(-1, size)
        parts.append(records.tobytes())
    write_target(target, b"".join(parts))

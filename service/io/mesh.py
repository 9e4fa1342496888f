"""Triangle meshes in OBJ, PLY and NPZ files, with vertex order and count preserved.

A user's mesh is a correspondence: vertex ``i`` of the neutral is vertex ``i`` of every frame.
The readers here therefore never merge, split, drop or re-index vertices (unlike trimesh's
loaders). Polygons are triangulated as a fan, the split the ICT rig uses: a polygon
``(a,b,c,d,...)`` becomes the consecutive triangles ``(a,b,c), (a,c,d), ...``, and
:attr:`Mesh.quad_split` records, for every triangle, the polygon it came from, so a writer can
put the polygons back. Per-corner texture indices (OBJ ``v/vt``) are kept in
:attr:`Mesh.uv_faces`, as UV seams need them.

Readers take a path, bytes or a binary file object and bound every count before allocating
(``max_vertices``, ``max_faces``), raising :class:`~service.io.errors.SizeLimitError`; any
other malformed input raises :class:`~service.io.errors.MeshFormatError`.
"""

from __future__ import annotations

import io
import itertools
import os
import re
import struct
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Union

import numpy as np

from service.io.errors import MeshFormatError, SizeLimitError
from service.io.npz import ZIP_ERRORS, npy_header

MAX_VERTICES = 5_000_000
"""Default bound on the vertex count a reader accepts."""
MAX_FACES = 10_000_000
"""Default bound on the triangle count (after splitting polygons) a reader accepts."""

Source = Union[str, os.PathLike, bytes, bytearray, memoryview, BinaryIO]
Target = Union[str, os.PathLike, BinaryIO]


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh exactly as a file gave it; constructing one validates it.

    Attributes
    ----------
    vertices : (V,3) float64
        Positions in the file's unit (the sample actor uses mm), in file order.
    faces : (T,3) int64
        0-based vertex indices of the triangles, corners in file order.
    uv : (K,2) float64 or None
        Texture coordinates. Without `uv_faces` they are per vertex (K == V).
    uv_faces : (T,3) int64 or None
        Per-corner 0-based indices into `uv` (UV seams give a vertex several uv).
    quad_split : (T,) int64 or None
        For every triangle, the 0-based index of the file polygon it was cut from; polygons
        are numbered 0, 1, 2, ... in file order and polygon ``(a,b,c,d,...)`` with n corners
        became the n-2 consecutive triangles ``(a,b,c), (a,c,d), ...``. None when every polygon
        was a triangle (triangle t is polygon t).

    Raises
    ------
    MeshFormatError
        If the arrays have the wrong shape or dtype, an index is out of range, a coordinate is
        not finite, or `quad_split` does not describe fans of consecutive triangles.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    quad_split: np.ndarray | None = None

    def __post_init__(self):
        vertices = _float_array(self.vertices, "vertices", 3)
        faces = _index_array(self.faces, "faces", 3)
        if len(vertices) == 0:
            raise MeshFormatError("the mesh has no vertices")
        if len(faces) == 0:
            raise MeshFormatError("the mesh has no faces")
        _check_finite(vertices, "vertex")
        _check_range(faces, len(vertices), "vertex", "vertices")
        uv = uv_faces = quad_split = None
        if self.uv is not None:
            uv = _float_array(self.uv, "uv", 2)
            _check_finite(uv, "uv")
        if self.uv_faces is not None:
            if uv is None:
                raise MeshFormatError("uv_faces given without uv")
            uv_faces = _index_array(self.uv_faces, "uv_faces", 3)
            if uv_faces.shape != faces.shape:
                raise MeshFormatError(
                    f"uv_faces has shape {uv_faces.shape} but faces has shape {faces.shape}"
                )
            _check_range(uv_faces, len(uv), "uv", "uv coordinates")
        elif uv is not None and len(uv) != len(vertices):
            raise MeshFormatError(
                f"uv has {len(uv)} rows but the mesh has {len(vertices)} vertices "
                "(per-corner uv needs uv_faces)"
            )
        if self.quad_split is not None:
            quad_split = _index_array(self.quad_split, "quad_split", None)
            _check_fans(quad_split, faces, uv_faces)
        for name, value in zip(
            ("vertices", "faces", "uv", "uv_faces", "quad_split"),
            (vertices, faces, uv, uv_faces, quad_split),
        ):
            object.__setattr__(self, name, value)

    @property
    def corner_uv(self) -> np.ndarray | None:
        """(T,3) int64 index into `uv` of every triangle corner, or None without uv."""
        if self.uv is None:
            return None
        return self.faces if self.uv_faces is None else self.uv_faces

    def seam_vertices(self) -> np.ndarray:
        """Vertices whose corners use more than one uv index.

        Returns
        -------
        (S,) int64, sorted; empty without uv or without per-corner uv.
        """
        if self.uv_faces is None:
            return np.zeros(0, np.int64)
        pairs = np.unique(np.stack([self.faces.ravel(), self.uv_faces.ravel()], axis=1), axis=0)
        per_vertex = np.bincount(pairs[:, 0], minlength=len(self.vertices))
        return np.flatnonzero(per_vertex > 1)

    def polygons(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The file's polygons, rebuilt from the fans that `quad_split` records.

        Returns
        -------
        sizes : (P,) int64          corner count of every polygon, in file order
        corners : (sum(sizes),) int64
            0-based vertex index of every corner, polygon after polygon
        uv_corners : (sum(sizes),) int64 or None
            index into `uv` of every corner, or None without uv
        """
        corner_uv = self.corner_uv
        if self.quad_split is None:
            sizes = np.full(len(self.faces), 3, np.int64)
            keep = np.ones(self.faces.shape, bool)
        else:
            sizes = np.bincount(self.quad_split) + 2
            keep = np.zeros(self.faces.shape, bool)
            keep[:, 2] = True
            keep[_fan_starts(self.quad_split)] = True
        return sizes, self.faces[keep], None if corner_uv is None else corner_uv[keep]


# ---------------------------------------------------------------------------- validation


def _float_array(values, name: str, columns: int) -> np.ndarray:
    array = np.asarray(values)
    if array.dtype.kind not in "fiu":
        raise MeshFormatError(f"{name} must be real numbers, got dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] != columns:
        raise MeshFormatError(f"{name} must have shape (N,{columns}), got {array.shape}")
    return np.ascontiguousarray(array, dtype=np.float64)


def _index_array(values, name: str, columns: int | None) -> np.ndarray:
    array = np.asarray(values)
    if array.dtype.kind not in "iu":
        raise MeshFormatError(f"{name} must be integers, got dtype {array.dtype}")
    if columns is None and array.ndim != 1:
        raise MeshFormatError(f"{name} must have shape (T,), got {array.shape}")
    if columns is not None and (array.ndim != 2 or array.shape[1] != columns):
        raise MeshFormatError(
            f"{name} must have shape (T,{columns}) (triangles), got {array.shape}"
        )
    return np.ascontiguousarray(array, dtype=np.int64)


def _check_finite(values: np.ndarray, what: str) -> None:
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if len(bad):
        row = bad[0]
        raise MeshFormatError(
            f"{what} {row} has a non-finite coordinate {tuple(values[row].tolist())}"
        )


def _check_range(faces: np.ndarray, count: int, what: str, plural: str) -> None:
    bad = np.flatnonzero(((faces < 0) | (faces >= count)).any(axis=1))
    if len(bad):
        face = bad[0]
        index = faces[face][(faces[face] < 0) | (faces[face] >= count)][0]
        raise MeshFormatError(
            f"face {face} references {what} {index} but the mesh has {count} {plural} "
            "(indices are 0-based)"
        )


def _fan_starts(quad_split: np.ndarray) -> np.ndarray:
    """(T,) bool: the triangle is the first of its polygon's fan."""
    starts = np.ones(len(quad_split), bool)
    starts[1:] = quad_split[1:] != quad_split[:-1]
    return starts


def _check_fans(quad_split: np.ndarray, faces: np.ndarray, uv_faces: np.ndarray | None) -> None:
    if len(quad_split) != len(faces):
        raise MeshFormatError(
            f"quad_split has {len(quad_split)} entries but the mesh has {len(faces)} triangles"
        )
    steps = np.diff(quad_split)
    if quad_split[0] != 0 or ((steps != 0) & (steps != 1)).any():
        raise MeshFormatError(
            "quad_split must number polygons 0, 1, 2, ... along consecutive triangles"
        )
    follow = np.flatnonzero(~_fan_starts(quad_split))
    for name, corners in (("faces", faces), ("uv_faces", uv_faces)):
        if corners is None:
            continue
        broken = (corners[follow, 0] != corners[follow - 1, 0]) | (
            corners[follow, 1] != corners[follow - 1, 2]
        )
        if broken.any():
            t = follow[np.argmax(broken)]
            raise MeshFormatError(
                f"{name} triangles {t - 1} and {t} share polygon {quad_split[t]} but do not "
                "form a fan (a,b,c),(a,c,d)"
            )


# ---------------------------------------------------------------------------- polygons


def _fan(sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons given by their corner counts.

    Parameters
    ----------
    sizes : (P,) int64          corner count of every polygon, each >= 3

    Returns
    -------
    corners : (T,3) int64       position of every triangle corner in the flat corner list
    polygon : (T,) int64        source polygon of every triangle
    """
    triangles = sizes - 2
    polygon = np.repeat(np.arange(len(sizes)), triangles)
    first_corner = (np.cumsum(sizes) - sizes)[polygon]
    k = np.arange(len(polygon)) - (np.cumsum(triangles) - triangles)[polygon]
    corners = np.stack([first_corner, first_corner + k + 1, first_corner + k + 2], axis=1)
    return corners, polygon


def _mesh_from_polygons(
    vertices: np.ndarray,
    sizes: np.ndarray,
    corners: np.ndarray,
    uv: np.ndarray | None,
    uv_corners: np.ndarray | None,
    max_faces: int,
) -> Mesh:
    triangle_count = int((sizes - 2).sum())
    if triangle_count > max_faces:
        raise SizeLimitError("triangles", triangle_count, max_faces)
    fan, polygon = _fan(sizes)
    return Mesh(
        vertices=vertices,
        faces=corners[fan],
        uv=uv,
        uv_faces=None if uv_corners is None else uv_corners[fan],
        quad_split=polygon if (sizes > 3).any() else None,
    )


def _size_runs(sizes: np.ndarray):
    """Yield (first polygon, end polygon, first corner, size) of runs of equal-size polygons."""
    bounds = np.r_[0, np.flatnonzero(np.diff(sizes)) + 1, len(sizes)]
    offsets = np.cumsum(sizes) - sizes
    for start, end in zip(bounds[:-1], bounds[1:]):
        yield int(start), int(end), int(offsets[start]), int(sizes[start])


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


def _float_format(dtype) -> str:
    """printf format that round-trips values of `dtype` exactly through text."""
    dtype = np.dtype(dtype)
    if dtype == np.float32:
        return "%.9g"
    if dtype == np.float64:
        return "%r"
    raise ValueError(f"dtype must be float32 or float64, got {dtype}")


# ---------------------------------------------------------------------------- OBJ


def read_obj(
    source: Source, *, max_vertices: int = MAX_VERTICES, max_faces: int = MAX_FACES
) -> Mesh:
    """Read a Wavefront OBJ mesh without re-indexing it.

    ``v`` lines give the vertices (a 4th ``w`` or colour columns are ignored), ``vt`` the
    texture coordinates (u, v), ``f`` the polygons with corners ``v``, ``v/vt``, ``v/vt/vn`` or
    ``v//vn`` (1-based; negative indices count back from the latest ``v``/``vt``). ``vn``, groups,
    materials, lines and points are ignored.

    Parameters
    ----------
    source : path, bytes or binary file
    max_vertices, max_faces : int
        Bounds on the ``v`` line count and on the triangle count after splitting polygons.

    Returns
    -------
    Mesh
        `uv`/`uv_faces` hold the ``vt`` coordinates and per-corner indices when the faces use
        them; polygons are fan-split and recorded in `quad_split`.

    Raises
    ------
    MeshFormatError, SizeLimitError
    """
    data = _read_source(source).replace(b"\\\r\n", b" ").replace(b"\\\n", b" ")
    raw = np.frombuffer(data + b"\n\n\n", np.uint8)
    starts = np.r_[0, np.flatnonzero(raw[: len(data)] == ord("\n")) + 1]
    if np.isin(raw[starts], (ord(" "), ord("\t"))).any():  # indented lines: unindent them
        data = re.sub(rb"(?m)^[ \t]+", b"", data)
        raw = np.frombuffer(data + b"\n\n\n", np.uint8)
        starts = np.r_[0, np.flatnonzero(raw[: len(data)] == ord("\n")) + 1]
    lines = data.decode("latin-1").split("\n")
    first, second, third = raw[starts], raw[starts + 1], raw[starts + 2]
    blank = (ord(" "), ord("\t"), ord("\r"), ord("\n"))
    is_v = (first == ord("v")) & np.isin(second, blank)
    is_vt = (first == ord("v")) & (second == ord("t")) & np.isin(third, blank)
    is_f = (first == ord("f")) & np.isin(second, blank)
    v_at, vt_at, f_at = map(np.flatnonzero, (is_v, is_vt, is_f))
    v_rows = [lines[k][1:] for k in v_at.tolist()]
    vt_rows = [lines[k][2:] for k in vt_at.tolist()]
    f_rows = [lines[k][1:] for k in f_at.tolist()]
    v_lines, vt_lines, f_lines = v_at + 1, vt_at + 1, f_at + 1
    f_v_seen = np.cumsum(is_v)[f_at]
    f_vt_seen = np.cumsum(is_vt)[f_at]
    if len(v_rows) > max_vertices:
        raise SizeLimitError("vertices", len(v_rows), max_vertices)
    if len(f_rows) > max_faces:
        raise SizeLimitError("faces", len(f_rows), max_faces)
    if not v_rows:
        raise MeshFormatError("the OBJ file has no vertices ('v' lines)")
    if not f_rows:
        raise MeshFormatError("the OBJ file has no faces ('f' lines)")
    vertices = _obj_floats(v_rows, v_lines, 3, "vertex")
    _check_finite_rows(vertices, v_lines, "vertex")

    split = list(map(str.split, f_rows))
    sizes = np.fromiter(map(len, split), np.int64, len(split))
    short = np.flatnonzero(sizes < 3)
    if len(short):
        face = short[0]
        raise MeshFormatError(
            f"face {face} (line {f_lines[face]}) has {sizes[face]} corners; a face needs at least 3"
        )
    if int((sizes - 2).sum()) > max_faces:
        raise SizeLimitError("triangles", int((sizes - 2).sum()), max_faces)
    corners = list(itertools.chain.from_iterable(split))
    corner_face = np.repeat(np.arange(len(sizes)), sizes)
    v_written, vt_written = _obj_corners(corners, corner_face, f_lines)
    v_seen = f_v_seen[corner_face]
    v_index = _obj_resolve(
        v_written, v_seen, len(vertices), corner_face, f_lines, "vertex", "vertices"
    )
    uv = uv_index = None
    if vt_written is not None:
        uv = _obj_floats(vt_rows, vt_lines, 2, "texture coordinate")
        _check_finite_rows(uv, vt_lines, "texture coordinate")
        vt_seen = f_vt_seen[corner_face]
        uv_index = _obj_resolve(
            vt_written, vt_seen, len(uv), corner_face, f_lines,
            "texture coordinate", "texture coordinates",
        )  # fmt: skip
    return _mesh_from_polygons(vertices, sizes, v_index, uv, uv_index, max_faces)


def _obj_floats(rows: list[str], lines: list[int], columns: int, what: str) -> np.ndarray:
    """Parse the first `columns` numbers of every row into an (N, columns) float64 array."""
    if not rows:
        return np.zeros((0, columns))
    try:  # fast path: every row has the same count of numbers
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            values = np.loadtxt(io.StringIO("\n".join(rows)), ndmin=2, comments=None)
        if values.shape[0] == len(rows) and values.shape[1] >= columns:
            return np.ascontiguousarray(values[:, :columns])
    except ValueError:
        pass
    split = list(map(str.split, rows))
    counts = np.fromiter(map(len, split), np.int64, len(split))
    short = np.flatnonzero(counts < columns)
    if len(short):
        row = short[0]
        raise MeshFormatError(
            f"line {lines[row]}: a {what} needs {columns} numbers, got '{rows[row].strip()}'"
        )
    values = np.empty((len(rows), columns))
    for row, tokens in enumerate(split):
        try:
            values[row] = [float(token) for token in tokens[:columns]]
        except ValueError:
            raise MeshFormatError(
                f"line {lines[row]}: cannot read {what} numbers from '{rows[row].strip()}'"
            ) from None
    return values


def _check_finite_rows(values: np.ndarray, lines: list[int], what: str) -> None:
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if len(bad):
        row = bad[0]
        raise MeshFormatError(
            f"{what} {row} (line {lines[row]}) has a non-finite coordinate "
            f"{tuple(values[row].tolist())}"
        )


def _obj_corners(
    corners: list[str], corner_face: np.ndarray, f_lines: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the written (1-based or negative) v and vt indices of corners ``v[/vt[/vn]]``.

    Returns
    -------
    v : (C,) int64
    vt : (C,) int64 or None when the corners have no texture index
    """
    slashes = np.fromiter(map(str.count, corners, itertools.repeat("/")), np.int64, len(corners))
    odd = np.flatnonzero(slashes != slashes[0])
    if len(odd) or slashes[0] > 2:
        corner = odd[0] if len(odd) else 0
        face = corner_face[corner]
        raise MeshFormatError(
            f"face {face} (line {f_lines[face]}) has corner '{corners[corner]}' but the first "
            f"corner of the file is '{corners[0]}'; every corner must use the same one of the "
            "forms v, v/vt, v/vt/vn, v//vn"
        )
    text = " ".join(corners)
    without_vt = slashes[0] == 2 and text.count("//") == len(corners)
    if without_vt:
        text = text.replace("//", "/")
    width = int(slashes[0]) + 1 - without_vt
    try:
        values = np.fromstring(text.replace("/", " "), dtype=np.int64, sep=" ")
    except ValueError:  # a malformed field: the general path below names it
        values = np.zeros(0, np.int64)
    if len(values) == width * len(corners):  # fast path: no empty or malformed field
        values = values.reshape(-1, width)
        return values[:, 0], (values[:, 1] if width > 1 and not without_vt else None)
    fields = "/".join(corners).split("/")
    v = _obj_integers(fields[:: width + without_vt], corner_face, f_lines, "vertex")
    if width + without_vt == 1:
        return v, None
    vt_fields = fields[1 :: width + without_vt]
    missing = vt_fields.count("")
    if missing == len(vt_fields):
        return v, None
    if missing:
        corner = vt_fields.index("") if vt_fields[0] else next(
            k for k, field in enumerate(vt_fields) if field
        )
        face = corner_face[corner]
        raise MeshFormatError(
            f"face {face} (line {f_lines[face]}) has corner '{corners[corner]}' but the first "
            f"corner of the file is '{corners[0]}'; either every corner has a texture index "
            "or none does"
        )
    return v, _obj_integers(vt_fields, corner_face, f_lines, "texture coordinate")


def _obj_integers(
    tokens: list[str], corner_face: np.ndarray, f_lines: np.ndarray, what: str
) -> np.ndarray:
    """Parse one index per corner, naming the face and line of the first bad one."""
    for corner, token in enumerate(tokens):
        try:
            np.int64(int(token))
        except (ValueError, OverflowError):
            face = corner_face[corner]
            raise MeshFormatError(
                f"face {face} (line {f_lines[face]}) has {what} index '{token}', "
                "expected an integer"
            ) from None
    return np.fromiter(map(int, tokens), np.int64, len(tokens))


def _obj_resolve(
    written: np.ndarray,
    seen: np.ndarray,
    total: int,
    corner_face: np.ndarray,
    f_lines: np.ndarray,
    what: str,
    plural: str,
) -> np.ndarray:
    """Resolve 1-based or negative (relative) OBJ indices to 0-based ones, checking range.

    Parameters
    ----------
    written : (C,) int64  indices as written, one per corner
    seen : (C,) int64     count of elements (v or vt) defined before each corner's line
    total : int           count of elements in the file
    """
    index = np.where(written < 0, written + seen, written - 1)
    bad = np.flatnonzero((written == 0) | (index < 0) | (index >= total))
    if len(bad):
        corner = bad[0]
        face = corner_face[corner]
        if written[corner] == 0:
            detail = "OBJ indices start at 1"
        elif written[corner] > 0:
            detail = f"the file has {total} {plural}"
        else:
            detail = f"only {seen[corner]} {plural} precede that line"
        raise MeshFormatError(
            f"face {face} (line {f_lines[face]}) references {what} {written[corner]} but {detail}"
        )
    return index


def write_obj(target: Target, mesh: Mesh, *, dtype=np.float64) -> None:
    """Write a mesh as Wavefront OBJ, polygons rebuilt from `quad_split`, order preserved.

    Parameters
    ----------
    target : path or binary file
    mesh : Mesh
        With uv, every corner is written ``v/vt`` (per-vertex uv as one ``vt`` per vertex).
    dtype : np.float32 or np.float64
        Precision of the written numbers: float64 writes the shortest repr that reads back
        bit-exactly as float64; float32 writes ``%.9g`` of the values rounded to float32, which
        reads back bit-exactly once cast to float32.
    """
    number = _float_format(dtype)
    vertices = mesh.vertices.astype(dtype).ravel().tolist()
    parts = [
        f"# facesynth: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles\n",
        (f"v {number} {number} {number}\n" * len(mesh.vertices)) % tuple(vertices),
    ]
    if mesh.uv is not None:
        uv = mesh.uv.astype(dtype).ravel().tolist()
        parts.append((f"vt {number} {number}\n" * len(mesh.uv)) % tuple(uv))
    sizes, corners, uv_corners = mesh.polygons()
    for start, end, first, size in _size_runs(sizes):
        stop = first + (end - start) * size
        if uv_corners is None:
            values, corner = corners[first:stop] + 1, " %d"
        else:
            values = np.stack([corners[first:stop], uv_corners[first:stop]], axis=1) + 1
            corner = " %d/%d"
        parts.append(("f" + corner * size + "\n") * (end - start) % tuple(values.ravel().tolist()))
    _write_target(target, "".join(parts).encode("ascii"))


# ---------------------------------------------------------------------------- PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_UV_NAMES = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"))
_PLY_FACE_LISTS = ("vertex_indices", "vertex_index")


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
    ``vertex_index``) of 0-based indices; polygons are fan-split. Other elements and properties
    are skipped.

    Parameters
    ----------
    source : path, bytes or binary file
    max_vertices, max_faces : int
        Bounds on the declared vertex and face counts and on the triangle count.

    Returns
    -------
    Mesh
        `uv` per vertex (no `uv_faces`) when present; `quad_split` when polygons were split.

    Raises
    ------
    MeshFormatError, SizeLimitError
    """
    data = _read_source(source)
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
    return _mesh_from_polygons(vertices, sizes, corners.astype(np.int64), uv, None, max_faces)


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
    for start, end, first, size in _size_runs(sizes):
        records = np.empty(end - start, [("n", count_code), ("i", "<i4", (size,))])
        records["n"] = size
        records["i"] = corners[first : first + (end - start) * size].reshape(-1, size)
        parts.append(records.tobytes())
    _write_target(target, b"".join(parts))


# ---------------------------------------------------------------------------- NPZ

_NPZ_SHAPES = {
    "vertices": ("V", 3), "faces": ("T", 3), "uv": ("K", 2), "uv_faces": ("T", 3),
    "quad_split": ("T",),
}  # fmt: skip
_NPZ_KEYS = tuple(_NPZ_SHAPES)
#: keys holding coordinates: floating point only (an int8 neutral was once accepted)
_NPZ_FLOAT_KEYS = ("vertices", "uv")
_ZIP_ERRORS = ZIP_ERRORS


def read_npz(
    source: Source, *, max_vertices: int = MAX_VERTICES, max_faces: int = MAX_FACES
) -> Mesh:
    """Read a mesh from an ``.npz`` archive with API.md's keys, never unpickling.

    Keys: ``vertices`` (V,3) float (float16/32/64; integer and boolean coordinates are
    refused, not cast), ``faces`` (T,3) int, optional ``uv`` (V,2) per vertex or
    (K,2) with ``uv_faces`` (T,3) int, optional ``quad_split`` (T,) int (see :class:`Mesh`).
    Array shapes are read from the ``.npy`` headers and bounded before any data is loaded.

    Parameters
    ----------
    source : path, bytes or binary file
    max_vertices, max_faces : int
        Bounds on V and T (uv rows are bounded by max(max_vertices, 3 * max_faces)).

    Returns
    -------
    Mesh

    Raises
    ------
    MeshFormatError, SizeLimitError
    """
    data = _read_source(source)
    try:
        archive = np.load(io.BytesIO(data), allow_pickle=False)
    except _ZIP_ERRORS as error:
        raise MeshFormatError(f"not a readable .npz archive: {error}") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise MeshFormatError("expected an .npz archive of named arrays, got a single .npy array")
    with archive:
        unknown = sorted(set(archive.files) - set(_NPZ_KEYS))
        if unknown:
            raise MeshFormatError(
                f"unexpected keys {unknown} in the mesh .npz; allowed: {list(_NPZ_KEYS)}"
            )
        for key in ("vertices", "faces"):
            if key not in archive.files:
                raise MeshFormatError(f"the mesh .npz lacks the key '{key}'")
        limits = {
            "vertices": ("vertices", max_vertices),
            "faces": ("faces", max_faces),
            "uv": ("uv coordinates", max(max_vertices, 3 * max_faces)),
            "uv_faces": ("faces", max_faces),
            "quad_split": ("faces", max_faces),
        }
        for key in archive.files:
            shape, dtype = _npy_header(archive.zip, key)
            if key in _NPZ_FLOAT_KEYS and dtype.kind != "f":
                raise MeshFormatError(
                    f"'{key}' must be floating point (float32 or float64), got {dtype}; "
                    "integer or boolean coordinates are refused rather than cast"
                )
            expected = _NPZ_SHAPES[key]
            if len(shape) != len(expected) or shape[1:] != expected[1:]:
                raise MeshFormatError(
                    f"'{key}' has shape {shape}, expected ({', '.join(map(str, expected))})"
                )
            what, limit = limits[key]
            if shape[0] > limit:
                raise SizeLimitError(what, shape[0], limit)
        try:
            arrays = {key: archive[key] for key in archive.files}
        except _ZIP_ERRORS as error:
            raise MeshFormatError(f"cannot read the mesh .npz: {error}") from None
    return Mesh(**arrays)


def _npy_header(archive: zipfile.ZipFile, key: str) -> tuple[tuple[int, ...], np.dtype]:
    try:
        return npy_header(archive, key + ".npy")
    except ZIP_ERRORS as error:
        raise MeshFormatError(f"cannot read the header of '{key}' in the .npz: {error}") from None


def write_npz(target: Target, mesh: Mesh, *, dtype=np.float64, compress: bool = False) -> None:
    """Write a mesh as ``.npz`` with API.md's keys (plus ``quad_split`` when polygons were split).

    Parameters
    ----------
    target : path or binary file
    mesh : Mesh
    dtype : np.float32 or np.float64
        dtype of ``vertices`` and ``uv``; index arrays are int32 (int64 beyond 2**31 - 1).
    compress : bool
        Deflate the archive.
    """
    if np.dtype(dtype) not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    arrays = {"vertices": mesh.vertices.astype(dtype), "faces": mesh.faces}
    if mesh.uv is not None:
        arrays["uv"] = mesh.uv.astype(dtype)
    if mesh.uv_faces is not None:
        arrays["uv_faces"] = mesh.uv_faces
    if mesh.quad_split is not None:
        arrays["quad_split"] = mesh.quad_split
    for key in ("faces", "uv_faces", "quad_split"):
        if key in arrays and arrays[key].max() <= np.iinfo(np.int32).max:
            arrays[key] = arrays[key].astype(np.int32)
    buffer = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buffer, **arrays)
    _write_target(target, buffer.getvalue())


# ---------------------------------------------------------------------------- dispatch

_READERS = {".obj": read_obj, ".ply": read_ply, ".npz": read_npz}


def read_mesh(
    source: Source,
    suffix: str | None = None,
    *,
    max_vertices: int = MAX_VERTICES,
    max_faces: int = MAX_FACES,
) -> Mesh:
    """Read a mesh, choosing the reader by file suffix (``.obj``, ``.ply``, ``.npz``).

    Parameters
    ----------
    source : path, bytes or binary file
    suffix : str, optional
        e.g. ``".obj"``; taken from the path when omitted (required for bytes and streams).
    max_vertices, max_faces : int
        Passed to the reader.

    Returns
    -------
    Mesh

    Raises
    ------
    MeshFormatError
        For an unsupported or missing suffix, or malformed content.
    SizeLimitError
    """
    if suffix is None and isinstance(source, (str, os.PathLike)):
        suffix = Path(source).suffix
    reader = _READERS.get((suffix or "").lower())
    if reader is None:
        raise MeshFormatError(f"unsupported mesh file type {suffix!r}; expected .obj, .ply or .npz")
    return reader(source, max_vertices=max_vertices, max_faces=max_faces)

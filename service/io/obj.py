"""Wavefront OBJ meshes, read and written with vertex order and count preserved.

See :mod:`service.io.triangle_mesh` for what a :class:`~service.io.triangle_mesh.Mesh` keeps
(fan-split polygons in ``quad_split``, per-corner texture indices in ``uv_faces``).
"""

from __future__ import annotations

import io
import itertools
import re
import warnings

import numpy as np

from service.io.errors import MeshFormatError, SizeLimitError
from service.io.sources import Source, Target, read_source, write_target
from service.io.triangle_mesh import MAX_FACES, MAX_VERTICES, Mesh, mesh_from_polygons, size_runs


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
    data = read_source(source).replace(b"\\\r\n", b" ").replace(b"\\\n", b" ")
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
    v_written, vt_written, textured = _obj_corners(corners, corner_face, f_lines, sizes)
    v_seen = f_v_seen[corner_face]
    v_index = _obj_resolve(
        v_written, v_seen, len(vertices), corner_face, f_lines, "vertex", "vertices"
    )
    uv = uv_index = None
    if vt_written is not None:
        uv = _obj_floats(vt_rows, vt_lines, 2, "texture coordinate")
        _check_finite_rows(uv, vt_lines, "texture coordinate")
        vt_seen = f_vt_seen[corner_face]
        uv_index = np.full(len(corners), -1, np.int64)  # -1: a face written without vt
        uv_index[textured] = _obj_resolve(
            vt_written[textured], vt_seen[textured], len(uv), corner_face[textured], f_lines,
            "texture coordinate", "texture coordinates",
        )  # fmt: skip
    return mesh_from_polygons(vertices, sizes, v_index, uv, uv_index, max_faces)


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
    corners: list[str], corner_face: np.ndarray, f_lines: np.ndarray, sizes: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read the written (1-based or negative) v and vt indices of corners ``v[/vt[/vn]]``.

    Every corner of a face uses the same form (``v``, ``v/vt``, ``v/vt/vn`` or ``v//vn``), as far
    as having a texture index goes; different faces may use different forms (multi-object
    exports mix ``v/vt`` objects with bare ``v`` or ``v//vn`` ones).

    Returns
    -------
    v : (C,) int64
    vt : (C,) int64 or None
        The written texture index of every corner (meaningful where `textured`), or None when
        no corner has one.
    textured : (C,) bool   the corner has a texture index
    """
    slashes = np.fromiter(map(str.count, corners, itertools.repeat("/")), np.int64, len(corners))
    if slashes.max() > 2:
        corner = int(np.argmax(slashes > 2))
        face = corner_face[corner]
        raise MeshFormatError(
            f"face {face} (line {f_lines[face]}) has corner '{corners[corner]}'; a corner is "
            "one of v, v/vt, v/vt/vn, v//vn"
        )
    if (slashes == slashes[0]).all():
        uniform = _obj_uniform_corners(corners, corner_face, f_lines, int(slashes[0]))
        if uniform is not None:
            v, vt = uniform
            return v, vt, np.full(len(corners), vt is not None)
    fields = [corner.split("/") for corner in corners]
    v = _obj_integers([f[0] for f in fields], corner_face, f_lines, "vertex")
    textured = np.fromiter((len(f) > 1 and f[1] != "" for f in fields), bool, len(fields))
    starts = np.cumsum(sizes) - sizes
    first = np.repeat(textured[starts], sizes)
    odd = np.flatnonzero(textured != first)
    if len(odd):
        corner = odd[0]
        face = corner_face[corner]
        raise MeshFormatError(
            f"face {face} (line {f_lines[face]}) has corner '{corners[corner]}' but the first "
            f"corner of the face is '{corners[starts[face]]}'; within a face either every "
            "corner has a texture index or none does"
        )
    if not textured.any():
        return v, None, textured
    vt = np.zeros(len(corners), np.int64)
    vt[textured] = _obj_integers(
        [f[1] for f, has in zip(fields, textured.tolist()) if has], corner_face[textured],
        f_lines, "texture coordinate",
    )  # fmt: skip
    return v, vt, textured


def _obj_uniform_corners(
    corners: list[str], corner_face: np.ndarray, f_lines: np.ndarray, slashes: int
) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(v, vt or None) of corners that all have `slashes` slashes, or None when some have a
    texture index and some do not (``v//vn`` beside ``v/vt/vn``)."""
    text = " ".join(corners)
    without_vt = slashes == 2 and text.count("//") == len(corners)
    if without_vt:
        text = text.replace("//", "/")
    width = slashes + 1 - without_vt
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
        return None
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
    starts = np.cumsum(sizes) - sizes
    textured = np.zeros(len(sizes), bool) if uv_corners is None else uv_corners[starts] >= 0
    for start, end, first, size in size_runs(sizes, textured):
        stop = first + (end - start) * size
        if not textured[start]:
            values, corner = corners[first:stop] + 1, " %d"
        else:
            values = np.stack([corners[first:stop], uv_corners[first:stop]], axis=1) + 1
            corner = " %d/%d"
        parts.append(("f" + corner * size + "\n") * (end - start) % tuple(values.ravel().tolist()))
    write_target(target, "".join(parts).encode("ascii"))



def _float_format(dtype) -> str:
    """printf format that round-trips values of `dtype` exactly through text."""
    dtype = np.dtype(dtype)
    if dtype == np.float32:
        return "%.9g"
    if dtype == np.float64:
        return "%r"
    raise ValueError(f"dtype must be float32 or float64, got {dtype}")

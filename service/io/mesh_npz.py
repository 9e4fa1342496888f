"""Meshes as ``.npz`` archives with API.md's keys, read from the headers first, never unpickled.

See :mod:`service.io.triangle_mesh` for what a :class:`~service.io.triangle_mesh.Mesh` keeps.
"""

from __future__ import annotations

import io
import zipfile

import numpy as np

from service.io.arrays import check_dtype, check_shape
from service.io.errors import MeshFormatError, SizeLimitError
from service.io.npz import ZIP_ERRORS, npy_header
from service.io.sources import Source, Target, read_source, write_target
from service.io.triangle_mesh import MAX_FACES, MAX_VERTICES, Mesh


_NPZ_SHAPES = {
    "vertices": ("V", 3), "faces": ("T", 3), "uv": ("K", 2), "uv_faces": ("T", 3),
    "quad_split": ("T",),
}  # fmt: skip
_NPZ_KEYS = tuple(_NPZ_SHAPES)
_NPZ_COORDINATES = ("vertices", "uv")


def read_npz(
    source: Source, *, max_vertices: int = MAX_VERTICES, max_faces: int = MAX_FACES
) -> Mesh:
    """Read a mesh from an ``.npz`` archive with API.md's keys, never unpickling.

    Keys: ``vertices`` (V,3) float, ``faces`` (T,3) int, optional ``uv`` (V,2) per vertex or
    (K,2) with ``uv_faces`` (T,3) int, optional ``quad_split`` (T,) int (see :class:`Mesh`).
    Array shapes and dtypes are read from the ``.npy`` headers and checked before any data is
    loaded: ``vertices`` and ``uv`` must be floating point (integer coordinates, e.g. int8, are
    refused rather than cast); the index arrays are checked by :class:`Mesh`.

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
    data = read_source(source)
    try:
        archive = np.load(io.BytesIO(data), allow_pickle=False)
    except ZIP_ERRORS as error:
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
            if key in _NPZ_COORDINATES:
                check_dtype(f"'{key}'", dtype, "f", MeshFormatError,
                            " (float32 or float64); integer coordinates are refused, not cast")
            check_shape(f"'{key}'", shape, _NPZ_SHAPES[key], MeshFormatError)
            what, limit = limits[key]
            if shape[0] > limit:
                raise SizeLimitError(what, shape[0], limit)
        try:
            arrays = {key: archive[key] for key in archive.files}
        except ZIP_ERRORS as error:
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
    write_target(target, buffer.getvalue())

"""Arrays in and out: NPZ encoding (``np.savez``, never pickles), NPZ decoding
(``allow_pickle=False``), and meshes from NumPy arrays, trimesh-like objects or files.

A *mesh* argument may be

- an object with ``.vertices`` (V,3) and ``.faces`` (T,3), and optionally ``.visual.uv``
  (V,2) — e.g. a ``trimesh.Trimesh``. Load it with ``process=False`` (and
  ``maintain_order=True``): trimesh's default processing merges vertices, which breaks the
  vertex correspondence every clip relies on;
- a mapping with ``vertices``, ``faces`` and optionally ``uv``, ``uv_faces``, ... arrays;
- a path (``str`` / :class:`os.PathLike`) of an ``.obj`` or ``.npz`` file, sent as is;
- the bytes of an ``.obj`` or ``.npz`` file (told apart by the zip signature).
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["NPZ", "OBJ", "JSON", "npz_bytes", "load_npz", "mesh_arrays", "mesh_body",
           "frames_array", "is_path"]

NPZ = "application/x-npz"
OBJ = "model/obj"
JSON = "application/json"
EXR = "image/x-exr"
#: media types of marker files by suffix (they travel as multipart file parts)
MARKER_FILE_SUFFIXES = {".c3d": "application/x-c3d", ".trc": "text/x-trc", ".csv": "text/csv",
                        ".json": JSON, ".npz": NPZ}


def is_path(value: Any) -> bool:
    """Whether ``value`` names a file (``str`` or :class:`os.PathLike`)."""
    return isinstance(value, (str, os.PathLike))


def npz_bytes(**arrays: Any) -> bytes:
    """An ``.npz`` archive of ``arrays`` (``np.savez``; no object arrays, so no pickles).

    Examples
    --------
    >>> data = npz_bytes(markers=np.zeros((2, 150, 3), np.float32))
    >>> load_npz(data)["markers"].shape
    (2, 150, 3)
    """
    clean: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if value is None:
            continue
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise TypeError(f"array {name!r} has dtype object; send numeric arrays "
                            "(object arrays would need pickles)")
        clean[name] = array
    buffer = io.BytesIO()
    np.savez(buffer, **clean)
    return buffer.getvalue()


def load_npz(data: bytes) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` archive (read with ``allow_pickle=False``)."""
    with np.load(io.BytesIO(data), allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def _faces(faces: Any) -> np.ndarray:
    F = np.asarray(faces)
    if F.dtype.kind not in "iu":
        raise TypeError(f"faces must be integers, got dtype {F.dtype}")
    return F.astype(np.int32) if F.size == 0 or F.max() < 2**31 else F.astype(np.int64)


def _vertices(vertices: Any) -> np.ndarray:
    V = np.asarray(vertices)
    return V if V.dtype.kind == "f" else V.astype(np.float64)


def mesh_arrays(mesh: Any = None, *, vertices: Any = None, faces: Any = None, uv: Any = None,
                **extra: Any) -> dict[str, np.ndarray]:
    """The arrays of a mesh: ``vertices`` (V,3) float, ``faces`` (T,3) int32, ``uv`` (V,2)
    when known, and any ``extra`` arrays (e.g. ``uv_faces`` (T,3), ``region_<name>`` (V,)).

    Parameters
    ----------
    mesh : trimesh-like or mapping, optional   ``.vertices``, ``.faces``, ``.visual.uv``
    vertices, faces, uv : array_like, optional  given directly (override ``mesh``'s)
    """
    out: dict[str, Any] = {}
    if mesh is not None:
        if isinstance(mesh, Mapping):
            out.update({k: v for k, v in mesh.items() if v is not None})
        else:
            if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
                raise TypeError(f"a mesh needs .vertices and .faces, got {type(mesh).__name__}")
            out["vertices"], out["faces"] = mesh.vertices, mesh.faces
            visual_uv = getattr(getattr(mesh, "visual", None), "uv", None)
            if visual_uv is not None:
                out["uv"] = visual_uv
    for name, value in (("vertices", vertices), ("faces", faces), ("uv", uv), *extra.items()):
        if value is not None:
            out[name] = value
    if "vertices" not in out:
        raise TypeError("a mesh needs vertices (V,3)")
    out["vertices"] = _vertices(out["vertices"])
    if "faces" in out:
        out["faces"] = _faces(out["faces"])
    if "uv_faces" in out:
        out["uv_faces"] = _faces(out["uv_faces"])
    return {k: np.asarray(v) for k, v in out.items()}


def mesh_body(source: Any = None, **arrays: Any) -> tuple[bytes, str]:
    """A mesh upload's body and media type: a file's bytes as they are (``.obj``:
    ``model/obj``, ``.npz``: ``application/x-npz``), else the mesh's arrays as NPZ."""
    if is_path(source):
        path = Path(source)
        suffix = path.suffix.lower()
        if suffix not in (".obj", ".npz"):
            raise ValueError(f"{path}: a mesh file must be .obj or .npz")
        return path.read_bytes(), (OBJ if suffix == ".obj" else NPZ)
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
        return data, (NPZ if data[:2] == b"PK" else OBJ)
    return npz_bytes(**mesh_arrays(source, **arrays)), NPZ


def frames_array(frames: Any, what: str = "vertices") -> np.ndarray:
    """(F,N,3) from an (F,N,3) or one-frame (N,3) array, or a sequence of meshes (their
    ``.vertices``)."""
    if isinstance(frames, Sequence) and frames and hasattr(frames[0], "vertices"):
        frames = np.stack([np.asarray(m.vertices) for m in frames])
    elif hasattr(frames, "vertices") and not isinstance(frames, np.ndarray):
        frames = np.asarray(frames.vertices)
    array = np.asarray(frames)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or array.shape[-1] != 3:
        raise ValueError(f"{what} must be (F,N,3) or (N,3), got shape {array.shape}")
    return array if array.dtype.kind == "f" else array.astype(np.float64)

"""Triangle meshes in OBJ, PLY and NPZ files, with vertex order and count preserved.

The public mesh API in one place: the :class:`Mesh` type (:mod:`service.io.triangle_mesh`), the
per-format readers and writers (:mod:`service.io.obj`, :mod:`service.io.ply`,
:mod:`service.io.mesh_npz`) and :func:`read_mesh`, which chooses the reader by file suffix.

Readers take a path, bytes or a binary file object and bound every count before allocating
(``max_vertices``, ``max_faces``), raising :class:`~service.io.errors.SizeLimitError`; any
other malformed input raises :class:`~service.io.errors.MeshFormatError`.
"""

from __future__ import annotations

import os
from pathlib import Path

from service.io.errors import MeshFormatError
from service.io.mesh_npz import read_npz, write_npz
from service.io.obj import read_obj, write_obj
from service.io.ply import read_ply, write_ply
from service.io.sources import Source, Target
from service.io.triangle_mesh import MAX_FACES, MAX_VERTICES, Mesh

__all__ = [
    "MAX_FACES", "MAX_VERTICES", "Mesh", "Source", "Target", "read_mesh",
    "read_npz", "read_obj", "read_ply", "write_npz", "write_obj", "write_ply",
]  # fmt: skip


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

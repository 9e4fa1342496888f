"""The triangle mesh that every mesh reader returns, validated, with its polygon record.

A user's mesh is a correspondence: vertex ``i`` of the neutral is vertex ``i`` of every frame.
The readers (:mod:`service.io.obj`, :mod:`service.io.ply`, :mod:`service.io.mesh_npz`) therefore
never merge, split, drop or re-index vertices (unlike trimesh's loaders). Polygons are
triangulated as a fan, the split the ICT rig uses: a polygon ``(a,b,c,d,...)`` becomes the
consecutive triangles ``(a,b,c), (a,c,d), ...``, and :attr:`Mesh.quad_split` records, for every
triangle, the polygon it came from, so a writer can put the polygons back. Per-corner texture
indices (OBJ ``v/vt``) are kept in :attr:`Mesh.uv_faces`, as UV seams need them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.io.arrays import Axes, as_array, check_finite, check_indices
from service.io.errors import MeshFormatError, SizeLimitError

MAX_VERTICES = 5_000_000
"""Default bound on the vertex count a reader accepts."""
MAX_FACES = 10_000_000
"""Default bound on the triangle count (after splitting polygons) a reader accepts."""
NO_UV = -1
"""A `uv_faces` row of this value: the file gave that triangle no texture coordinates."""


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
        Per-corner 0-based indices into `uv` (UV seams give a vertex several uv). A row of
        :data:`NO_UV` (-1) is a triangle the file gave no texture coordinates (an OBJ object
        written with ``v`` or ``v//vn`` corners beside ``v/vt`` ones); a row is all -1 or none.
    quad_split : (T,) int64 or None
        For every triangle, the 0-based index of the file polygon it was cut from; polygons
        are numbered 0, 1, 2, ... in file order and polygon ``(a,b,c,d,...)`` with n corners
        became the n-2 consecutive triangles ``(a,b,c), (a,c,d), ...``. None when every polygon
        was a triangle (triangle t is polygon t).

    Raises
    ------
    MeshFormatError
        (checked with :mod:`service.io.arrays`, the one array dialect) If the arrays have the
        wrong shape or dtype, an index is out of range, a coordinate is
        not finite, or `quad_split` does not describe fans of consecutive triangles.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    quad_split: np.ndarray | None = None

    def __post_init__(self):
        axes, error = Axes(), MeshFormatError
        vertices = as_array(self.vertices, "vertices", ("V", 3), "fiu", np.float64, error, axes)
        faces = as_array(self.faces, "faces", ("T", 3), "iu", np.int64, error, axes)
        if len(vertices) == 0:
            raise MeshFormatError("the mesh has no vertices")
        if len(faces) == 0:
            raise MeshFormatError("the mesh has no faces")
        check_finite(vertices, "", ("vertex",), error=error)
        check_indices(faces, len(vertices), "face", "vertex", "mesh", "vertices", error)
        uv = uv_faces = quad_split = None
        if self.uv is not None:
            uv = as_array(self.uv, "uv", ("K", 2), "fiu", np.float64, error)
            check_finite(uv, "", ("uv",), error=error)
        if self.uv_faces is not None:
            if uv is None:
                raise MeshFormatError("uv_faces given without uv")
            uv_faces = as_array(self.uv_faces, "uv_faces", ("T", 3), "iu", np.int64, error, axes)
            untextured = uv_faces == NO_UV
            partial = np.flatnonzero(untextured.any(axis=1) & ~untextured.all(axis=1))
            if len(partial):
                raise MeshFormatError(
                    f"uv_faces row {partial[0]} is {uv_faces[partial[0]].tolist()}; a triangle "
                    f"has uv at every corner or none ({NO_UV} at all three)"
                )
            check_indices(uv_faces, len(uv), "face", "uv", "mesh", "uv coordinates", error,
                          skip=NO_UV)
        elif uv is not None and len(uv) != len(vertices):
            raise MeshFormatError(
                f"uv has {len(uv)} rows but the mesh has {len(vertices)} vertices "
                "(per-corner uv needs uv_faces)"
            )
        if self.quad_split is not None:
            quad_split = as_array(self.quad_split, "quad_split", ("T",), "iu", np.int64, error,
                                  axes)
            _check_fans(quad_split, faces, uv_faces)
        for name, value in zip(
            ("vertices", "faces", "uv", "uv_faces", "quad_split"),
            (vertices, faces, uv, uv_faces, quad_split),
        ):
            object.__setattr__(self, name, value)

    @property
    def corner_uv(self) -> np.ndarray | None:
        """(T,3) int64 index into `uv` of every triangle corner (-1 rows: no uv), or None."""
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
        pairs = np.stack([self.faces.ravel(), self.uv_faces.ravel()], axis=1)
        pairs = np.unique(pairs[pairs[:, 1] != NO_UV], axis=0)
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


def _fan_starts(quad_split: np.ndarray) -> np.ndarray:
    """(T,) bool: the triangle is the first of its polygon's fan."""
    starts = np.ones(len(quad_split), bool)
    starts[1:] = quad_split[1:] != quad_split[:-1]
    return starts


def _check_fans(quad_split: np.ndarray, faces: np.ndarray, uv_faces: np.ndarray | None) -> None:
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


def mesh_from_polygons(
    vertices: np.ndarray,
    sizes: np.ndarray,
    corners: np.ndarray,
    uv: np.ndarray | None,
    uv_corners: np.ndarray | None,
    max_faces: int,
) -> Mesh:
    """The fan-split :class:`Mesh` of polygons given as corner lists (the readers' last step).

    Parameters
    ----------
    vertices : (V,3) float
    sizes : (P,) int64              corner count of every polygon, each >= 3
    corners : (sum(sizes),) int64   0-based vertex index of every corner, polygon after polygon
    uv : (K,2) float or None
    uv_corners : (sum(sizes),) int64 or None   index into `uv` of every corner
    max_faces : int                 bound on the triangle count after splitting

    Raises
    ------
    MeshFormatError, SizeLimitError
    """
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


def size_runs(sizes: np.ndarray, keys: np.ndarray | None = None):
    """Yield (first polygon, end polygon, first corner, size) of runs of equal-size polygons.

    With ``keys`` ((P,) values), a run also ends where the key changes (e.g. textured or not).
    """
    change = np.diff(sizes) != 0
    if keys is not None:
        change |= np.diff(keys) != 0
    bounds = np.r_[0, np.flatnonzero(change) + 1, len(sizes)]
    offsets = np.cumsum(sizes) - sizes
    for start, end in zip(bounds[:-1], bounds[1:]):
        yield int(start), int(end), int(offsets[start]), int(sizes[start])

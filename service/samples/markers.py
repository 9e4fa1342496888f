"""Mocap marker layout of the sample actor: ~150 evenly spaced surface points on the face.

Markers avoid the eyelids and the inner lips (where real markers fall off or get
occluded), are spread by farthest-point sampling over the narrow-face region, and sit
inside triangles (triangle + barycentric), not on vertices, as real markers do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from service.geometry.closest_point import surface_points
from service.geometry.topology import edge_face_counts, vertex_face_adjacency
from service.io import markers as io_markers

EYELID_CLEARANCE_MM = 9.0    # no marker closer than this to an eye opening
INNER_LIP_CLEARANCE_MM = 4.0  # ... or to the mouth opening


@dataclass(frozen=True)
class MarkerLayout:
    """Markers as surface points of a mesh.

    Attributes
    ----------
    names : tuple[str, ...]       (M,) marker names
    triangle : (M,) int           containing triangle
    barycentric : (M,3) float     barycentric coordinates in that triangle (sum to 1)
    vertex : (M,) int             the triangle's vertex nearest the marker (thin-shell handle)
    """

    names: tuple[str, ...]
    triangle: np.ndarray
    barycentric: np.ndarray
    vertex: np.ndarray

    def positions(self, V: np.ndarray, F: np.ndarray) -> np.ndarray:
        """Marker positions (…,M,3) on a surface with vertices V (…,n,3) and faces F."""
        return surface_points(V, F, self.triangle, self.barycentric)

    def to_layout(self) -> io_markers.MarkerLayout:
        """The API.md marker layout (every marker in triangle + barycentric form)."""
        M = len(self.names)
        return io_markers.MarkerLayout(
            names=tuple(self.names), kinds=("triangle",) * M, vertex=np.full(M, -1),
            triangle=np.asarray(self.triangle, np.int64),
            barycentric=np.asarray(self.barycentric, np.float64),
            position=np.full((M, 3), np.nan))


def hole_loops(V: np.ndarray, F: np.ndarray) -> list[np.ndarray]:
    """Boundary loops of the mesh as vertex index arrays, largest first."""
    E, count = edge_face_counts(F)
    bnd = E[count == 1]
    verts = np.unique(bnd)
    local = np.searchsorted(verts, bnd)
    G = sp.coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(len(verts),) * 2)
    k, label = connected_components(G, directed=False)
    loops = [verts[label == i] for i in range(k)]
    return sorted(loops, key=len, reverse=True)


def place_markers(
    V: np.ndarray,
    F: np.ndarray,
    candidates: np.ndarray,
    eye_landmarks: np.ndarray,
    mouth_landmarks: np.ndarray,
    count: int = 150,
    seed: int = 0,
) -> MarkerLayout:
    """Spread ``count`` markers over ``candidates`` by farthest-point sampling.

    Parameters
    ----------
    V : (n,3) float               neutral positions, mm
    F : (m,3) int
    candidates : (n,) bool        vertices that may carry a marker (e.g. the narrow face)
    eye_landmarks, mouth_landmarks : (k,3) float
        points on the eye and mouth openings; the boundary loop nearest each set is the
        opening kept clear (EYELID_CLEARANCE_MM, INNER_LIP_CLEARANCE_MM)
    """
    rng = np.random.default_rng([seed, 0x3A])
    allowed = np.asarray(candidates, dtype=bool).copy()
    loops = hole_loops(V, F)
    loop_tree = [cKDTree(V[loop]) for loop in loops]
    for points, clearance in ((eye_landmarks, EYELID_CLEARANCE_MM),
                              (mouth_landmarks, INNER_LIP_CLEARANCE_MM)):
        for p in np.atleast_2d(points):
            nearest = int(np.argmin([t.query(p)[0] for t in loop_tree]))
            d, _ = loop_tree[nearest].query(V)
            allowed &= d > clearance
    pool = np.flatnonzero(allowed)
    if len(pool) < count:
        raise ValueError(f"only {len(pool)} candidate vertices for {count} markers")

    # farthest-point sampling, seeded start
    chosen = [int(rng.integers(len(pool)))]
    dist = np.linalg.norm(V[pool] - V[pool[chosen[0]]], axis=1)
    for _ in range(count - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(V[pool] - V[pool[nxt]], axis=1))
    vertex = pool[np.array(chosen)]

    # a point inside one incident triangle, near the chosen vertex
    VF = vertex_face_adjacency(F, len(V)).tocsr()
    triangle = np.array([rng.choice(VF.indices[VF.indptr[v]:VF.indptr[v + 1]]) for v in vertex])
    weights = rng.dirichlet([1.0, 1.0, 1.0], size=count) * 0.5
    corner = np.argmax(F[triangle] == vertex[:, None], axis=1)
    weights[np.arange(count), corner] += 0.5
    # order markers top-to-bottom, then left-to-right, so names read like a layout sheet
    pos = surface_points(V, F, triangle, weights)
    order = np.lexsort((pos[:, 0], -np.round(pos[:, 1] / 10.0)))
    names = tuple(f"M{i:03d}" for i in range(count))
    nearest_corner = F[triangle[order], np.argmax(weights[order], axis=1)]
    return MarkerLayout(names=names, triangle=triangle[order], barycentric=weights[order],
                        vertex=nearest_corner)

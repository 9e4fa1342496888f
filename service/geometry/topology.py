"""Mesh connectivity: edges, adjacency and k-ring neighbourhoods of a triangle mesh.

All functions take ``F`` (m,3) int triangles and the vertex count ``n``; none of them
re-indexes vertices.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def halfedges(F: np.ndarray) -> np.ndarray:
    """Directed half-edges of every triangle corner.

    Parameters
    ----------
    F : (m,3) int   triangles

    Returns
    -------
    H : (m,3,2) int  ``H[f, k] = (F[f,k+1], F[f,k+2])``, the edge opposite corner k
    """
    F = np.asarray(F)
    return np.stack([np.roll(F, -1, axis=1), np.roll(F, -2, axis=1)], axis=2)


def edges(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges and, per triangle corner, the index of its opposite edge.

    Returns
    -------
    E : (e,2) int           edges with ``E[:,0] < E[:,1]``, sorted lexicographically
    corner_edge : (m,3) int  ``E[corner_edge[f,k]]`` is the edge opposite corner k of face f
    """
    H = halfedges(F).reshape(-1, 2)
    Hs = np.sort(H, axis=1).astype(np.int64)
    # one int64 key per edge sorts like the (lo, hi) pairs and is far faster to unique
    n = int(Hs.max()) + 1 if len(Hs) else 1
    keys, inverse = np.unique(Hs[:, 0] * n + Hs[:, 1], return_inverse=True)
    E = np.stack([keys // n, keys % n], axis=1)
    return E, inverse.reshape(-1, 3)


def edge_face_counts(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges and how many triangles share each (1 on the boundary, 2 inside).

    Returns
    -------
    E : (e,2) int
    count : (e,) int
    """
    E, corner_edge = edges(F)
    return E, np.bincount(corner_edge.ravel(), minlength=len(E))


def boundary_vertices(F: np.ndarray, n: int) -> np.ndarray:
    """Boolean mask (n,) of vertices on a boundary edge (an edge used by one triangle)."""
    E, count = edge_face_counts(F)
    mask = np.zeros(n, dtype=bool)
    mask[E[count == 1].ravel()] = True
    return mask


def adjacency_matrix(F: np.ndarray, n: int) -> sp.csr_matrix:
    """Symmetric (n,n) 0/1 vertex adjacency matrix in CSR form."""
    E, _ = edges(F)
    data = np.ones(2 * len(E), dtype=np.int8)
    A = sp.coo_matrix(
        (data, (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(n, n)
    ).tocsr()
    A.data[:] = 1
    return A


def vertex_face_adjacency(F: np.ndarray, n: int) -> sp.csr_matrix:
    """Sparse (n,m) incidence: entry (i,f) is 1 when vertex i is a corner of triangle f."""
    m = len(F)
    rows = np.asarray(F).ravel()
    cols = np.repeat(np.arange(m), 3)
    return sp.csr_matrix((np.ones(3 * m, dtype=np.int8), (rows, cols)), shape=(n, m))


def k_ring(F: np.ndarray, n: int, seeds: np.ndarray, k: int) -> np.ndarray:
    """Vertices within ``k`` edges of any seed vertex (the seeds included).

    Parameters
    ----------
    F : (m,3) int
    n : int              vertex count
    seeds : (s,) int     seed vertex indices
    k : int              ring depth, ``k >= 0``

    Returns
    -------
    ring : (r,) int      sorted vertex indices
    """
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")
    A = adjacency_matrix(F, n)
    reached = np.zeros(n, dtype=bool)
    reached[np.asarray(seeds, dtype=np.int64)] = True
    for _ in range(k):
        reached |= (A @ reached.astype(np.int8)) > 0
    return np.flatnonzero(reached)


def k_ring_matrix(F: np.ndarray, n: int, k: int) -> sp.csr_matrix:
    """Sparse (n,n) boolean matrix whose row i marks the k-ring of vertex i (i included)."""
    A = adjacency_matrix(F, n).astype(np.int32) + sp.identity(n, dtype=np.int32, format="csr")
    R = sp.identity(n, dtype=np.int32, format="csr")
    for _ in range(k):
        R = R @ A
        R.data[:] = 1
    return R.astype(bool)

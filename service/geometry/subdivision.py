"""Triangle-mesh subdivision as a sparse linear operator, carrying UVs.

Each pass splits every triangle 1→4. The original vertices keep their indices ``[0, n)``;
one new vertex per edge follows, in the order of :func:`service.geometry.topology.edges`.
Because the result is a linear operator ``S`` (n',n), any per-vertex quantity of the
coarse mesh (blendshape deltas, identity modes, colours) is subdivided as ``S @ X``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from service.geometry.topology import adjacency_matrix, edges


@dataclass(frozen=True)
class Subdivision:
    """Result of :func:`subdivide`.

    Attributes
    ----------
    S : (n',n) sparse CSR     fine vertices = ``S @ coarse vertices``
    faces : (4^k m,3) int     fine triangles
    S_uv : (K',K) sparse CSR | None   fine UVs = ``S_uv @ coarse UVs`` (always linear)
    uv_faces : (4^k m,3) int | None   fine per-corner UV indices
    """

    S: sp.csr_matrix
    faces: np.ndarray
    S_uv: sp.csr_matrix | None = None
    uv_faces: np.ndarray | None = None


def _split_faces(F: np.ndarray, corner_edge: np.ndarray, n: int) -> np.ndarray:
    """1→4 split of (m,3) triangles; edge e becomes new vertex ``n + e``."""
    a, b, c = F[:, 0], F[:, 1], F[:, 2]
    m_bc, m_ca, m_ab = (n + corner_edge[:, k] for k in range(3))
    return np.concatenate([
        np.stack([a, m_ab, m_ca], axis=1),
        np.stack([m_ab, b, m_bc], axis=1),
        np.stack([m_ca, m_bc, c], axis=1),
        np.stack([m_ab, m_bc, m_ca], axis=1),
    ]).astype(np.int64)


def _midpoint_operator(E: np.ndarray, n: int) -> sp.csr_matrix:
    """(n+e, n) operator: identity on old vertices, edge midpoints for new ones."""
    e = len(E)
    rows = np.r_[np.arange(n), np.repeat(n + np.arange(e), 2)]
    cols = np.r_[np.arange(n), E.ravel()]
    vals = np.r_[np.ones(n), np.full(2 * e, 0.5)]
    return sp.csr_matrix((vals, (rows, cols)), shape=(n + e, n))


def _loop_operator(F: np.ndarray, E: np.ndarray, corner_edge: np.ndarray, n: int) -> sp.csr_matrix:
    """(n+e, n) Loop (1987) subdivision operator with the standard boundary rules.

    Odd vertex on an interior edge ab with opposite vertices c, d: 3/8 (a+b) + 1/8 (c+d);
    on a boundary edge: (a+b)/2. Even interior vertex of valence k:
    (1 - kβ) v + β Σ neighbours, β = (5/8 - (3/8 + ¼ cos(2π/k))²) / k (Loop's weights);
    even boundary vertex: ¾ v + ⅛ (its two boundary neighbours).
    """
    e = len(E)
    # the vertex opposite each edge, seen from each triangle that uses it
    opp_edge = corner_edge.ravel()
    opp_vert = F.ravel()
    count = np.bincount(opp_edge, minlength=e)
    interior_edge = count == 2

    rows, cols, vals = [], [], []
    # odd vertices
    w_end = np.where(interior_edge, 3 / 8, 1 / 2)
    rows += [n + np.arange(e), n + np.arange(e)]
    cols += [E[:, 0], E[:, 1]]
    vals += [w_end, w_end]
    inner = interior_edge[opp_edge]
    rows.append(n + opp_edge[inner])
    cols.append(opp_vert[inner])
    vals.append(np.full(inner.sum(), 1 / 8))

    # even vertices
    A = adjacency_matrix(F, n)
    valence = np.asarray(A.sum(axis=1)).ravel()
    bnd_edges = E[~interior_edge]
    on_boundary = np.zeros(n, dtype=bool)
    on_boundary[bnd_edges.ravel()] = True
    k = np.maximum(valence, 1)
    beta = (5 / 8 - (3 / 8 + 0.25 * np.cos(2 * np.pi / k)) ** 2) / k
    Ai = A.tocoo()
    interior_rows = ~on_boundary[Ai.row]
    rows.append(Ai.row[interior_rows])
    cols.append(Ai.col[interior_rows])
    vals.append(beta[Ai.row[interior_rows]])
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    vals.append(np.where(on_boundary, 3 / 4, 1 - valence * beta))
    rows += [bnd_edges[:, 0], bnd_edges[:, 1]]
    cols += [bnd_edges[:, 1], bnd_edges[:, 0]]
    vals += [np.full(len(bnd_edges), 1 / 8)] * 2

    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n + e, n)
    )


def subdivide(
    F: np.ndarray,
    n: int,
    uv_faces: np.ndarray | None = None,
    n_uv: int | None = None,
    iterations: int = 1,
    scheme: str = "loop",
) -> Subdivision:
    """Subdivide a triangle mesh ``iterations`` times, as linear operators.

    Parameters
    ----------
    F : (m,3) int          triangles over ``n`` vertices
    uv_faces : (m,3) int   per-corner UV indices into ``n_uv`` UV coordinates (optional)
    scheme : ``"loop"`` (smooth, Loop 1987) or ``"midpoint"`` (linear 1→4 split)

    Returns
    -------
    Subdivision
        ``S`` maps coarse to fine positions; UVs always use the midpoint rule (UV layouts
        are piecewise linear charts, and seams are kept because UVs are per corner).

    Notes
    -----
    Original vertices keep indices ``[0, n)`` at every level, so a fine mesh's first n
    vertices correspond to the coarse vertices (displaced by Loop's even rule).
    """
    if scheme not in ("loop", "midpoint"):
        raise ValueError(f"scheme must be 'loop' or 'midpoint', got {scheme!r}")
    F = np.asarray(F, dtype=np.int64)
    S = sp.identity(n, format="csr")
    S_uv = sp.identity(n_uv, format="csr") if uv_faces is not None else None
    UF = None if uv_faces is None else np.asarray(uv_faces, dtype=np.int64)
    for _ in range(iterations):
        E, corner_edge = edges(F)
        step = (_loop_operator(F, E, corner_edge, n) if scheme == "loop"
                else _midpoint_operator(E, n))
        S = (step @ S).tocsr()
        if UF is not None:
            E_uv, corner_edge_uv = edges(UF)
            k = S_uv.shape[0]
            S_uv = (_midpoint_operator(E_uv, k) @ S_uv).tocsr()
            UF = _split_faces(UF, corner_edge_uv, k)
        F = _split_faces(F, corner_edge, n)
        n = S.shape[0]
    return Subdivision(S=S, faces=F, S_uv=S_uv, uv_faces=UF)

"""Discrete Laplace-Beltrami operators and mass matrices.

Sign convention (libigl's): ``L`` is negative semi-definite, ``(L x)_i = Σ_j w_ij (x_j - x_i)``,
so ``-L`` is the stiffness matrix and ``M⁻¹ L`` approximates the Laplace-Beltrami operator Δ.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from service.geometry.topology import adjacency_matrix


def triangle_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Areas (m,) of the triangles ``F`` over vertices ``V`` (n,3), in squared units of V."""
    V = np.asarray(V, dtype=np.float64)
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)


def cotangents(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Cotangent of the interior angle at every triangle corner.

    Returns
    -------
    C : (m,3) float  ``C[f,k] = cot`` of the angle at corner ``F[f,k]``
    """
    V = np.asarray(V, dtype=np.float64)
    P = V[F]                                   # (m,3,3) corner positions
    a = np.roll(P, -1, axis=1) - P             # to the next corner
    b = np.roll(P, -2, axis=1) - P             # to the previous corner
    dot = np.einsum("fkd,fkd->fk", a, b)
    cross = np.linalg.norm(np.cross(a, b), axis=2)
    return dot / np.maximum(cross, np.finfo(np.float64).tiny)


def cotangent_laplacian(V: np.ndarray, F: np.ndarray) -> sp.csr_matrix:
    """Cotangent Laplacian (Pinkall & Polthier 1993; Meyer et al. 2003 [MDSB03]).

    ``L_ij = ½ (cot α_ij + cot β_ij)`` for an edge ij, ``L_ii = -Σ_j L_ij``.

    Parameters
    ----------
    V : (n,3) float
    F : (m,3) int

    Returns
    -------
    L : (n,n) sparse CSR, symmetric, negative semi-definite, rows sum to zero
    """
    n = len(V)
    C = cotangents(V, F)
    i = np.roll(F, -1, axis=1).ravel()         # the edge opposite corner k
    j = np.roll(F, -2, axis=1).ravel()
    w = 0.5 * C.ravel()
    L = sp.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    L = L - sp.diags(np.asarray(L.sum(axis=1)).ravel())
    return L.tocsr()


def mass_matrix(V: np.ndarray, F: np.ndarray, kind: str = "barycentric") -> sp.dia_matrix:
    """Lumped (diagonal) mass matrix.

    Parameters
    ----------
    kind : ``"barycentric"`` (a third of each incident triangle's area) or ``"voronoi"``
        (mixed Voronoi areas of Meyer et al. 2003, robust to obtuse triangles).

    Returns
    -------
    M : (n,n) sparse diagonal, entries in squared units of V
    """
    n = len(V)
    A = triangle_areas(V, F)
    if kind == "barycentric":
        corner = np.repeat(A[:, None] / 3.0, 3, axis=1)
    elif kind == "voronoi":
        corner = _mixed_voronoi_corner_areas(V, F, A)
    else:
        raise ValueError(f"kind must be 'barycentric' or 'voronoi', got {kind!r}")
    m = np.bincount(F.ravel(), weights=corner.ravel(), minlength=n)
    return sp.diags(m)


def _mixed_voronoi_corner_areas(V: np.ndarray, F: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Per-corner mixed Voronoi areas (m,3) of Meyer et al. 2003, Fig. 4."""
    V = np.asarray(V, dtype=np.float64)
    C = cotangents(V, F)
    P = V[F]
    # squared length of the edge opposite each corner
    opp = np.roll(P, -1, axis=1) - np.roll(P, -2, axis=1)
    l2 = np.einsum("fkd,fkd->fk", opp, opp)
    # Voronoi area at corner k: (|e_{k,k+1}|² cot(k+2) + |e_{k,k+2}|² cot(k+1)) / 8,
    # and the edge (k,k+1) is the one opposite corner k+2
    lc = l2 * C
    voronoi = (np.roll(lc, -2, axis=1) + np.roll(lc, -1, axis=1)) / 8.0
    obtuse = C < 0
    any_obtuse = obtuse.any(axis=1, keepdims=True)
    return np.where(any_obtuse, np.where(obtuse, A[:, None] / 2, A[:, None] / 4), voronoi)


def uniform_laplacian(F: np.ndarray, n: int) -> sp.csr_matrix:
    """Uniform (graph) Laplacian ``L_ij = 1`` for neighbours, ``L_ii = -deg(i)``.

    Returns
    -------
    L : (n,n) sparse CSR, negative semi-definite
    """
    A = adjacency_matrix(F, n).astype(np.float64)
    return (A - sp.diags(np.asarray(A.sum(axis=1)).ravel())).tocsr()

"""Locally weighted linear regression of the vertex offsets from the shell on the markers'
displacements: the part of bickel2008's fine-scale correction (§3, §5.2) that is linear in
the marker motion, learned before the RBFs.

bickel2008 §5.2 interpolates the corrections with RBFs of the strain features, and
:mod:`.polynomial` adds the biharmonic spline's linear term in those features. Strains are
rotation invariant scalars: they cannot say in which direction the skin between the
markers bulges, and a medium-scale shape the thin shell misses (a lip roll, a cheek bulge,
2–6 mm across: inside the detail metric's high-pass) is carried between poses only through
the RBF cone of a few example poses. Its magnitude is close to linear in the nearby
markers' displacement vectors (a blend-shape rig is exactly linear; measured, family a
level 0: the smooth offset ``M − X`` of the held-out amplified performance is reproduced
by a global linear regression on the markers to a high-passed relative error of 0.005,
while the nearest training frame's offset re-posed on the held-out shell leaves 0.45 and
the whole correction of WPSD 0.70).

Per vertex v a ridge regression, local by Gaussian weights over the markers' rest
distances (the locally weighted regression of [Cleveland & Devlin 1988], in the features
rather than the samples):

    y_v(u) = ȳ_v + Σ_m B_v,m (u_m − ū_m)        (3,), u_m the handle displacement of marker m,

a ridge regression in the scaled features φ_v(u) = (g_v,m (u_m − ū_m))_m, with
g_v,m² = exp(−‖x_v − r_m‖² / s²) (x_v, r_m rest vertex and marker, s = ``radius``), zero
below ``cutoff``. Solved in dual form over the T training frames: the kernel
K_v = Σ_m g_v,m² U_m U_mᵀ (T,T) (U_m (T,3) the centred training displacements of marker m),
A_v = (K_v + λ tr(K_v)/T · I)⁻¹ (Y_v − ȳ_v) (T,3) and B_v,m = g_v,m² U_mᵀ A_v (3,3).
Stored as one CSR matrix (3n, 3M) and the means, so evaluation is one sparse product per
frame: ``y = ȳ + L (u − ū)``.

Anchored (``anchor`` y₀ given): the regression passes through the rest pose instead of the
training means, ū = 0 and ȳ = y₀ (the offsets of the neutral), and the ridge regression of
Y − y₀ on the uncentred u: the neutral is reproduced exactly, whatever the training frames'
mean (the PDM's medium band, :mod:`service.methods.pdm.model`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

#: vertices per chunk of the per-vertex solves (bounds the (c,T,T) kernels)
CHUNK = 256


@dataclass(frozen=True)
class MarkerRegression:
    """``y = mean_y + L (u − mean_u)``: L (3n,3M) CSR float32 (row 3v + i, column 3m + j),
    mean_u (M,3), mean_y (n,3) float32, mm."""

    L: sp.csr_matrix
    mean_u: np.ndarray
    mean_y: np.ndarray

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Offsets (F,n,3) float32 for handle displacements u (F,M,3)."""
        du = (np.asarray(u, np.float64) - self.mean_u).reshape(len(u), -1).T.astype(np.float32)
        return (self.L @ du).T.reshape(len(u), -1, 3) + self.mean_y


def marker_spacing(marker_rest: np.ndarray) -> float:
    """Median distance (mm) from each rest marker (M,3) to its nearest neighbour."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(marker_rest).query(marker_rest, k=2)
    return float(np.median(d[:, 1]))


def marker_weights(vertices: np.ndarray, marker_rest: np.ndarray, radius: float,
                   cutoff: float) -> sp.csr_matrix:
    """(n,M) CSR of g² = exp(−d²/s²), d the rest distance vertex–marker, s = ``radius`` (mm),
    entries below ``cutoff`` dropped."""
    d2 = ((vertices[:, None, :] - marker_rest[None]) ** 2).sum(-1)
    g2 = np.exp(-d2 / radius ** 2)
    g2[g2 < cutoff] = 0.0
    return sp.csr_matrix(g2)


def fit(u: np.ndarray, Y: np.ndarray, vertices: np.ndarray, marker_rest: np.ndarray,
        radius: float, ridge: float, cutoff: float = 1e-3,
        anchor: np.ndarray | None = None) -> MarkerRegression:
    """Fit the regression (module docstring).

    Parameters
    ----------
    u : (T,M,3) float        training handle displacements, mm
    Y : (T,n,3) float        training vertex offsets (head pose removed), mm
    vertices : (n,3)         rest vertices;  marker_rest (M,3) rest markers, mm
    radius : float           s, mm;  ridge: λ (relative to tr(K_v)/T);  cutoff: g² dropped below
    anchor : (n,3) | None    y₀, the offsets at u = 0 the fit passes through (None: the means)
    """
    T, M = u.shape[:2]
    n = Y.shape[1]
    mean_u = u.mean(axis=0) if anchor is None else np.zeros(u.shape[1:])
    U = (u - mean_u).astype(np.float64)                                    # (T,M,3)
    G = np.einsum("tmc,smc->mts", U, U).reshape(M, T * T)                  # U_m U_mᵀ
    W = marker_weights(vertices, marker_rest, radius, cutoff)
    mean_y = Y.mean(axis=0) if anchor is None else np.asarray(anchor, np.float64)
    blocks = []
    diag = np.arange(T)
    Uf = U.reshape(T, M * 3)
    for v0 in range(0, n, CHUNK):
        vs = slice(v0, min(v0 + CHUNK, n))
        g2 = W[vs].toarray()                                               # (c,M)
        c = len(g2)
        K = (g2 @ G).reshape(c, T, T)
        scale = ridge * np.maximum(np.einsum("vtt->v", K) / T, 1e-30)
        K[:, diag, diag] += scale[:, None]
        A = _spd_solve(K, (Y[:, vs] - mean_y[vs]).transpose(1, 0, 2))      # (c,T,3)
        # B_v,m = g²_v,m A_vᵀ U_m: rows (v, out i), columns (m, in j)
        B = (A.transpose(0, 2, 1).reshape(c * 3, T) @ Uf).reshape(c, 3, M, 3) * g2[:, None, :, None]
        blocks.append(sp.csr_matrix(B.reshape(c * 3, M * 3).astype(np.float32)))
    L = sp.vstack(blocks, format="csr")
    return MarkerRegression(L, mean_u, mean_y.astype(np.float32))


def _spd_solve(K: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A (c,T,k) with K_i A_i = B_i for symmetric positive definite K (c,T,T): one Cholesky
    factorization each. (NumPy's stacked ``solve`` runs an LU per matrix ~10× slower at
    T = 120: 0.40 s against 0.04 s CPU for 256 matrices; measured agreement 6e-15.)"""
    from scipy.linalg import cho_factor, cho_solve

    return np.stack([cho_solve(cho_factor(k, lower=True, check_finite=False), b, check_finite=False)
                     for k, b in zip(K, B)])

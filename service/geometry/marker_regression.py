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
Kept in low-rank form, ``L ≈ P Q`` with ``Q = V_rᵀ`` the leading right singular vectors of
L (the eigenvectors of LᵀL, (3M,3M)) and ``P = L V_r``, so evaluation is two dense products
per frame, ``y = ȳ + P (Q (u − ū))``. For any input the truncation adds at most
σ_{r+1} ‖u − ū‖ (σ L's singular values); r keeps every σ above ``RANK_TOL`` σ₁. L is
neither sparse nor low-rank in the usual sense (at s = 4 marker spacings a vertex reaches
85 % of the markers, and σ decays slowly: σ_r/σ₁ = 0.11, 0.024, 0.011, 0.004 at r = 32, 96,
160, 256 of 450; family a level 0, the PDM's ``medium_regression``), but the tail carries
little: measured on the held-out performances of family a level 0 (6 frames each, PDM mesh
against the full L), RANK_TOL = 1e-2 (r = 160) moves the vertices by a mean 0.002–0.004 mm,
max 0.07–0.09 mm (r = 96: 0.010–0.021 / 0.25–0.59; r = 128: 0.004–0.006 / 0.15–0.21);
confirmed on family b (the same tol keeps r ≈ 100 of 354: ≤ 0.0015 mm mean, ≤ 0.09 max);
against a CSR of nnz 12.9 M (85 % of 3n × 3M, 8 bytes each) a frame reads P's 3n × r
entries as int16 (quantized per column, :class:`MarkerRegression`): 10 MB instead of 103 MB.
A projection on the training inputs' principal directions instead (their span is
16-dimensional there) fails on the held-out in-range and combination performances (mean
0.06–0.08, max 1.8–2.3 mm at r = 32–120): the local regression answers inputs outside the
training frames' span, which is what it is for.

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


#: the stored fields, in the constructor's order (:meth:`MarkerRegression.arrays`)
MEMBERS = ("Pq", "scale", "Q", "mean_u", "mean_y")
#: singular values of L kept: those above RANK_TOL × the largest (module docstring)
RANK_TOL = 1e-2
#: largest |int16| a quantized column reaches
INT16_MAX = int(np.iinfo(np.int16).max)


@dataclass(frozen=True)
class MarkerRegression:
    """``y = mean_y + P Q (u − mean_u)`` with ``P = Pq diag(scale)``: Pq (3n,r) int16 (row
    3v + i), scale (r,) float32 per column, Q (r,3M) float32 (column 3m + j, orthonormal
    rows), mean_u (M,3), mean_y (n,3) float32, mm.

    P is quantized per column (``scale = max |P[:,k]| / 32767``, each entry within half a
    step: 1.5e-5 of its column's largest) so a frame reads 2 bytes per entry
    (:mod:`.int16_rows`)."""

    Pq: np.ndarray
    scale: np.ndarray
    Q: np.ndarray
    mean_u: np.ndarray
    mean_y: np.ndarray

    @classmethod
    def from_factors(cls, P: np.ndarray, Q: np.ndarray, mean_u: np.ndarray, mean_y: np.ndarray) -> "MarkerRegression":
        """The regression of factors P (3n,r) float and Q (r,3M), P quantized per column."""
        P = np.asarray(P, np.float64)
        top = np.abs(P).max(axis=0) if len(P) else np.zeros(P.shape[1])
        scale = np.where(top > 0, top / INT16_MAX, 1.0)
        return cls(np.rint(P / scale).astype(np.int16), scale.astype(np.float32),
                   np.ascontiguousarray(Q, np.float32), np.asarray(mean_u, np.float64),
                   np.asarray(mean_y, np.float32))

    @classmethod
    def from_matrix(cls, L, mean_u: np.ndarray, mean_y: np.ndarray, tol: float = RANK_TOL) -> "MarkerRegression":
        """The regression of a full matrix L (3n,3M) (dense or sparse), truncated at ``tol``
        (σ_k > tol σ₁ kept; 0 keeps every σ above 1e-6 σ₁, L's float32 rounding: L reproduced
        up to P's quantization)."""
        L = L.tocsr() if sp.issparse(L) else np.asarray(L)

        def row_blocks():                       # float64 rows of L, a block at a time
            for r0 in range(0, L.shape[0], 4096):
                B = L[r0:r0 + 4096]
                yield r0, np.asarray(B.toarray() if sp.issparse(B) else B, np.float64)

        G = np.zeros((L.shape[1], L.shape[1]))
        for _, B in row_blocks():
            G += B.T @ B
        w, V = np.linalg.eigh(G)                        # ascending
        V = V[:, ::-1][:, w[::-1] > max(tol, 1e-6) ** 2 * max(w[-1], 1e-300)]   # σ ≤ 1e-6 σ₁: rounding
        P = np.empty((L.shape[0], V.shape[1]))
        for r0, B in row_blocks():
            P[r0:r0 + len(B)] = B @ V
        return cls.from_factors(P, V.T, mean_u, mean_y)

    @property
    def rank(self) -> int:
        return len(self.Q)

    @property
    def P(self) -> np.ndarray:
        """(3n,r) float32 ``Pq diag(scale)``."""
        return self.Pq * self.scale

    @property
    def L(self) -> np.ndarray:
        """The full (3n,3M) float32 matrix P Q."""
        return self.P @ self.Q

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Offsets (F,n,3) float32 for handle displacements u (F,M,3)."""
        from service.geometry import ranges
        from service.geometry.int16_rows import row_products      # Numba: loaded on first use

        du = (np.asarray(u, np.float64) - self.mean_u).reshape(len(u), -1).astype(np.float32)
        z = np.ascontiguousarray((du @ self.Q.T) * self.scale, np.float32)     # (F,r), scale folded in
        y = np.empty((len(u), len(self.Pq)), np.float32)
        for f in range(len(u)):
            ranges.run(row_products, len(self.Pq), self.Pq, z[f], y[f])
        return y.reshape(len(u), -1, 3) + self.mean_y

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The model-file members ``PREFIX_Pq``, ``_scale``, ``_Q``, ``_mean_u``, ``_mean_y``
        (:func:`service.methods.model_dir.read_regression` reads them back)."""
        return {f"{prefix}_{k}": getattr(self, k) for k in MEMBERS}


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
        anchor: np.ndarray | None = None, tol: float = RANK_TOL) -> MarkerRegression:
    """Fit the regression (module docstring).

    Parameters
    ----------
    u : (T,M,3) float        training handle displacements, mm
    Y : (T,n,3) float        training vertex offsets (head pose removed), mm
    vertices : (n,3)         rest vertices;  marker_rest (M,3) rest markers, mm
    radius : float           s, mm;  ridge: λ (relative to tr(K_v)/T);  cutoff: g² dropped below
    anchor : (n,3) | None    y₀, the offsets at u = 0 the fit passes through (None: the means)
    tol : float              the rank truncation (:meth:`MarkerRegression.from_matrix`)
    """
    T, M = u.shape[:2]
    n = Y.shape[1]
    mean_u = u.mean(axis=0) if anchor is None else np.zeros(u.shape[1:])
    U = (u - mean_u).astype(np.float64)                                    # (T,M,3)
    G = np.einsum("tmc,smc->mts", U, U).reshape(M, T * T)                  # U_m U_mᵀ
    W = marker_weights(vertices, marker_rest, radius, cutoff)
    mean_y = Y.mean(axis=0) if anchor is None else np.asarray(anchor, np.float64)
    L = np.empty((3 * n, 3 * M), np.float32)
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
        L[3 * v0:3 * v0 + 3 * c] = B.reshape(c * 3, M * 3)
    return MarkerRegression.from_matrix(L, mean_u, mean_y, tol)


def _spd_solve(K: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A (c,T,k) with K_i A_i = B_i for symmetric positive definite K (c,T,T): one Cholesky
    factorization each. (NumPy's stacked ``solve`` runs an LU per matrix ~10× slower at
    T = 120: 0.40 s against 0.04 s CPU for 256 matrices; measured agreement 6e-15.)"""
    from scipy.linalg import cho_factor, cho_solve

    return np.stack([cho_solve(cho_factor(k, lower=True, check_finite=False), b, check_finite=False)
                     for k, b in zip(K, B)])

"""The linear polynomial term of the biharmonic RBF (bickel2008 §5.2 eq. 2 / §5.3 eq. 5, in the
form of [CBC*01] that §5.2 cites for its kernel).

[CBC*01] (Carr et al. 2001, §3) write the biharmonic spline as
``s(x) = p(x) + Σ_j λ_j φ(‖x − x_j‖)`` with φ(r) = r and p a linear polynomial: φ(r) = r is
only conditionally positive definite (of order 1), and without p the interpolant cannot
reproduce a linear function of the pose. bickel2008's eq. 2 and eq. 5 print the sum alone.
Here the fine-scale correction of a vertex v is

    d_v(f) = Σ_j w_v,j φ(‖f − f_j‖_v) + c_v + Σ_{i ∈ S_v} a_v,i f_i,

with S_v the vertex's **support**: for WPSD the feature edges of nonzero α_v,i (eq. 4: the
same local control as the distance, ≤ ``max_edges_per_vertex`` edges); for PSD all E edges (a
global linear term: E + 1 unknowns per coordinate, so with fewer training frames than
features it interpolates the training set; PSD's default is therefore no polynomial). A map
texel uses the support of its nearest vertex (the largest barycentric weight).

Why (measured, family a level 0, least squares P = 12, λ = 1e-4, 1,345 face vertices;
relative RMS error of the corrections on held-out frames in range / combinations /
amplified): WPSD without p 0.471 / 0.553 / 0.338, with p 0.424 / 0.352 / 0.168; its training
RMS (the Fig. 4 quantity) 0.133 → 0.038 mm. Confirmed on family b: 0.455 / 0.663 / 0.526 →
0.093 / 0.392 / 0.123, training 0.301 → 0.023 mm. The wrinkles of a sum of expressions are
close to the sum of their strains' effects, which the cone-shaped kernels of a few example
poses approximate poorly and a local linear term carries exactly.

Stored sparsely: a constant (n,3) and the linear coefficients as one CSR matrix (3n,E)
whose row 3v + c holds a_v,·,c (the rows have the vertex's support as their columns), so
evaluation is ``c + (A @ fᵀ)ᵀ`` — one sparse product per frame — and the transfer of §5.4
interpolates it like α (a sparse product with the barycentric correspondence).

Exact interpolation with p: the P example poses give P equations for P + 1 + |S_v|
unknowns; the minimum-norm solution interpolates them exactly (the [CBC*01] side conditions
Σ_j λ_j p(x_j) = 0 have no solution when P < 1 + |S_v|).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def support_index(S: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Padded column indices of each row's nonzeros.

    Parameters
    ----------
    S : (B,E) sparse     support pattern (α, or a dense all-ones row for PSD)

    Returns
    -------
    idx : (B,w) int64    column indices, padded with 0 (w = the largest row count)
    mask : (B,w) bool    True at the real entries
    """
    S = sp.csr_matrix(S)
    counts = np.diff(S.indptr)
    w = int(counts.max()) if len(counts) else 0
    idx = np.zeros((S.shape[0], w), np.int64)
    mask = np.arange(w)[None, :] < counts[:, None]
    idx[mask] = S.indices
    return idx, mask


def design(f: np.ndarray, idx: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Polynomial columns Q (B,T,1+w): a constant and the supported features of each row.

    f : (T,E) features; idx, mask : (B,w) from :func:`support_index`.
    """
    f = np.asarray(f, np.float64)
    lin = f[:, idx].transpose(1, 0, 2) * mask[:, None, :]                     # (B,T,w)
    return np.concatenate([np.ones(lin.shape[:2] + (1,)), lin], axis=2)


def to_sparse(coef: np.ndarray, idx: np.ndarray, mask: np.ndarray,
              n_edges: int) -> tuple[np.ndarray, sp.csr_matrix]:
    """Constant (B,C) and linear CSR (B·C,E) of fitted coefficients ``coef`` (B,1+w,C)."""
    B, _, C = coef.shape
    const = coef[:, 0, :]
    lin = coef[:, 1:, :]                                                      # (B,w,C)
    b, k = np.nonzero(mask)
    rows = (b[:, None] * C + np.arange(C)[None]).ravel()
    cols = np.repeat(idx[b, k], C)
    vals = lin[b, k, :].ravel()
    A = sp.csr_matrix((vals, (rows, cols)), shape=(B * C, n_edges))
    A.sort_indices()
    return const, A


def evaluate(const: np.ndarray, A: sp.csr_matrix, f: np.ndarray) -> np.ndarray:
    """p_v(f) (F,B,C) of features f (F,E) for the stored constant (B,C) and linear CSR (B·C,E)."""
    f = np.atleast_2d(np.asarray(f, A.dtype))
    B, C = const.shape
    return (A @ f.T).T.reshape(len(f), B, C) + const[None]

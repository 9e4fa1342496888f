"""Linear blend skinning with sparse weights (Le & Deng 2012 eq. 1; Magnenat-Thalmann 1988).

``v_i^t = Σ_j w_ij (R_j^t p_i + T_j^t)`` with the rest vertices p_i, per-frame rigid bone
transforms (R_j^t, T_j^t) that map rest space to frame t, and weights stored sparsely as
``K`` (bone index, weight) pairs per vertex.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def skin(rest: np.ndarray, index: np.ndarray, weight: np.ndarray, R: np.ndarray,
         t: np.ndarray) -> np.ndarray:
    """Skinned vertices of every frame.

    Parameters
    ----------
    rest : (V,3) float        rest-pose vertices p_i, mm
    index : (V,K) int         bone of each influence
    weight : (V,K) float      weight of each influence (0 for unused slots)
    R : (F,B,3,3) float       bone rotations, rest → frame
    t : (F,B,3) float         bone translations, mm

    Returns
    -------
    (F,V,3) float64
    """
    rest = np.asarray(rest, np.float64)
    F, B = R.shape[:2]
    V, K = index.shape
    # v^t = Z @ M^t with Z (V,4B) sparse: row i holds w_ij (p_i, 1) in the 4 columns of bone j
    ph = np.column_stack([rest, np.ones(V)])
    rows = np.repeat(np.arange(V), 4 * K)
    cols = (4 * index[:, :, None] + np.arange(4)).ravel()
    vals = (weight[:, :, None] * ph[:, None, :]).ravel()
    Z = sp.csr_matrix((vals, (rows, cols)), shape=(V, 4 * B))
    M = np.concatenate([R, t[..., None]], axis=-1)                      # (F,B,3,4)
    Ms = M.transpose(1, 3, 0, 2).reshape(4 * B, 3 * F)                  # rows (j,a), cols (t,d)
    return (Z @ Ms).reshape(V, F, 3).transpose(1, 0, 2)


def dense_weights(index: np.ndarray, weight: np.ndarray, bones: int) -> np.ndarray:
    """The (V,B) dense weight matrix of sparse (V,K) influences."""
    W = np.zeros((len(index), bones))
    np.add.at(W, (np.repeat(np.arange(len(index)), index.shape[1]), index.ravel()), weight.ravel())
    return W

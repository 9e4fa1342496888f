"""Linear blend skinning with sparse weights (Le & Deng 2012 eq. 1; Magnenat-Thalmann 1988).

``v_i^t = Σ_j w_ij (R_j^t p_i + T_j^t)`` with the rest vertices p_i, per-frame rigid bone
transforms (R_j^t, T_j^t) that map rest space to frame t, and weights stored sparsely as
``K`` (bone index, weight) pairs per vertex.
"""

from __future__ import annotations

import numpy as np


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
    out = np.zeros((len(R), len(rest), 3))
    for k in range(index.shape[1]):                     # K ≤ 8 slots, vectorized over V and F
        w = weight[:, k]
        used = w != 0
        if not used.any():
            continue
        b, p = index[used, k], rest[used]
        out[:, used] += w[used, None] * (np.einsum("fvij,vj->fvi", R[:, b], p) + t[:, b])
    return out


def dense_weights(index: np.ndarray, weight: np.ndarray, bones: int) -> np.ndarray:
    """The (V,B) dense weight matrix of sparse (V,K) influences."""
    W = np.zeros((len(index), bones))
    np.add.at(W, (np.repeat(np.arange(len(index)), index.shape[1]), index.ravel()), weight.ravel())
    return W

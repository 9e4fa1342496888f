"""The extrapolation limit of PDM parameters (the issue's answer to bermano2014 §7).

ma2008 gives no rule for deformations outside the training range; a biquadratic (eq. 1)
evaluated there grows without bound, most of all in the corners of the (d1, d2) plane that
no training frame visited. Per texel the training parameters d_t = (d1, d2)_t span an
ellipse about the neutral (d = 0): their second moment Σ = mean_t d_t d_tᵀ (ridged by
1e-6 tr Σ) and the largest Mahalanobis radius R = max_t √(d_tᵀ Σ⁻¹ d_t). Synthesis scales
a d with √(dᵀ Σ⁻¹ d) > (1 + margin) R back towards the neutral onto that bound: along the
direction of the expression, with the detail of the most extreme trained one.

A limit is stored as (4,P) float32 rows (i11, i12, i22, R), Σ⁻¹ = [[i11, i12], [i12, i22]].
"""

from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

#: ridge of Σ relative to its trace (a texel whose parameters moved along one line only)
RIDGE = 1e-6


def training_limit(chunks: Callable[[], Iterable[tuple[np.ndarray, np.ndarray]]]) -> np.ndarray:
    """Limit (4,P) float32 of training parameters given as chunks of frames.

    ``chunks()`` yields (d1, d2) pairs of (t,P) arrays covering all training frames; it is
    called twice (moments, then radii), so frames never need to be in memory at once.
    """
    m, T = None, 0
    for d1, d2 in chunks():
        d1, d2 = np.asarray(d1, np.float64), np.asarray(d2, np.float64)
        step = np.stack([(d1 * d1).sum(0), (d1 * d2).sum(0), (d2 * d2).sum(0)])
        m = step if m is None else m + step
        T += len(d1)
    s11, s12, s22 = m / max(T, 1)
    ridge = RIDGE * (s11 + s22) + 1e-12
    s11, s22 = s11 + ridge, s22 + ridge
    det = s11 * s22 - s12 * s12
    inv = np.stack([s22 / det, -s12 / det, s11 / det])
    R2 = np.zeros(m.shape[1])
    for d1, d2 in chunks():
        d1, d2 = np.asarray(d1, np.float64), np.asarray(d2, np.float64)
        R2 = np.maximum(R2, (d1 * d1 * inv[0] + 2 * d1 * d2 * inv[1] + d2 * d2 * inv[2]).max(0))
    return np.vstack([inv, np.sqrt(R2)[None]]).astype(np.float32)


def limit_parameters(d1: np.ndarray, d2: np.ndarray, limit: np.ndarray,
                     margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d1, d2 (…,P) scaled onto ``(1 + margin) R`` where they exceed it, and the mask (…,P).

    The inputs are returned as they are when no point exceeds the limit (the common case
    in synthesis: one pass over the points, in place on one temporary).
    """
    i11, i12, i22, R = limit
    m2 = d2 * i12                                  # Mahalanobis² = d1 (i11 d1 + 2 i12 d2) + i22 d2²
    m2 *= 2
    m2 += d1 * i11
    m2 *= d1
    tmp = d2 * i22
    tmp *= d2
    m2 += tmp
    L = np.asarray(1 + margin, dtype=R.dtype) * R
    over = m2 > L * L
    if not over.any():
        return d1, d2, over
    scale = np.where(over, L / np.sqrt(np.maximum(m2, 1e-30)), np.asarray(1, dtype=m2.dtype))
    return d1 * scale, d2 * scale, over

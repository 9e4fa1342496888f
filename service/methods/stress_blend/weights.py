"""Blend weights of the expression scans from the similarity of local stress.

For a vertex with local stress s (:mod:`service.geometry.surface_strain`) and the scans' local stresses s_0 (the
neutral) … s_K at that vertex, the distances

    d_k² = ‖s − s_k‖² + β² D_k²,      D_k² = mean over vertices of ‖s − s_k‖²

(the local stress distance, plus β times the whole frame's RMS stress distance to scan k,
which only matters where several scans have nearly the same local stress: there, e.g. on
skin an expression does not move, the scan the whole frame resembles most wins instead of
an arbitrary split) give inverse-distance (Shepard 1968) weights

    w_k = d_k^-p / Σ_j d_j^-p  =  Π_{j≠k} d_j^p / Σ_l Π_{j≠l} d_j^p .

The right-hand product form is evaluated (exclusive prefix/suffix products, distances
scaled by their maximum first, which leaves w unchanged), so it is exact at d_k = 0:

* **partition of unity**: w_k ≥ 0 and Σ_k w_k = 1 by construction;
* **reduces to the scan**: a frame equal to scan k has s = s_k at every vertex and
  D_k = 0, so d_k = 0 while every other d_j ≥ β D_j > 0 (β > 0 and the scans differ
  somewhere); every other product contains the factor d_k = 0, so w_k = 1 and w_j = 0
  exactly, and the frame gets that scan's maps bit for bit;
* **smooth**: for p = 2 the weights are a ratio of polynomials in the frame's stress
  (d_k² is quadratic), infinitely differentiable wherever the denominator is non-zero,
  i.e. everywhere except where two scans are both at distance 0 (for β > 0: two scans
  identical over the whole surface); there the weights split equally between them.

With β = 0 the weights are purely local (and split equally wherever several scans have
exactly the frame's stress, so a frame equal to a scan is reproduced only where no other
scan shares its stress).

Weights vary over the surface as smoothly as the local stress does; texel weights are
their barycentric interpolation over the UV layout (still a partition of unity, and still
one-hot where all three corners are).
"""

from __future__ import annotations

import numpy as np


def shepard_weights(stress: np.ndarray, scan_stress: np.ndarray, power: float = 2.0,
                    global_weight: float = 0.5) -> np.ndarray:
    """Per-vertex blend weights (module docstring).

    Parameters
    ----------
    stress : (n,3) or (F,n,3)     local stress of the frame(s)
    scan_stress : (S,n,3)         local stress of the S scans (neutral first)
    power : float                 p ≥ 2
    global_weight : float         β ≥ 0, the weight of the whole frame's stress distance

    Returns
    -------
    (n,S) or (F,n,S) float64      non-negative, rows summing to 1
    """
    s = np.asarray(stress, np.float64)
    single = s.ndim == 2
    s = s[None] if single else s
    d2 = np.sum((s[:, None] - scan_stress[None]) ** 2, axis=-1)           # (F,S,n)
    d = np.sqrt(d2 + global_weight ** 2 * d2.mean(axis=-1, keepdims=True))
    d = np.moveaxis(d, 1, -1)                                            # (F,n,S)
    top = d.max(axis=-1, keepdims=True)
    x = (d / np.where(top > 0, top, 1.0)) ** power
    ones = np.ones(x.shape[:-1] + (1,))
    prefix = np.cumprod(np.concatenate([ones, x[..., :-1]], axis=-1), axis=-1)
    suffix = np.cumprod(np.concatenate([ones, x[..., :0:-1]], axis=-1), axis=-1)[..., ::-1]
    psi = prefix * suffix
    tot = psi.sum(axis=-1, keepdims=True)
    zero = d == 0
    w = np.where(tot > 0, psi / np.where(tot > 0, tot, 1.0),
                 zero / np.maximum(zero.sum(axis=-1, keepdims=True), 1))
    return w[0] if single else w

"""The strain-driven fine band's per-frame texel pass, compiled (issue 23): the band of
:mod:`.strain_band` at the 715k texels of a level-1 fine map.

As NumPy passes (the sparse interpolation of the vertex strain, the monomials, one product
per term, the guards) a level-1 frame took about 55 ms (load 2); here one pass per texel
reads its three vertices' strains and its coefficients once. The same operations as
:meth:`.strain_band.StrainBand.__call__` in float32, the strain summed in float32 instead
of the CSR product's float64 (values within rounding: tests/methods/pdm/test_strain_band.py).
Numba is imported here, so this module is imported where an evaluator is built.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from service.methods.pdm.texel_validity import _rho


@njit(nogil=True, cache=True, error_model="numpy")
def texel_values(lo, hi, corner, weight, strain, inv_scale, terms, target_range, margin,
                 rho_corner, rho_weight, point_rho, width, out):
    """Texels [lo, hi) of a strain-driven band (:mod:`service.methods.pdm.strain_band`):
    the (already clamped) vertex strain interpolated (``corner`` (3,P) uint32, ``weight``
    (3,P) float32; ``strain`` (3,n) float32, a component per row), scaled by ``inv_scale``
    (3,), the polynomial of ``terms`` (K,P) (a term per row: K = 4 linear, 10 biquadratic), clipped to ``target_range`` (P,2)
    widened by ``margin`` (< 0: no clip) and faded toward the constant by w(ρ), ρ the texel's
    gauge from the UV points' ``point_rho`` (Q,) float64 through ``rho_corner`` (3,P) uint32,
    ``rho_weight`` (3,P) float64 (:func:`.texel_validity._rho`) and w the smoothstep falloff
    of ``width`` (:func:`service.methods.confidence.falloff`; ``width`` < 0: no fade), into
    ``out`` (P,) float32.

    Term- and component-major, so each texel's coefficients and the strains stream by rows
    (level 1, interleaved with the texel-major layout in one process: a maps frame 39.3 →
    32.2 and 56.9 → 52.3 ms CPU as the machine's speed moved, bit for bit)."""
    quadratic = terms.shape[0] == 10
    m = np.float32(margin)
    for p in range(lo, hi):
        c0, c1, c2 = corner[0, p], corner[1, p], corner[2, p]
        w0, w1, w2 = weight[0, p], weight[1, p], weight[2, p]
        x0 = (w0 * strain[0, c0] + w1 * strain[0, c1] + w2 * strain[0, c2]) * inv_scale[0]
        x1 = (w0 * strain[1, c0] + w1 * strain[1, c1] + w2 * strain[1, c2]) * inv_scale[1]
        x2 = (w0 * strain[2, c0] + w1 * strain[2, c1] + w2 * strain[2, c2]) * inv_scale[2]
        a0 = terms[0, p]
        v = a0 + terms[1, p] * x0 + terms[2, p] * x1 + terms[3, p] * x2
        if quadratic:
            v += (terms[4, p] * x0 * x0 + terms[5, p] * x1 * x1 + terms[6, p] * x2 * x2
                  + terms[7, p] * x0 * x1 + terms[8, p] * x0 * x2 + terms[9, p] * x1 * x2)
        if margin >= 0:
            v = _clamp(v, target_range[p, 0], target_range[p, 1], m)
        if width >= 0:
            e = _rho(p, point_rho, rho_corner, rho_weight) - np.float32(1)
            if e > 0:                                   # else w = 1
                w = np.float32(0)
                if width > 0:
                    t = min(e / np.float32(width), np.float32(1))
                    w = np.float32(1) - t * t * (np.float32(3) - np.float32(2) * t)
                v = a0 + w * (v - a0)
        out[p] = v


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _clamp(x, lo, hi, margin):
    """x clamped to [lo, hi] widened by ``margin`` × (hi − lo) on each side."""
    pad = margin * (hi - lo)
    return min(max(x, lo - pad), hi + pad)

"""The per-texel pass of :class:`service.geometry.normal_map.NormalMapper`, compiled (issue 23).

For each covered texel of a normal map: the vertex rows (T, N) interpolated with the texel's
barycentric weights over its triangle's corners, the surface gradient ``g = Ku ∂h/∂u +
Kv ∂h/∂v`` of the triangle's operators (1), the texel frame's projections of g and the unit
normal ``(x, y, 1) / |(x, y, 1)|`` written straight into the output map
(:mod:`service.geometry.normal_map`'s module notes). As NumPy passes over blocks of texels
this was six sparse products, a gather of (Ku, Kv), about 40 elementwise passes over (3,b)
temporaries and a scatter of the results (the level-1 sample actor's 1024² map, 715k
covered texels: about 30 of 45 ms per map); here each texel is read and written once, in a
Numba kernel over texel ranges ``[lo, hi)`` (:func:`service.geometry.ranges.run`).

The same float32 operations in the same order as the NumPy passes (compiled without
fast-math: nothing reassociated or contracted; the interpolation sums the three corners in
order from 0, as SciPy's CSR product did), so the maps are the NumPy path's bit for bit
(tests/geometry/test_normal_map.py). NumPy's error model: IEEE division without a zero test
per division (the Python model's tests cost the pass 18 → 14 ms on the level-1 map). Numba
is imported here: the mapper imports this module when it is built, i.e. where a model is
built, never by ``facesynth serve``'s start.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _interpolate(TN, r, v0, v1, v2, w0, w1, w2):
    """Row r of TN (6,n) at a texel: ``0 + w0 TN[r,v0] + w1 TN[r,v1] + w2 TN[r,v2]`` summed
    in that order (SciPy's CSR row sum)."""
    s = np.float32(0) + w0 * TN[r, v0]
    s += w1 * TN[r, v1]
    s += w2 * TN[r, v2]
    return s


@njit(nogil=True, cache=True, error_model="numpy")
def normal_texels(lo, hi, texel, triangle, lam, corners, du, dv, K, TN, eps, out):
    """Texels [lo, hi): ``out[texel[i]]`` (H·W,3) float32 = the unit tangent-space normal of
    covered texel i, from its triangle ``triangle[i]`` (a column of the operators K (6,mu)
    float32, rows Ku, Kv), its barycentric weights ``lam`` (N,3) float32 on the vertices
    ``corners`` (N,3), the map's derivatives ``du``, ``dv`` (N,) float32 and the vertex rows
    ``TN`` (6,n) float32 (T, N); ``eps`` the clamp of |T×N|² and |Z|² (FRAME_DEGENERATE)."""
    one = np.float32(1)
    for i in range(uint64(lo), uint64(hi)):
        q = triangle[i]
        a, b = du[i], dv[i]
        g0 = K[0, q] * a
        g1 = K[1, q] * a
        g2 = K[2, q] * a
        g0 += K[3, q] * b
        g1 += K[4, q] * b
        g2 += K[5, q] * b
        v0, v1, v2 = corners[i, 0], corners[i, 1], corners[i, 2]
        w0, w1, w2 = lam[i, 0], lam[i, 1], lam[i, 2]
        t0 = _interpolate(TN, 0, v0, v1, v2, w0, w1, w2)
        t1 = _interpolate(TN, 1, v0, v1, v2, w0, w1, w2)
        t2 = _interpolate(TN, 2, v0, v1, v2, w0, w1, w2)
        n0 = _interpolate(TN, 3, v0, v1, v2, w0, w1, w2)
        n1 = _interpolate(TN, 4, v0, v1, v2, w0, w1, w2)
        n2 = _interpolate(TN, 5, v0, v1, v2, w0, w1, w2)
        x0 = t1 * n2 - t2 * n1                     # X = T × N
        x1 = t2 * n0 - t0 * n2
        x2 = t0 * n1 - t1 * n0
        z0 = x1 * n2 - x2 * n1                     # Z = X × N
        z1 = x2 * n0 - x0 * n2
        z2 = x0 * n1 - x1 * n0
        zz = z0 * z0 + z1 * z1 + z2 * z2
        xx = x0 * x0 + x1 * x1 + x2 * x2
        x = z0 * g0 + z1 * g1 + z2 * g2
        x /= np.sqrt(zz if (zz > eps or zz != zz) else eps)
        y = x0 * g0 + x1 * g1 + x2 * g2
        y /= np.sqrt(xx if (xx > eps or xx != xx) else eps)
        r = x * x
        r += y * y
        r += one
        r = one / np.sqrt(r)
        p = texel[i]
        out[p, 0] = x * r
        out[p, 1] = y * r
        out[p, 2] = r

"""The per-frame surface strain of :class:`~service.geometry.surface_strain.StressField`,
compiled (issue 23: a frame's strain at the 715k texels of a level-1 fine map).

As NumPy passes, :meth:`StressField.stress` of one level-1 frame (89k triangles, 45k
vertices) and its sparse interpolation to the fine texels took 40 and 35 ms (load 2). Here:

1. :func:`triangle_metrics`: per triangle the Sumner–Popović deformation gradient
   ``G = [e1 e2 e3] Ṽ0⁻¹`` and its right Cauchy–Green tensor ``C = GᵀG`` (6 entries);
2. :func:`vertex_strain`: per vertex the area-weighted mean of its triangles' C (the
   field's ``average`` rows) restricted to the rest tangent plane, ``(E_TT, E_BB, √2 E_TB)``;
then :mod:`service.methods.pdm.strain_texels` takes it to the texels.

The same formulas as the NumPy operators in float64, summed in another order: the strains
agree to rounding (tests/geometry/test_strain_kernels.py). Numba is imported here, so this
module is imported where an evaluator is built.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True, error_model="numpy")
def triangle_metrics(lo, hi, V, faces, R, C):
    """Triangles [lo, hi) of mesh V (n,3) float64: C = GᵀG into ``C`` (m,6) float64 in the
    order xx yy zz xy xz yz; ``R`` (m,3,3) the rest edge frames' inverses."""
    for t in range(lo, hi):
        a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
        e1x, e1y, e1z = V[b, 0] - V[a, 0], V[b, 1] - V[a, 1], V[b, 2] - V[a, 2]
        e2x, e2y, e2z = V[c, 0] - V[a, 0], V[c, 1] - V[a, 1], V[c, 2] - V[a, 2]
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        s = np.sqrt(np.sqrt(nx * nx + ny * ny + nz * nz))
        e3x, e3y, e3z = nx / s, ny / s, nz / s
        # G = [e1 e2 e3] R: column j of G is Σ_k column k of the frame × R[k, j]
        g00 = e1x * R[t, 0, 0] + e2x * R[t, 1, 0] + e3x * R[t, 2, 0]
        g10 = e1y * R[t, 0, 0] + e2y * R[t, 1, 0] + e3y * R[t, 2, 0]
        g20 = e1z * R[t, 0, 0] + e2z * R[t, 1, 0] + e3z * R[t, 2, 0]
        g01 = e1x * R[t, 0, 1] + e2x * R[t, 1, 1] + e3x * R[t, 2, 1]
        g11 = e1y * R[t, 0, 1] + e2y * R[t, 1, 1] + e3y * R[t, 2, 1]
        g21 = e1z * R[t, 0, 1] + e2z * R[t, 1, 1] + e3z * R[t, 2, 1]
        g02 = e1x * R[t, 0, 2] + e2x * R[t, 1, 2] + e3x * R[t, 2, 2]
        g12 = e1y * R[t, 0, 2] + e2y * R[t, 1, 2] + e3y * R[t, 2, 2]
        g22 = e1z * R[t, 0, 2] + e2z * R[t, 1, 2] + e3z * R[t, 2, 2]
        C[t, 0] = g00 * g00 + g10 * g10 + g20 * g20
        C[t, 1] = g01 * g01 + g11 * g11 + g21 * g21
        C[t, 2] = g02 * g02 + g12 * g12 + g22 * g22
        C[t, 3] = g00 * g01 + g10 * g11 + g20 * g21
        C[t, 4] = g00 * g02 + g10 * g12 + g20 * g22
        C[t, 5] = g01 * g02 + g11 * g12 + g21 * g22


@njit(nogil=True, cache=True, error_model="numpy")
def vertex_strain(lo, hi, indptr, indices, data, C, tangent, out):
    """Vertices [lo, hi): the Green strain ``(E_TT, E_BB, √2 E_TB)`` into ``out`` (n,3)
    float32 of the mean tensor ``Σ_t w_vt C_t`` (the averaging CSR ``indptr``, ``indices``,
    ``data``) in the rest tangent frame ``tangent`` (n,2,3) (T, B)."""
    r2 = np.sqrt(2.0)
    for v in range(lo, hi):
        m0 = m1 = m2 = m3 = m4 = m5 = 0.0
        for k in range(indptr[v], indptr[v + 1]):
            t, w = indices[k], data[k]
            m0 += w * C[t, 0]
            m1 += w * C[t, 1]
            m2 += w * C[t, 2]
            m3 += w * C[t, 3]
            m4 += w * C[t, 4]
            m5 += w * C[t, 5]
        T0, T1, T2 = tangent[v, 0, 0], tangent[v, 0, 1], tangent[v, 0, 2]
        B0, B1, B2 = tangent[v, 1, 0], tangent[v, 1, 1], tangent[v, 1, 2]
        # C T and C B of the symmetric tensor (xx yy zz xy xz yz)
        CT0 = m0 * T0 + m3 * T1 + m4 * T2
        CT1 = m3 * T0 + m1 * T1 + m5 * T2
        CT2 = m4 * T0 + m5 * T1 + m2 * T2
        CB0 = m0 * B0 + m3 * B1 + m4 * B2
        CB1 = m3 * B0 + m1 * B1 + m5 * B2
        CB2 = m4 * B0 + m5 * B1 + m2 * B2
        out[v, 0] = 0.5 * (T0 * CT0 + T1 * CT1 + T2 * CT2 - 1.0)
        out[v, 1] = 0.5 * (B0 * CB0 + B1 * CB1 + B2 * CB2 - 1.0)
        out[v, 2] = r2 * 0.5 * (T0 * CB0 + T1 * CB1 + T2 * CB2)

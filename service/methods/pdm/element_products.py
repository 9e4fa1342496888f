"""d1, d2 of points sorted by coarse element from their element's terms, compiled (issue 23).

ma2008 eq. 3 at a point p of a coarse element e is a quadratic form in the point's fixed
barycentric weights (:class:`.deformation.ParameterField`):
``d_i(p) = Σ_k G_ik(e) m_k(p)``, k over the six symmetric terms, G (T,12,E) the per-frame
element terms (:meth:`.deformation.ParameterField.element_terms`, d1's six then d2's) and m
(6,P) the point's weight monomials. The NumPy path made one ``(2,6)·(6,run)`` BLAS product
per element: ~300 elements per band, each call a few microseconds of Python and NumPy
dispatch, 2.6 ms of a mesh frame on the level-1 sample actor's 45,600 UV points. Here one
pass over the element ranges ``[lo, hi)`` (run by :func:`service.geometry.ranges.run`)
computes each point's two sums in the arithmetic of that product (OpenBLAS's float32 GEMM
kernel on FMA hardware: ``m_0 G_0`` rounded, then one fused multiply-add per further term in
term order), so the values are the products' bit for bit (tests against the per-element
``np.matmul``), and writes them in the point order the caller asks for (sorted, or back to
the points' own order through ``order``: no separate scatter).

Numba is imported here; :mod:`.deformation` imports this module inside the calls that use it.
"""

from __future__ import annotations

import numpy as np
from numba import njit, types, uint64
from numba.extending import intrinsic


@intrinsic
def fma32(typingctx, a, b, c):
    """``a b + c`` float32 with one rounding (LLVM's ``llvm.fma.f32``)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return sig, codegen


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _form(c0, c1, c2, c3, c4, c5, mono, p):
    """``Σ_k c_k mono[k, p]`` float32: the first product rounded, then one fused
    multiply-add per term in term order (the GEMM kernel's arithmetic)."""
    x = c0 * mono[0, p]
    x = fma32(c1, mono[1, p], x)
    x = fma32(c2, mono[2, p], x)
    x = fma32(c3, mono[3, p], x)
    x = fma32(c4, mono[4, p], x)
    return fma32(c5, mono[5, p], x)


@njit(nogil=True, cache=True, error_model="numpy")
def element_products(lo, hi, first, g, mono, starts, order, shift, d1, d2):
    """Elements ``first + [lo, hi)``: for each point p of element e (``starts[e] ≤ p <
    starts[e+1]``, positions in the element-sorted point order) and frame f,
    ``d1[f, q] = Σ_k g[f, k, e] mono[k, p]`` and ``d2[f, q] = Σ_k g[f, 6+k, e] mono[k, p]``
    (k = 0..5; the first product rounded, the others fused multiply-adds), at
    ``q = order[p]`` when ``order`` (P,) is given (non-empty), else ``q = p − shift``.

    g (T,12,E) float32, mono (6,P) float32, starts (E+1,) int64, d1 and d2 (T,Q) float32."""
    T = uint64(g.shape[0])
    scatter = order.shape[0] > 0
    for e in range(uint64(first) + uint64(lo), uint64(first) + uint64(hi)):
        s, t = uint64(starts[e]), uint64(starts[e + uint64(1)])
        for f in range(T):
            a0, a1, a2, a3, a4, a5 = g[f, 0, e], g[f, 1, e], g[f, 2, e], g[f, 3, e], g[f, 4, e], g[f, 5, e]
            b0, b1, b2, b3, b4, b5 = g[f, 6, e], g[f, 7, e], g[f, 8, e], g[f, 9, e], g[f, 10, e], g[f, 11, e]
            if scatter:
                for p in range(s, t):
                    q = uint64(order[p])
                    d1[f, q] = _form(a0, a1, a2, a3, a4, a5, mono, p)
                    d2[f, q] = _form(b0, b1, b2, b3, b4, b5, mono, p)
            else:                                  # contiguous: vectorized over the points
                for p in range(s, t):
                    d1[f, p - uint64(shift)] = _form(a0, a1, a2, a3, a4, a5, mono, p)
                    d2[f, p - uint64(shift)] = _form(b0, b1, b2, b3, b4, b5, mono, p)


NO_ORDER = np.empty(0, np.int64)

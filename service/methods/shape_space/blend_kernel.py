"""The per-element sum of :func:`service.methods.shape_space.blending.blend`, compiled (issue 23).

bermano2014 eq. 4 for one request frame is, per element e (triangle, texel or vertex) and
component c, ``b[e,c] = Σ_j coef[j,e] · values[k_j,e,c]`` over the K active database frames
k_j, with ``coef`` (K,k) the region-blended weights. The NumPy passes this replaces made,
per active frame, one product into a temporary and one addition into the result: about
five passes over a (k,C) array per active frame (level 1: the (89k,9) float32 detail and the
715k-texel fine map, 12–20 active frames, ~25 ms of a 150 ms frame). Here each element's sum
runs over the active frames in a block of elements at a time, the block's partial sums
staying in the cache: one read of each active frame's values, one write of the result.

Bit for bit the NumPy passes: the same float32 (or float64) operations in the same order —
each stored value converted to the compute type (int16 and float32 exactly), multiplied by
its coefficient, added to the running sum that starts at zero, frames in increasing order —
compiled without fast-math (no contraction into fused multiply-adds).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.extending import overload

#: elements per block: the block's partial sums (BLOCK × C compute-type values, 36 KB for
#: the detail's 9 float32 components) stay in the cache while every active frame is added
BLOCK = 1024


def _add(o, v, w):
    """``o += w · v`` per element of a block: this NumPy form is what runs uncompiled; in
    :func:`blend_rows` Numba runs :func:`_add_typed` instead."""
    o += v.astype(o.dtype) * (w[:, None] if o.ndim == 2 else w)


@overload(_add, jit_options={"nogil": True})
def _add_typed(o, v, w):
    """The block update for the block's type: ``o[e, c] += w[e] · v[e, c]`` (C components),
    or ``o[e] += w[e] · v[e]`` (one: the element loop alone, which vectorizes; with the
    single component's loop inside it did not, 2.4× slower). Stored values are converted to
    the compute type (``o``'s) before the product."""
    if o.ndim == 2:
        def rows(o, v, w):
            for e in range(o.shape[0]):
                a = w[e]
                for c in range(o.shape[1]):
                    o[e, c] += o.dtype.type(v[e, c]) * a
        return rows

    def one(o, v, w):
        for e in range(o.shape[0]):
            o[e] += o.dtype.type(v[e]) * w[e]
    return one


@njit(nogil=True, cache=True, error_model="numpy")
def blend_rows(lo, hi, values, frames, coef, out):
    """Elements [lo, hi): ``out[e, c] = Σ_j coef[j, e] · values[frames[j], e, c]``, the sum in
    ``out``'s dtype (float32 or float64) over j in increasing order from zero.

    values : (N,k,C) or (N,k) int16, float32 or float64   the stored per-frame values (one
                                                 component as (N,k): its loop vectorizes)
    frames : (K,) int64                          the active frames, increasing
    coef : (K,k) of ``out``'s dtype              each active frame's coefficient per element
    out : (k,C) or (k,) float32 or float64       written

    A block of elements at a time: its sums zeroed, then each active frame's rows added in
    increasing order. The rows are sliced per block (contiguous views of known layout: the
    loops vectorize; indexed through the whole arrays they did not, 4× slower).
    """
    for s in range(lo, hi, BLOCK):
        e1 = min(s + BLOCK, hi)
        o = out[s:e1]
        o[:] = 0
        for j in range(frames.shape[0]):
            _add(o, values[frames[j], s:e1], coef[j, s:e1])

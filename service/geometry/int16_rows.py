"""Row products of an int16 matrix with a float32 vector: the per-frame read of a stored
low-rank factor at half the bytes of float32 (:mod:`.marker_regression`).

A memory-bound product reads each matrix entry once per frame, so its time is the matrix's
bytes: a (3n, r) factor quantized per column to int16 (``P ≈ Pq diag(scale)``) is read at
half float32's cost, the column scale folded into the vector first. Measured (one thread,
3n = 134,358 rows × r = 155, load ~5): NumPy's float32 ``P @ z`` 7.6 ms, :func:`row_products`
2.0 ms, the result 4e-5 of its largest value apart (the quantization; summation in float32).

Numba, ``nogil``, over row ranges (:func:`service.geometry.ranges.run`); imported where a
product is computed, never at a service's start.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64


@njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def row_products(lo, hi, Pq, z, out):
    """Rows [lo, hi): ``out[i] = Σ_k Pq[i,k] z[k]`` for Pq (m,r) int16, z (r,) float32,
    out (m,) float32 (each entry converted exactly, the sum in float32)."""
    r = Pq.shape[1]
    for i in range(uint64(lo), uint64(hi)):
        acc = np.float32(0.0)
        for k in range(r):
            acc += np.float32(Pq[i, k]) * z[k]
        out[i] = acc

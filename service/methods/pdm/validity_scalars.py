"""The scalar pieces both compiled validity passes share — the medium band's points
(:mod:`.point_validity`) and a texel band's (:mod:`.texel_validity`): a term's monomial and
the falloff, each in the float32 operations of the NumPy function it stands for
(:func:`.polynomial.evaluate`, :func:`service.methods.confidence.falloff`), so both kernels
stay bit for bit with their references. Numba is imported here (as by the kernels)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def monomial(a, b, i, j):
    """``d1^i d2^j`` at (a, b) float32 as :func:`.polynomial.evaluate` rounds it: each power a
    repeated product from the first, a mixed term the product of the two powers."""
    x = a
    for _ in range(1, i):
        x *= a
    y = b
    for _ in range(1, j):
        y *= b
    return x if j == 0 else (y if i == 0 else x * y)


@njit(nogil=True, cache=True, error_model="numpy")
def falloff(excess, width):
    """:func:`service.methods.confidence.falloff` of one float32 excess > 0."""
    if width <= 0:
        return np.float32(0)
    x = min(excess / np.float32(width), np.float32(1))
    return np.float32(1) - x * x * (np.float32(3) - np.float32(2) * x)

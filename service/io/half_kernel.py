"""float32 → float16 bits, compiled: :func:`service.io.half.to_float16`'s rounding as one
Numba loop over the values, bit for bit its NumPy blocks (and so NumPy's ``astype``).

The NumPy form makes ~12 passes over each block: 7.8–8.0 ms for 4.2 M map-like values
(a level-1 maps frame's 1024² displacement and normal map; 2 cores, load ~2); this loop
reads each value once: 1.9–2.3 ms. Numba is imported here only, so this module is imported
at the first half-precision response, never at ``facesynth serve``'s start (issue 23's
cold start); the compiled loop is cached on disk (``cache=True``). Pinned bit for bit
against NumPy in ``tests/io/test_half.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from service.io.binary16 import REBIAS, SMALLEST_NORMAL, SPECIAL

#: 2²⁴: a value below 2⁻¹⁴ times this is its float16 subnormal mantissa (exact scaling)
SUBNORMAL_SCALE = np.float32(2.0 ** 24)


@njit(nogil=True, cache=True, error_model="numpy")
def half_bits(bits, values, out):
    """float16 bits ``out`` (n,) uint16 of float32 ``values`` (n,) (``bits`` (n,) uint32 the
    same memory), rounded to nearest, ties to even (Giesen's ``float_to_half_fast3_rtne``);
    returns whether any |value| ≥ 65536, ∞ or NaN is present (those get 0 here and are
    NumPy's to convert).

    - ``a ≥ 2⁻¹⁴`` (``a`` the bits without sign): rebias the exponent, add ``0xFFF`` plus the
      lowest kept mantissa bit, shift right by 13 (a carry steps the exponent, to ∞);
    - ``a < 2⁻¹⁴``: the float16 subnormal mantissa is |value|·2²⁴ (exact in float32) rounded
      half to even (``np.rint``), which is what the NumPy form's float add of 0.5 leaves in
      the low bits.
    """
    special = False
    for i in range(bits.size):
        u = bits[i]
        a = u & np.uint32(0x7FFFFFFF)
        normal = (a + REBIAS + ((a >> np.uint32(13)) & np.uint32(1))) >> np.uint32(13)
        # both branches computed and one selected: the loop vectorizes (a large value's
        # scaled product is unused, and ∞/NaN's too)
        small = np.uint32(np.rint(min(abs(values[i]), np.float32(1.0)) * SUBNORMAL_SCALE))
        h = small if a < SMALLEST_NORMAL else normal
        special |= a >= SPECIAL
        h = np.uint32(0) if a >= SPECIAL else h
        out[i] = np.uint16(h | ((u >> np.uint32(16)) & np.uint32(0x8000)))
    return special

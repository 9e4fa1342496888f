"""float32 → float16 bits, compiled: :func:`service.io.half.to_float16`'s rounding as one
Numba loop over the values, bit for bit its NumPy blocks (and so NumPy's ``astype``).

The NumPy form makes ~12 passes over each block: 7.8–8.0 ms for 4.2 M map-like values
(a level-1 maps frame's 1024² displacement and normal map; 2 cores, load ~2); this loop
reads each value once: 1.9–2.3 ms. Numba is imported here only, so this module is imported
at the first half-precision response, never at ``facesynth serve``'s start (issue 23's
cold start); the compiled loop is cached on disk (``cache=True``). Pinned bit for bit
against NumPy in ``tests/io/test_half.py``.

:func:`binary16` is the rounding of one value, inlined into every kernel that writes
half-precision output (:func:`half_bits`; the PDM's maps written as float16 by the map
kernels themselves, :mod:`service.geometry.texel_image` and
:mod:`service.geometry.normal_texels`, issue 23), so it also covers what NumPy does with
|x| ≥ 65536, ∞ and NaN (NumPy's ``npy_floatbits_to_halfbits``) instead of leaving those to a
NumPy pass afterwards.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from service.geometry.binary16 import REBIAS, SMALLEST_NORMAL, SPECIAL

#: 2²⁴: a value below 2⁻¹⁴ times this is its float16 subnormal mantissa (exact scaling)
SUBNORMAL_SCALE = np.float32(2.0 ** 24)
#: float32 bits of +∞ (an absolute value above it is a NaN); float16 bits of +∞
F32_INF, F16_INF = np.uint32(0x7F800000), np.uint32(0x7C00)


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def binary16(u, x):
    """The float16 bits (uint16) of the float32 ``x`` whose bits are ``u`` (uint32), rounded
    to nearest, ties to even: NumPy's ``astype(np.float16)`` bit for bit for every input
    (Giesen's ``float_to_half_fast3_rtne`` for finite values below 65536; NumPy's rule
    beyond). Branch-free (every case computed, one selected), so loops over it vectorize.

    - ``a ≥ 2⁻¹⁴`` (``a`` the bits without sign): rebias the exponent, add ``0xFFF`` plus the
      lowest kept mantissa bit, shift right by 13 (a carry steps the exponent, up to ∞);
    - ``a < 2⁻¹⁴``: the float16 subnormal mantissa is |x|·2²⁴ (exact in float32) rounded
      half to even (``np.rint``);
    - ``a ≥ 65536`` and ∞: ∞; NaN: ``0x7C00`` plus the top 10 bits of its payload, at least
      ``0x7C01`` (still a NaN), as NumPy keeps it.

    The sign is or-ed back as bit 15.
    """
    a = u & np.uint32(0x7FFFFFFF)
    normal = (a + REBIAS + ((a >> np.uint32(13)) & np.uint32(1))) >> np.uint32(13)
    small = np.uint32(np.rint(min(abs(x), np.float32(1.0)) * SUBNORMAL_SCALE))
    h = small if a < SMALLEST_NORMAL else normal
    nan = max(F16_INF + ((a & np.uint32(0x7FFFFF)) >> np.uint32(13)), F16_INF + np.uint32(1))
    special = F16_INF if a <= F32_INF else nan
    h = special if a >= SPECIAL else h
    return np.uint16(h | ((u >> np.uint32(16)) & np.uint32(0x8000)))


@njit(nogil=True, cache=True, error_model="numpy")
def half_bits(bits, values, out):
    """float16 bits ``out`` (n,) uint16 of float32 ``values`` (n,) (``bits`` (n,) uint32 the
    same memory): :func:`binary16` of each."""
    for i in range(bits.size):
        out[i] = binary16(bits[i], values[i])

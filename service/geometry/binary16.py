"""IEEE 754 binary16 constants of the float32 → float16 conversion: the bit patterns that
:func:`service.io.half.to_float16`'s NumPy blocks and its compiled loop
(:mod:`service.geometry.half_kernel`) both round with, declared once (plain NumPy, so importing
them imports no Numba)."""

from __future__ import annotations

import numpy as np

#: float32 bits of the smallest normal float16, 2⁻¹⁴
SMALLEST_NORMAL = np.uint32(0x38800000)
#: float32 bits of 65536, from which the normal branch would overflow its 15 bits (∞, NaN
#: and these are left to NumPy)
SPECIAL = np.uint32(0x47800000)
#: the exponent rebias (15 - 127) << 23 plus the rounding bias 0xFFF, modulo 2³²
REBIAS = np.uint32((((15 - 127) << 23) + 0xFFF) & 0xFFFFFFFF)
#: float32 0.5 (bits ((127 - 15) + (23 - 10) + 1) << 23): adding it to a value below 2⁻¹⁴
#: rounds that value to a multiple of 2⁻²⁴ (the float16 subnormal step) in the low bits
MAGIC = np.uint32(((127 - 15) + (23 - 10) + 1) << 23)

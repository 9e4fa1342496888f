"""float32 → float16 (IEEE 754 binary16) conversion, bit for bit NumPy's, vectorized.

NumPy's ``astype(np.float16)`` is a scalar loop on this build (its F16C path is compiled only
into a baseline that includes F16C), and slower again on values that become float16
subnormals: measured on a level-1 PDM maps frame (2 cores, load ~3), the 1024² normal map
(3.1 M values, 23 % of them zero or below 2⁻¹⁴) takes 12.7 ms and the 1024² displacement
2.9 ms — most of what ``half=true`` adds to an NPZ response (issue 23). :func:`to_float16`
does the same rounding with a handful of in-cache integer ufuncs per block instead:
8.6 ms and 1.6 ms for those two maps (1.5× and 1.7×; blocks of 2¹⁷ values: 7.9 ms).

The method (F. Giesen, "float_to_half_fast3_rtne", 2016) works on the float32 bits ``u``
with the sign cleared, ``a``:

- ``a ≥ 2⁻¹⁴`` (a normal float16): rebias the exponent and round the 13 dropped mantissa
  bits to nearest, ties to even, by adding ``0xFFF`` plus the lowest kept bit, then shift
  right by 13 (a carry out of the mantissa steps the exponent, up to ``0x7C00``: ∞);
- ``a < 2⁻¹⁴`` (a float16 subnormal or zero): add 0.5 in float32, whose spacing there is
  2⁻²⁴ — the float16 subnormal step — so the FPU's own round-to-nearest-even leaves the 10
  mantissa bits at the bottom, and subtract 0.5's bits;
- ``a ≥ 65536``, ∞ and NaN (whose payload NumPy keeps): those few values are converted by
  NumPy itself, so every bit pattern comes out as NumPy's (65520 ≤ a < 65536 already
  carries into ``0x7C00``, ∞, in the normal branch).

The sign is or-ed back as bit 15. Checked against NumPy on every exponent × sign with all
rounding cases of the dropped bits (ties, sticky bits, odd and even kept mantissas) and on
the real maps (``tests/io/test_half.py``).

:func:`to_float16` runs the same rounding as one compiled loop
(:func:`service.geometry.half_kernel.half_bits`, imported at the first call): on 4.2 M map-like
float32 values (2 cores, load ~2) 1.9–2.3 ms against 7.8–8.0 ms for the NumPy blocks
(:func:`to_float16_blocks`, kept as the reference it is pinned against) and 15.6 ms for
``astype``. It can write into a caller's buffer (``out``: an NPZ response's member, so the
converted map is not copied again). The compiled rounding of one value
(:func:`service.geometry.half_kernel.binary16`) also gives NumPy's bits for |x| ≥ 65536, ∞
and NaN, so the loop needs no NumPy pass after it; the PDM's map kernels write float16 maps
with it directly (issue 23).
"""

from __future__ import annotations

import numpy as np

from service.geometry.binary16 import MAGIC, REBIAS, SMALLEST_NORMAL, SPECIAL

#: values per block: 64 Ki float32 (256 KiB in, a few such temporaries) stays in L2
BLOCK = 1 << 16


def to_float16(values: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``values`` as float16, bit for bit NumPy's ``astype(np.float16)``: float32 by the
    compiled loop (:func:`service.geometry.half_kernel.half_bits`), any other dtype by NumPy
    (which rounds it once, not through float32).

    Parameters
    ----------
    values : array of any shape
    out : (values.size,) float16 or uint16 C-contiguous array, optional   written in place
          (in C order of ``values``) and returned reshaped

    Returns
    -------
    float16 array of ``values``' shape (C order); overflow to ±∞ raises no warning
    """
    values = np.asarray(values)
    if out is None:
        out = np.empty(values.size, np.float16)
    flat = out.reshape(-1).view(np.uint16)
    if flat.size != values.size:
        raise ValueError(f"out holds {flat.size} values for {values.size}")
    if values.dtype != np.float32:
        with np.errstate(over="ignore"):
            flat[...] = values.astype(np.float16).reshape(-1).view(np.uint16)
        return flat.view(np.float16).reshape(values.shape)
    from service.geometry.half_kernel import half_bits   # Numba: at the first call, not at import

    x = np.ascontiguousarray(values).reshape(-1)
    half_bits(x.view(np.uint32), x, flat)
    return flat.view(np.float16).reshape(values.shape)


def to_float16_blocks(values: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """``values`` as float16 by the NumPy blocks of the method above (the reference of
    :func:`to_float16`'s compiled loop), bit for bit NumPy's ``astype(np.float16)``.

    Parameters
    ----------
    values : array of any shape; float32 takes the vectorized conversion below, any other
             dtype NumPy's own (which rounds it once, not through float32)
    block : int   values converted per pass (see :data:`BLOCK`)

    Returns
    -------
    float16 array of ``values``' shape (C order); overflow to ±∞ raises no warning
    """
    values = np.asarray(values)
    if values.dtype != np.float32:
        with np.errstate(over="ignore"):
            return np.ascontiguousarray(values.astype(np.float16))
    x = np.ascontiguousarray(values)
    bits = x.reshape(-1).view(np.uint32)
    n = bits.size
    out = np.empty(n, np.uint16)
    size = max(1, min(block, n))
    a, t, s = (np.empty(size, np.uint32) for _ in range(3))
    small = np.empty(size, bool)
    magic = MAGIC.view(np.float32)
    special = False
    # the float add of the subnormal branch sees NaN and inf too (their result is NumPy's)
    with np.errstate(invalid="ignore", over="ignore"):
        for start in range(0, n, size):
            u = bits[start:start + size]
            k = u.size
            A, T, S, M = a[:k], t[:k], s[:k], small[:k]
            np.bitwise_and(u, 0x7FFFFFFF, out=A)
            # normal: ((a + rebias + 0xFFF + odd) >> 13), odd = the lowest kept mantissa bit
            np.right_shift(A, 13, out=T)
            np.bitwise_and(T, 1, out=T)
            np.add(T, A, out=T)
            np.add(T, REBIAS, out=T)
            np.right_shift(T, 13, out=T)
            # subnormal or zero: the FPU rounds a + 0.5 to the float16 step; minus 0.5's bits
            np.add(A.view(np.float32), magic, out=S.view(np.float32))
            np.subtract(S, MAGIC, out=S)
            np.less(A, SMALLEST_NORMAL, out=M)
            np.copyto(T, S, where=M)
            # the sign as bit 15
            np.right_shift(u, 16, out=S)
            np.bitwise_and(S, 0x8000, out=S)
            np.bitwise_or(T, S, out=T)
            out[start:start + k] = T
            special = special or bool(A.max() >= SPECIAL)
    half = out.view(np.float16).reshape(x.shape)
    if special:
        flat, source = half.reshape(-1), x.reshape(-1)
        where = np.flatnonzero((bits & 0x7FFFFFFF) >= SPECIAL)
        with np.errstate(over="ignore", invalid="ignore"):
            flat[where] = source[where].astype(np.float16)
    return half

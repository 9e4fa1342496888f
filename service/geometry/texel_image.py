"""Maps from values at a set of covered texels, written texel by texel (issue 23).

A band of a texture (e.g. the PDM's fine displacement, ma2008 §5 step 5) is evaluated at its
covered texels in an order of its own (:class:`service.methods.pdm.texel_band.TexelBand`:
grouped by coarse element), and its output map is that band scattered into an image that is
0 elsewhere. As NumPy that is a zero-filled (H,W) map and a fancy-index scatter in the band's
order (level-1 PDM, 715k of 1024² texels: 3.3 ms of a maps frame under cProfile, the freshly
mapped output's page faults included). Here the map is written in one pass in texel order,
each texel reading its value through the band's inverse index (:func:`inverse_index`) or
writing 0: every texel written once, sequentially, no zero fill (0.95 ms under cProfile,
the page faults included; the inverse index costs 4 bytes per texel of the map, 4 MB at
1024²). The values are copied, so the map is the scatter's bit for bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64

from service.geometry.half_kernel import binary16

#: the inverse index of a texel that is not in the band
NOT_COVERED = np.uint32(0xFFFFFFFF)
#: texels per block of a half-precision :func:`band_image` (1 KiB of float32: in L1)
BLOCK = 256


def inverse_index(index: np.ndarray, size: int) -> np.ndarray:
    """(size,) uint32: at flat texel ``index[i]`` its position i in the band, elsewhere
    :data:`NOT_COVERED`; ``index`` (P,) distinct flat texel indices, P < 2³²−1."""
    index = np.asarray(index, np.int64)
    if len(index) >= int(NOT_COVERED):
        raise ValueError(f"{len(index)} texels do not fit a uint32 inverse index")
    inverse = np.full(int(size), NOT_COVERED, np.uint32)
    inverse[index] = np.arange(len(index), dtype=np.uint32)
    return inverse


@njit(nogil=True, cache=True, error_model="numpy")
def band_image(lo, hi, inverse, values, out):
    """Texels [lo, hi) of a flat map ``out`` (H·W,): ``values[inverse[p]]`` (values (P,)) where
    ``inverse[p]`` (:func:`inverse_index`) is a band position, 0 where it is
    :data:`NOT_COVERED`."""
    none = uint64(NOT_COVERED)
    for p in range(uint64(lo), uint64(hi)):
        q = uint64(inverse[p])
        out[p] = values[q] if q != none else 0


@njit(nogil=True, cache=True, error_model="numpy")
def band_image_half(lo, hi, inverse, values, out, half):
    """:func:`band_image` of float32 ``values`` written as float16 bits into ``half`` (H·W,)
    uint16 (:func:`service.geometry.half_kernel.binary16`: NumPy's ``astype(np.float16)`` of
    the float32 map bit for bit) and, unless ``out`` is None, as float32 into ``out`` too; a
    block of :data:`BLOCK` texels at a time (gathered, then rounded in a loop that vectorizes)."""
    none = uint64(NOT_COVERED)
    block = np.empty(BLOCK, np.float32)
    bits = block.view(np.uint32)
    for s in range(uint64(lo), uint64(hi), uint64(BLOCK)):
        n = min(uint64(BLOCK), uint64(hi) - s)
        for j in range(n):
            q = uint64(inverse[s + j])
            block[j] = values[q] if q != none else np.float32(0)
        if out is not None:
            for j in range(n):
                out[s + j] = block[j]
        for j in range(n):
            half[s + j] = binary16(bits[j], block[j])

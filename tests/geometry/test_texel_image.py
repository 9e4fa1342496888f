"""Tests for service.geometry.texel_image: a band's values written into its map texel by
texel, pinned against the zero-filled NumPy scatter it replaced (issue 23)."""

import numpy as np
import pytest

from service.geometry.texel_image import BLOCK, NOT_COVERED, band_image, band_image_half, inverse_index


def test_band_image_is_the_zero_filled_scatter_bit_for_bit_over_any_ranges():
    rng = np.random.default_rng(0)
    H = 37
    index = rng.permutation(H * H)[: H * H // 2]                   # a band in an order of its own
    values = rng.normal(size=len(index)).astype(np.float32)
    values[:3] = [np.nan, -0.0, np.inf]
    want = np.zeros(H * H, np.float32)
    want[index] = values
    inverse = inverse_index(index, H * H)
    assert inverse.dtype == np.uint32 and (inverse == NOT_COVERED).sum() == H * H - len(index)
    out = np.full(H * H, 7.0, np.float32)                            # dirty: every texel is written
    cuts = [0, 1, 100, 100, 800, H * H]
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        band_image(lo, hi, inverse, values, out)
    assert np.array_equal(out.view(np.uint32), want.view(np.uint32))


def test_band_image_writes_float16_bits_as_numpy_rounds_the_float32_map():
    """Issue 23: band_image_half writes the same texels as float16 bits, beside the float32
    map or alone, NumPy's ``astype(np.float16)`` of the float32 map bit for bit (specials
    too), over ranges that start and end inside its blocks."""
    rng = np.random.default_rng(1)
    H = 41
    index = rng.permutation(H * H)[: H * H // 2]
    values = (rng.normal(size=len(index)) * np.logspace(-9, 5, len(index))).astype(np.float32)
    values[:5] = [np.nan, -0.0, -np.inf, 7e4, 65520.0]
    want = np.zeros(H * H, np.float32)
    want[index] = values
    with np.errstate(over="ignore", invalid="ignore"):
        want16 = want.astype(np.float16).view(np.uint16)
    inverse = inverse_index(index, H * H)
    out, both, alone = np.full(H * H, 7.0, np.float32), np.full(H * H, 7, np.uint16), np.full(H * H, 7, np.uint16)
    cuts = [0, 1, BLOCK + 44, BLOCK + 44, 3 * BLOCK, H * H]
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        band_image_half(lo, hi, inverse, values, out, both)
        band_image_half(lo, hi, inverse, values, None, alone)
    assert np.array_equal(out.view(np.uint32), want.view(np.uint32))
    assert np.array_equal(both, want16) and np.array_equal(alone, want16)
    assert (want16 != 0).sum() > len(index) // 2


def test_inverse_index_is_the_position_in_the_band():
    index = np.array([5, 0, 3])
    np.testing.assert_array_equal(inverse_index(index, 6), [1, NOT_COVERED, NOT_COVERED, 2, NOT_COVERED, 0])
    with pytest.raises(IndexError):
        inverse_index(np.array([6]), 6)

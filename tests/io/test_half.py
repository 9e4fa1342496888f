"""service.io.half.to_float16 (compiled) and to_float16_blocks (NumPy) against NumPy's
astype(float16), bit for bit."""

import numpy as np
import pytest

from service.io.half import to_float16, to_float16_blocks

BOTH = pytest.mark.parametrize("convert", [to_float16, to_float16_blocks])


def _bits(values: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(values).view(np.uint16)


def _numpy(values: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        return values.astype(np.float16)


@BOTH
def test_every_exponent_and_rounding_case_matches_numpy(convert):
    # the top 16 bits (sign, exponent, 7 mantissa bits) all 65536 ways, the low 16 bits
    # every combination of the kept bits 13-15 (odd/even) with the rounding bit 12 and the
    # sticky bits 0-11 (none, lowest, highest, all): every tie and near-tie of every binade
    hi = np.arange(1 << 16, dtype=np.uint32) << 16
    lo = np.array(sorted({b12 | kept | sticky for b12 in (0, 0x1000)
                          for kept in (0, 0x2000, 0x4000, 0x6000, 0x8000, 0xE000)
                          for sticky in (0, 1, 0x800, 0xFFF)}), np.uint32)
    x = (hi[:, None] | lo[None, :]).reshape(-1).view(np.float32)
    got, want = convert(x), _numpy(x)
    assert got.dtype == np.float16 and got.shape == x.shape
    mismatch = np.flatnonzero(_bits(got) != _bits(want))
    assert mismatch.size == 0, [hex(b) for b in x.view(np.uint32)[mismatch[:5]]]
    # the cases exist: float16 subnormals, ties rounded up and down, overflow to inf, NaN
    assert np.isinf(got).sum() > 0 and np.isnan(got).sum() > 0
    assert ((got != 0) & (np.abs(got) < 2.0 ** -14)).sum() > 1000


@pytest.mark.parametrize("block", [1, 7, 1 << 16, None])
def test_map_like_values_any_block_and_shape(block):
    rng = np.random.default_rng(3)
    maps = rng.standard_normal((2, 64, 48, 3)).astype(np.float32)
    maps[:, :10] = 0.0                                   # outside the UV charts
    maps[:, 10:20] *= 1e-6                               # float16 subnormals
    maps[0, 0, 0] = [np.nan, np.inf, -70000.0]
    maps[1, 0, 0] = [65519.0, 65520.0, -0.0]             # just below / at the overflow
    view = maps[:, :, ::-1]                              # a non-contiguous view
    got = to_float16(view) if block is None else to_float16_blocks(view, block=block)
    want = _numpy(maps[:, :, ::-1])
    assert got.shape == want.shape and got.flags.c_contiguous
    np.testing.assert_array_equal(_bits(got), _bits(want))
    assert float(got[1, 0, -1, 0]) == 65504.0 and np.isinf(got[1, 0, -1, 1])


@BOTH
def test_empty_and_scalar(convert):
    assert convert(np.zeros((0, 3), np.float32)).shape == (0, 3)
    assert _bits(convert(np.float32(1.0 / 3.0)).reshape(1)).tolist() == [0x3555]


def test_out_is_written_in_place():
    x = np.random.default_rng(5).standard_normal((4, 5, 3)).astype(np.float32)
    x[0, 0] = [np.inf, 7e4, np.nan]
    buffer = np.full(x.size + 2, 0xFFFF, np.uint16)
    got = to_float16(x[:, ::-1], out=buffer[1:-1])
    assert np.shares_memory(got, buffer) and got.shape == (4, 5, 3)
    np.testing.assert_array_equal(_bits(got), _bits(_numpy(x[:, ::-1])))
    assert buffer[0] == buffer[-1] == 0xFFFF
    with pytest.raises(ValueError, match="out holds 3 values for 60"):
        to_float16(x, out=np.empty(3, np.float16))


@BOTH
def test_other_dtypes_round_once_as_numpy_does(convert):
    """float64 goes to float16 directly (NumPy's single rounding), not through float32."""
    x = np.array([1 + 2.0 ** -11 + 2.0 ** -40, -65519.9, 1e-9, np.inf, np.nan])  # ties after float32
    got = convert(x)
    with np.errstate(over="ignore"):
        expected = x.astype(np.float16)
    assert got.view(np.uint16).tolist() == expected.view(np.uint16).tolist()
    assert convert(x[:1])[0] != np.float32(x[0]).astype(np.float16)    # the double rounding avoided

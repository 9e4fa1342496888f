"""Tests for service.geometry.normal_texels: the compiled per-texel pass of the normal mapper,
pinned bit for bit against the NumPy passes it replaced (issue 23)."""

import numpy as np

from service.geometry.normal_map import _EPS, NormalMapper
from service.geometry.normal_texels import BLOCK, FLAT, FLAT_HALF, flat_runs, normal_texels
from service.geometry.tangent_frames import tangent_frames
from service.geometry.uv_raster import rasterize_uv
from tests.geometry.test_normal_map import _numpy_normal_map, cylinder


def _inputs(mapper, h, V, frames):
    """The kernel's arguments after (lo, hi), as NormalMapper.normal_map passes them."""
    hf = np.asarray(h).reshape(-1)
    TN = np.empty((6, mapper.n), np.float32)
    TN[:3] = frames[:, 0].T
    TN[3:] = frames[:, 2].T
    return (mapper._texel, mapper._triangle, mapper._lam, mapper._corners, mapper._code, mapper._scales,
            mapper.shape[1], hf, mapper.gradient_operators(V), TN, _EPS)


def _cylinder_case(seed):
    st, V, F = cylinder()
    H, W = 48, 64
    mapper = NormalMapper(rasterize_uv(st, F, H, W), F, st, F, len(V))
    frames = tangent_frames(V, F, st, F).astype(np.float32)
    h = 0.2 * np.random.default_rng(seed).normal(size=(H, W))
    return mapper, h, V, frames


def test_blocked_kernel_over_any_ranges_is_the_numpy_pass_bit_for_bit():
    """Ranges that start and end inside blocks, a range shorter than a block, an empty one:
    every covered texel is the NumPy pass's, bit for bit, and no other texel is written."""
    mapper, h, V, frames = _cylinder_case(1)
    N = len(mapper.texels)
    assert N > 3 * BLOCK
    ref = _numpy_normal_map(mapper, h, V, frames).reshape(-1, 3)
    out = np.full(ref.shape, np.nan, np.float32)
    cuts = [0, 1, 5, 5, BLOCK + 3, 2 * BLOCK + 3, 2 * BLOCK + 4, N - 7, N]
    args = _inputs(mapper, h, V, frames)
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        normal_texels(lo, hi, *args, out)
    covered = np.zeros(len(out), bool)
    covered[mapper.texels] = True
    assert np.array_equal(out[covered].view(np.uint32), ref[covered].view(np.uint32))
    assert np.isnan(out[~covered]).all()


def test_degenerate_and_nan_frames_follow_the_numpy_clamp():
    """Zero frames (|T×N|² = 0 < eps: the clamp), opposite tangents and NaN frames (NaN kept,
    as np.maximum keeps it) at some vertices: the same bits, NaN where NumPy has NaN."""
    mapper, h, V, frames = _cylinder_case(2)
    rng = np.random.default_rng(3)
    frames = frames.copy()
    k = len(frames)
    frames[: k // 3] = 0.0                                   # whole triangles: T×N = 0
    frames[rng.choice(k, k // 10, replace=False), :2] *= -1
    frames[rng.choice(k, 3, replace=False), 0, 1] = np.nan
    ref = _numpy_normal_map(mapper, h, V, frames).reshape(-1, 3)
    out = np.zeros_like(ref)
    out[:, 2] = 1.0
    normal_texels(0, len(mapper.texels), *_inputs(mapper, h, V, frames), out)
    flat = (ref[mapper.texels] == [0, 0, 1]).all(axis=1)      # clamped: slopes 0 despite h
    assert np.isnan(ref).any() and flat.sum() > len(mapper.texels) // 10
    assert np.array_equal(out.view(np.uint32), ref.view(np.uint32))


def test_float16_bits_out_is_the_float32_pass_rounded_by_numpy():
    """A uint16 ``out`` takes each texel's normal as float16 bits (NaN and clamped texels
    included), ``astype(np.float16)`` of the float32 pass bit for bit; the uncovered runs
    take FLAT_HALF, (0, 0, 1)."""
    mapper, h, V, frames = _cylinder_case(4)
    frames = frames.copy()
    frames[:40] = 0.0
    frames[40:43, 0, 1] = np.nan
    args = _inputs(mapper, h, V, frames)
    full, bits = np.zeros((h.size, 3), np.float32), np.full((h.size, 3), 0xFFFF, np.uint16)
    for lo, hi in ((0, 5), (5, BLOCK + 9), (BLOCK + 9, len(mapper.texels))):
        normal_texels(lo, hi, *args, full)
        normal_texels(lo, hi, *args, bits)
    runs = np.array([[0, 7], [100, 140]], np.uint32)                 # as if uncovered
    flat_runs(0, len(runs), runs, full, FLAT)
    flat_runs(0, len(runs), runs, bits, FLAT_HALF)
    assert np.isnan(full).any() and (full == FLAT).all(axis=1).sum() >= 47
    assert np.array_equal(bits, full.astype(np.float16).view(np.uint16))

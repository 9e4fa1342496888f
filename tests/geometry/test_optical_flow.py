"""Tests for service.geometry.optical_flow: flows on a synthetic shift, NCC confidence, warping."""

import numpy as np
import pytest
from scipy import ndimage

from service.geometry import optical_flow as of

SHIFT = np.array([2.5, -1.25])          # (dx, dy) texels


def texture(seed, n=160):
    """Pore-like random texture: dark blobs on a speckled, slowly varying base."""
    rng = np.random.default_rng(seed)
    img = 0.5 + 0.15 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 1.2) * 4
    img += 0.1 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 12) * 12
    return img


def shifted_pair(seed=0):
    """reference(x) = moving(x + SHIFT), so the backward flow is SHIFT everywhere."""
    moving = texture(seed)
    H, W = moving.shape
    grid = of.flow_to_coords(np.zeros((H, W, 2), np.float32))
    reference = of.remap(moving, grid + SHIFT.astype(np.float32))
    return reference, moving


def interior(a, m=16):
    return a[m:-m, m:-m]


# (the reference is a bilinear resampling, i.e. slightly blurred; the refined flow's bicubic
# residual pass does not reproduce that blur: 0.058 texel here, 0.07 on sharp sample scans)
@pytest.mark.parametrize("method, tol", [("dis", 0.05), ("refined", 0.08), ("farneback", 0.1)])
def test_flow_recovers_a_synthetic_shift(method, tol):
    ref, mov = shifted_pair()
    r8, m8 = of.to_uint8(ref, mov)
    flow = {"dis": lambda: of.dis_flow(r8, m8, finest_scale=0),
            "refined": lambda: of.refined_flow(r8, m8),
            "farneback": lambda: of.farneback_flow(r8, m8)}[method]()
    err = np.linalg.norm(interior(flow) - SHIFT, axis=-1)
    assert flow.shape == ref.shape + (2,) and flow.dtype == np.float32
    assert np.median(err) < tol


def test_ncc_confidence_high_on_the_shift_and_low_on_unrelated_images():
    ref, mov = shifted_pair()
    r8, m8 = of.to_uint8(ref, mov)
    flow = of.refined_flow(r8, m8)
    good = of.ncc_confidence(ref, of.warp(mov, flow))
    other = texture(seed=7)
    bad = of.ncc_confidence(ref, other)
    assert np.median(interior(good)) > 0.95
    assert np.median(interior(bad)) < 0.2
    assert good.dtype == np.float32 and 0.0 <= bad.min() and good.max() <= 1.0


def test_ncc_is_invariant_to_gain_and_offset_and_zero_for_inverted_images():
    a = texture(3)
    np.testing.assert_allclose(of.ncc_confidence(a, 2.0 * a + 3.0, smooth_sigma=0), 1.0, atol=1e-3)
    assert of.ncc_confidence(a, -a, smooth_sigma=0).max() == 0.0
    mask = np.zeros(a.shape, bool)
    mask[20:100, 30:120] = True
    c = of.ncc_confidence(a, a, mask=mask)
    assert c[~mask].max() == 0.0 and c[mask].min() > 0.99      # outside the mask: 0, no bleed


def test_identical_images_give_zero_flow():
    a = texture(1)
    a8, _ = of.to_uint8(a, a)
    for flow in (of.dis_flow(a8, a8, finest_scale=0), of.refined_flow(a8, a8)):
        assert np.abs(flow).max() == 0.0
    # OpenCV's Farneback is not exactly zero at the image border (up to 0.16 texel here)
    assert np.abs(interior(of.farneback_flow(a8, a8))).max() < 1e-3


def test_warp_by_zero_flow_is_the_identity_and_constant_flows_compose_by_adding():
    a = texture(2)
    np.testing.assert_array_equal(of.warp(a, np.zeros(a.shape + (2,), np.float32)), a.astype(np.float32))
    f1 = np.broadcast_to(np.float32([1.5, -0.5]), a.shape + (2,))
    f2 = np.broadcast_to(np.float32([0.25, 2.0]), a.shape + (2,))
    np.testing.assert_allclose(of.compose_flows(f1, f2), f1 + f2, atol=1e-6)
    # warping twice equals warping once by the composition (linear image: bilinear is exact)
    ramp = np.add.outer(0.3 * np.arange(64.0), 0.7 * np.arange(64.0))
    twice = of.warp(of.warp(ramp, f1[:64, :64]), f2[:64, :64])
    once = of.warp(ramp, of.compose_flows(f1[:64, :64], f2[:64, :64]))
    np.testing.assert_allclose(interior(twice, 4), interior(once, 4), atol=1e-4)


def test_remap_and_sample_agree_and_handle_many_channels_and_long_point_lists():
    img = np.random.default_rng(0).random((20, 30, 5))
    xy = np.random.default_rng(1).uniform(0, 19, (40_000, 2))
    pts = of.sample(img, xy)
    assert pts.shape == (40_000, 5)
    x0, y0 = np.floor(xy[0]).astype(int)
    fx, fy = xy[0] - [x0, y0]
    expect = ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
              + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])
    np.testing.assert_allclose(pts[0], expect, atol=1e-3)
    assert np.all(of.sample(img[..., 0], [[-5.0, 3.0]], border=-1.0) == -1.0)


def test_to_uint8_shares_one_range_and_flows_reject_float_images():
    a = np.linspace(0, 1, 64 * 64).reshape(64, 64)
    a8, b8 = of.to_uint8(a, 0.5 * a, percentile=0)
    assert a8.max() == 255 and b8.max() == 128            # the second image is half as bright
    with pytest.raises(ValueError, match="uint8"):
        of.dis_flow(a, a)
    with pytest.raises(ValueError, match="one size"):
        of.dis_flow(a8, a8[:32])

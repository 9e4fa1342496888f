"""Tests for service.methods.correspondence.texture: over-sharpening, masks, pinned dots."""

import numpy as np

from service.methods.correspondence.texture import (
    flow_texture,
    luminance,
    oversharpen,
    pin_dots,
)


def test_oversharpen_keeps_constants_up_to_the_mask_border_and_amplifies_detail():
    mask = np.zeros((40, 40), bool)
    mask[5:35, 8:30] = True
    const = np.full((40, 40), 0.4)
    np.testing.assert_allclose(oversharpen(const, mask, 3.0, 2.0)[mask], 0.4, atol=1e-6)
    dot = const.copy()
    dot[20, 20] = 0.5
    sharp = oversharpen(dot, mask, 3.0, 2.0)
    assert abs(sharp[20, 20] - 0.4 - 3 * 0.1 + 2 * 0.1 / (2 * np.pi * 9)) < 2e-3   # 1 + k(1 − g(0))
    assert np.all(sharp[~mask] == 0.0)


def test_masks_and_pinned_points_are_black():
    albedo = np.full((32, 32, 3), 0.5)
    mask = np.ones((32, 32), bool)
    occ = np.zeros((32, 32), bool)
    occ[:4] = True
    tex = flow_texture(albedo, mask, 0.0, 0.0, occ, np.array([[10.2, 20.4]]), 2.0)
    assert np.all(tex[:4] == 0) and tex[20, 10] == 0 and tex[20, 13] == 0.5
    assert np.isclose(luminance(albedo), 0.5).all()
    assert pin_dots(np.array([[5.0, 5.0]]), (12, 12), 2.0).sum() == 13      # |dx|²+|dy|² ≤ 4

"""Tests for service.methods.correspondence.accuracy."""

import numpy as np

from service.methods.correspondence.accuracy import summary, warp_errors


def test_warp_errors_in_texels_and_mm_for_a_known_offset():
    H = W = 32
    xs, ys = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    truth = np.stack([xs, ys], axis=-1)
    position = np.stack([0.25 * xs, 0.25 * ys, np.zeros_like(xs)], axis=-1)      # 0.25 mm/texel
    valid = np.zeros((H, W), bool)
    valid[5:20, 5:20] = True
    tex, mm = warp_errors(truth + [3.0, 4.0], truth, valid, position)
    assert len(tex) == 225
    np.testing.assert_allclose(tex, 5.0)
    np.testing.assert_allclose(mm, 1.25, atol=1e-5)
    s = summary(np.arange(101.0))
    assert s == {"median": 50.0, "p95": 95.0, "mean": 50.0}

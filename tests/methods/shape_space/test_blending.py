"""Tests for service.methods.shape_space.blending: eq. 4 of bermano2014."""

import numpy as np

from service.methods.shape_space.blending import active_frames, blend


def test_blend_is_eq_4():
    rng = np.random.default_rng(0)
    N, k, R, C = 7, 11, 3, 9
    values = rng.normal(size=(N, k, C)).astype(np.float32)
    omega = rng.uniform(size=(R, k))
    hat = omega / omega.sum(axis=0)
    W = np.zeros((R, N))
    W[0, [1, 4]] = [0.25, 0.75]
    W[1, 2] = 1.0
    W[2, [1, 6]] = [0.5, 0.5]
    got = blend(values, hat, W)
    want = np.zeros((k, C))
    for t in range(k):
        for r in range(R):
            for j in range(N):
                want[t] += hat[r, t] * W[r, j] * values[j, t]
    # float32 values are blended in float32 (their stored precision)
    np.testing.assert_allclose(got, want, rtol=0, atol=4 * np.finfo(np.float32).eps)
    np.testing.assert_allclose(blend(values.astype(np.float64), hat, W), want, rtol=1e-12)
    assert active_frames(W).tolist() == [1, 2, 4, 6]


def test_one_frame_everywhere_returns_that_frame():
    values = np.random.default_rng(1).normal(size=(4, 5, 9)).astype(np.float32)
    W = np.zeros((2, 4))
    W[:, 3] = 1.0
    hat = np.full((2, 5), 0.5)
    np.testing.assert_array_equal(blend(values, hat, W), values[3].astype(np.float64))

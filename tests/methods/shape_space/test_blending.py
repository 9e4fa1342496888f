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


def _numpy_passes(values, omega_hat, weights, scale=None):
    """The NumPy passes the compiled sum replaced (one product and one sum per active frame)."""
    weights = np.asarray(weights, dtype=np.float64)
    K = active_frames(weights, 0.0)
    WK = weights[:, K] if scale is None else weights[:, K] * np.asarray(scale, np.float64)[K]
    dtype = np.result_type(values.dtype, np.float32)
    omega_hat = np.asarray(omega_hat)
    if omega_hat.dtype != dtype:
        omega_hat = omega_hat.astype(np.float64)
    coef = (WK.T.astype(omega_hat.dtype) @ omega_hat).astype(dtype, copy=False)
    out = np.zeros(values.shape[1:], dtype)
    tmp = np.empty_like(out)
    for j, k in enumerate(K):
        np.multiply(values[k], coef[j, :, None], out=tmp)
        out += tmp
    return out.astype(np.float64)


def test_compiled_sum_is_the_numpy_passes_bit_for_bit():
    """issue 23: the compiled per-element sum (blend_kernel) equals the NumPy passes it
    replaced bit for bit, for int16 (quantized maps, scale folded in), float32 (detail) and
    float64 values, float64 or compute-precision region weights, more elements than a block."""
    rng = np.random.default_rng(3)
    N, k, R = 40, 2500, 4
    W = np.zeros((R, N))
    for r in range(R):
        idx = rng.choice(N, size=6, replace=False)
        W[r, idx] = rng.dirichlet(np.ones(6))
    omega = rng.uniform(size=(R, k))
    hat = omega / omega.sum(axis=0)
    q = rng.integers(-32767, 32768, size=(N, k, 1)).astype(np.int16)
    scale = rng.uniform(1e-6, 1e-4, size=N).astype(np.float32)
    cases = [(rng.normal(size=(N, k, 9)).astype(np.float32), hat, None),
             (rng.normal(size=(N, k, 9)).astype(np.float32), hat.astype(np.float32), None),
             (rng.normal(size=(N, k, 3)), hat, None),
             (q, hat.astype(np.float32), scale), (q, hat, scale)]
    for values, omega_hat, s in cases:
        want = _numpy_passes(values, omega_hat, W, s)
        got = blend(values, omega_hat, W, s)
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, want)
        got32 = blend(values, omega_hat, W, s, dtype=np.float32)
        assert got32.dtype == np.float32
        np.testing.assert_array_equal(got32, want.astype(np.float32))
    half = rng.normal(size=(N, k, 1)).astype(np.float16)        # older models' maps: NumPy passes
    np.testing.assert_array_equal(blend(half, hat, W), _numpy_passes(half, hat, W))

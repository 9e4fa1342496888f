"""Locally weighted marker regression (service/geometry/marker_regression.py)."""

import numpy as np

import scipy.sparse as sp

from service.geometry.marker_regression import MarkerRegression, fit, marker_weights


def _data(seed=0, T=40, M=5, n=7):
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(M, 3)) * 10.0
    verts = rng.normal(size=(n, 3)) * 10.0
    u = rng.normal(size=(T, M, 3))
    return rng, rest, verts, u


def test_recovers_a_linear_map_with_wide_weights():
    """Offsets exactly linear in the markers, weights ≈ 1 everywhere: the ridge → 0 fit
    predicts new frames to 3e-5 of their largest offset (P's int16 quantization, float32)."""
    rng, rest, verts, u = _data()
    T, M, n = len(u), len(rest), len(verts)
    Btrue = rng.normal(size=(3 * n, 3 * M))
    c = rng.normal(size=(n, 3))
    Y = (u.reshape(T, -1) @ Btrue.T).reshape(T, n, 3) + c
    reg = fit(u, Y, verts, rest, radius=1e6, ridge=1e-12)
    new = rng.normal(size=(3, M, 3))
    want = (new.reshape(3, -1) @ Btrue.T).reshape(3, n, 3) + c
    assert np.abs(reg(new) - want).max() < 3e-5 * np.abs(want).max()      # measured 2.0e-5


def test_mean_input_gives_mean_offset_and_locality():
    """u = ū gives ȳ exactly; a vertex's row only holds markers with g² ≥ cutoff."""
    rng, rest, verts, u = _data(1)
    Y = rng.normal(size=(len(u), len(verts), 3))
    reg = fit(u, Y, verts, rest, radius=8.0, ridge=1e-2, cutoff=0.05, tol=0.0)
    assert np.allclose(reg(u.mean(axis=0)[None])[0], Y.mean(axis=0), atol=1e-5)
    W = marker_weights(verts, rest, 8.0, 0.05).toarray() > 0
    L = np.abs(reg.L)                               # P Q: L to P's int16 quantization (≤ r/2 steps)
    used = L.reshape(len(verts), 3, len(rest), 3).max(axis=(1, 3)) > 1e-3 * L.max()
    assert not (used & ~W).any()
    # a marker outside every vertex's reach moves nothing
    far = u.mean(axis=0)[None].copy()
    unused = np.flatnonzero(~W.any(axis=0))
    if len(unused):
        far[0, unused] += 100.0
        assert np.allclose(reg(far)[0], Y.mean(axis=0), atol=1e-4)


def test_an_anchored_fit_passes_through_the_anchor_and_recovers_a_linear_map():
    """Anchored at y₀: u = 0 gives y₀ exactly (the neutral), and offsets y₀ + B u with wide
    weights are recovered on new frames although the training frames' mean is not 0."""
    rng, rest, verts, u = _data(2)
    T, M, n = len(u), len(rest), len(verts)
    u = u + 3.0                                                  # mean far from the rest pose
    Btrue = rng.normal(size=(3 * n, 3 * M))
    y0 = rng.normal(size=(n, 3))
    Y = (u.reshape(T, -1) @ Btrue.T).reshape(T, n, 3) + y0
    reg = fit(u, Y, verts, rest, radius=1e6, ridge=1e-12, anchor=y0)
    np.testing.assert_array_equal(reg(np.zeros((1, M, 3)))[0], y0.astype(np.float32))
    new = rng.normal(size=(3, M, 3))
    want = (new.reshape(3, -1) @ Btrue.T).reshape(3, n, 3) + y0
    assert np.abs(reg(new) - want).max() < 1e-3
    # without the anchor the same data's fit need not pass through y₀ at rest once noise is added
    Yn = Y + rng.normal(0.0, 0.5, Y.shape)
    free = fit(u, Yn, verts, rest, radius=1e6, ridge=1e-2)
    held = fit(u, Yn, verts, rest, radius=1e6, ridge=1e-2, anchor=y0)
    assert np.abs(free(np.zeros((1, M, 3)))[0] - y0).max() > 1e-2
    np.testing.assert_array_equal(held(np.zeros((1, M, 3)))[0], y0.astype(np.float32))


def test_the_rank_truncation_keeps_the_singular_values_above_tol():
    """L = U diag(σ) Vᵀ with σ = 10, 5, 1, 0.05, 0.01: tol = 1e-2 keeps σ > 0.1 (r = 3) and
    leaves L − P Q = the dropped terms, so ‖(L − P Q) u‖ ≤ σ₄ ‖u‖; tol = 0 keeps all five."""
    rng = np.random.default_rng(5)
    U, _ = np.linalg.qr(rng.normal(size=(12, 5)))
    V, _ = np.linalg.qr(rng.normal(size=(6, 5)))
    sigma = np.array([10.0, 5.0, 1.0, 0.05, 0.01])
    L = (U * sigma) @ V.T
    reg = MarkerRegression.from_matrix(L, np.zeros((2, 3)), np.zeros((4, 3), np.float32), tol=1e-2)
    assert reg.rank == 3 and reg.Pq.dtype == np.int16 and reg.P.dtype == reg.Q.dtype == np.float32
    np.testing.assert_allclose(reg.Q @ reg.Q.T, np.eye(3), atol=1e-6)
    step = reg.scale.max()                                         # P's quantization step
    np.testing.assert_allclose(reg.L, (U[:, :3] * sigma[:3]) @ V[:, :3].T, atol=3 * step)
    u = rng.normal(size=(20, 2, 3))
    err = np.linalg.norm((reg(u) - (u.reshape(20, 6) @ L.T).reshape(20, 4, 3)).reshape(20, -1), axis=1)
    assert (err <= (0.05 + 6 * step) * np.linalg.norm(u.reshape(20, -1), axis=1)).all()
    full = MarkerRegression.from_matrix(sp.csr_matrix(L), np.zeros((2, 3)), np.zeros((4, 3)), tol=0.0)
    assert full.rank == 5
    np.testing.assert_allclose(full.L, L, atol=5 * full.scale.max())


def test_the_factor_is_quantized_per_column_within_half_a_step():
    """P = Pq diag(scale): every entry within half a step of its column (scale = max|P[:,k]|
    / 32767, the largest entry exactly ±32767), a zero column kept at scale 1; the offsets are
    the int16 row products (int16_rows), the float64 product of the same factors to 1e-6."""
    rng = np.random.default_rng(6)
    P = rng.normal(size=(30, 4)) * np.array([1e-3, 1.0, 50.0, 0.0])
    Q = np.linalg.qr(rng.normal(size=(9, 4)))[0].T
    reg = MarkerRegression.from_factors(P, Q, rng.normal(size=(3, 3)), np.zeros((10, 3)))
    np.testing.assert_array_equal(np.abs(reg.Pq[:, :3]).max(axis=0), 32767)
    assert reg.scale[3] == 1.0 and not reg.Pq[:, 3].any()
    assert (np.abs(reg.P - P) <= 0.5 * reg.scale * (1 + 1e-6) + 1e-12).all()
    u = rng.normal(size=(2, 3, 3))
    want = ((u - reg.mean_u).reshape(2, -1) @ Q.T.astype(np.float32).astype(np.float64)
            * reg.scale.astype(np.float64)) @ reg.Pq.T.astype(np.float64)
    np.testing.assert_allclose(reg(u), want.reshape(2, 10, 3), atol=1e-6 * np.abs(want).max())

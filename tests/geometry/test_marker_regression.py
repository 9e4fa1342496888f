"""Locally weighted marker regression (service/geometry/marker_regression.py)."""

import numpy as np

from service.geometry.marker_regression import fit, marker_weights


def _data(seed=0, T=40, M=5, n=7):
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(M, 3)) * 10.0
    verts = rng.normal(size=(n, 3)) * 10.0
    u = rng.normal(size=(T, M, 3))
    return rng, rest, verts, u


def test_recovers_a_linear_map_with_wide_weights():
    """Offsets exactly linear in the markers, weights ≈ 1 everywhere: the ridge → 0 fit
    predicts new frames to 1e-4 mm (float32 storage)."""
    rng, rest, verts, u = _data()
    T, M, n = len(u), len(rest), len(verts)
    Btrue = rng.normal(size=(3 * n, 3 * M))
    c = rng.normal(size=(n, 3))
    Y = (u.reshape(T, -1) @ Btrue.T).reshape(T, n, 3) + c
    reg = fit(u, Y, verts, rest, radius=1e6, ridge=1e-12)
    new = rng.normal(size=(3, M, 3))
    want = (new.reshape(3, -1) @ Btrue.T).reshape(3, n, 3) + c
    assert np.abs(reg(new) - want).max() < 1e-4


def test_mean_input_gives_mean_offset_and_locality():
    """u = ū gives ȳ exactly; a vertex's row only holds markers with g² ≥ cutoff."""
    rng, rest, verts, u = _data(1)
    Y = rng.normal(size=(len(u), len(verts), 3))
    reg = fit(u, Y, verts, rest, radius=8.0, ridge=1e-2, cutoff=0.05)
    assert np.allclose(reg(u.mean(axis=0)[None])[0], Y.mean(axis=0), atol=1e-5)
    W = marker_weights(verts, rest, 8.0, 0.05).toarray() > 0
    used = np.abs(reg.L.toarray()).reshape(len(verts), 3, len(rest), 3).sum(axis=(1, 3)) > 0
    assert not (used & ~W).any()
    # a marker outside every vertex's reach moves nothing
    far = u.mean(axis=0)[None].copy()
    unused = np.flatnonzero(~W.any(axis=0))
    if len(unused):
        far[0, unused] += 100.0
        assert np.allclose(reg(far)[0], Y.mean(axis=0), atol=1e-5)


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

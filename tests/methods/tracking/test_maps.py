"""Blended per-frame maps (fyffe §7.3) from per-vertex scan weights."""

from __future__ import annotations

import numpy as np

from service.methods.tracking.maps import blend_maps


def test_blend_maps_mixes_the_scans_maps_by_the_vertex_weights():
    # one quad covering the UV square, two scans with constant maps 1 and 3
    F = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    maps = np.stack([np.full((8, 8), 1.0), np.full((8, 8), 3.0)])
    W = np.zeros((2, 4, 2))
    W[0, :, 0] = 1.0                       # frame 0: all scan 0
    W[1, :] = [0.25, 0.75]                 # frame 1: 1/4 · 1 + 3/4 · 3 = 2.5
    out = blend_maps(W, F, uv, F, maps)
    assert out.shape == (2, 8, 8)
    np.testing.assert_allclose(out[0], 1.0, atol=1e-6)
    np.testing.assert_allclose(out[1], 2.5, atol=1e-6)
    # weights varying over the mesh blend per texel: left edge scan 0, right edge scan 1
    W2 = np.array([[[1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [1.0, 0.0]]])
    row = blend_maps(W2, F, uv, F, maps)[0, 4]
    assert row[0] < 1.3 and row[-1] > 2.7 and np.all(np.diff(row) > 0)


def _grid(k=21):
    """A flat k×k vertex grid on [0,1]², triangulated, with itself as the UV layout."""
    x, y = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(k * k)]
    i = np.arange(k - 1)[:, None] * k + np.arange(k - 1)[None, :]
    i = i.ravel()
    F = np.r_[np.c_[i, i + 1, i + k + 1], np.c_[i, i + k + 1, i + k]]
    return V, F


def _stretch_left(V, factor):
    """x stretched by ``factor`` on the left half (x < 0.5), the right half shifted rigidly."""
    W = V.copy()
    W[:, 0] = np.where(V[:, 0] < 0.5, V[:, 0] * factor, 0.5 * factor + (V[:, 0] - 0.5))
    return W


def _rigid(V, deg, t):
    a = np.deg2rad(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return V @ R.T + t


def test_stress_similarity_picks_the_scan_stretched_like_the_frame():
    from service.methods.tracking.maps import stress_similarity
    V, F = _grid()
    rng = np.random.default_rng(0)
    left = V[:, 0] < 0.2                           # ≥ 5 rings from the stretch's edge
    # scans: the neutral, the left half stretched 10 %, and one the tracking did not register
    scans = np.stack([V, _stretch_left(V, 1.1), np.full_like(V, np.nan)])
    frames = np.stack([_rigid(V, 30, [5.0, 1, 2]),                       # the neutral, moved
                       _rigid(_stretch_left(V, 1.1), -20, [0, 3, 1])])   # scan 1's shape, moved
    frames = frames + rng.normal(0, 1e-4, frames.shape)
    K = stress_similarity(V, F, V[:, :2], F, frames, scans)
    assert K.shape == (2, len(V), 3)
    np.testing.assert_allclose(K.sum(axis=2), 1.0, atol=1e-5)
    assert np.all(K[..., 2] == 0)                  # unregistered scan
    # Shepard weights of the Green strain (p = 3): measured 0.999998 and 0.999997 on the left
    assert K[0, left, 0].min() > 0.99              # neutral frame → neutral on the left
    assert K[1, left, 1].min() > 0.99              # stretched frame → scan 1 on the left
    right = V[:, 0] > 0.8                          # both scans unstretched there: an even split
    np.testing.assert_allclose(K[:, right, 0], 0.5, atol=0.05)     # measured exactly 0.5


def test_stress_similarity_is_the_stress_blend_models_weights():
    # one surface-stress measure: the tracking's kernel is stress_blend's StressField and
    # shepard_weights, called with the tracking's parameters
    from service.geometry.surface_strain import StressField
    from service.methods.stress_blend.weights import shepard_weights
    from service.methods.tracking.maps import stress_similarity
    V, F = _grid(9)
    scans = np.stack([V, _stretch_left(V, 1.1), V * [1.0, 1.05, 1.0]])
    frames = np.stack([_stretch_left(V, 1.05), V * [1.02, 1.03, 1.0]])
    field = StressField.build(V, F, V[:, :2], F, 2)
    ref = shepard_weights(field.stress(frames), field.stress(scans), 4.0, 0.3)
    out = stress_similarity(V, F, V[:, :2], F, frames, scans, smoothing=2, power=4.0, global_weight=0.3)
    np.testing.assert_allclose(out, ref, atol=1e-6)


def test_stress_weighted_blend_reproduces_the_frames_map_and_beats_every_single_scan():
    # scan 1 stretched 10 % on the left half, scan 2 on the right half; each scan's map is 2
    # where it is stretched, 1 elsewhere (blood flow follows strain). The frame is stretched
    # everywhere: its map is 2 everywhere, which no single scan has (each is off by 0.5 on
    # average, the neutral by 1), but the stress-weighted blend is
    from service.methods.tracking.maps import stress_similarity
    V, F = _grid()
    right = V.copy()
    right[:, 0] = np.where(V[:, 0] < 0.5, V[:, 0], 0.5 + 1.1 * (V[:, 0] - 0.5))
    scans = np.stack([V, _stretch_left(V, 1.1), right])
    frame = V * [1.1, 1.0, 1.0]
    u = np.broadcast_to((np.arange(32) + 0.5) / 32, (32, 32))
    maps = np.stack([np.ones((32, 32)), 1.0 + (u < 0.5), 1.0 + (u >= 0.5)])
    truth = np.full((32, 32), 2.0)
    W = stress_similarity(V, F, V[:, :2], F, _rigid(frame, 10, [1.0, 2, 3])[None], scans)
    out = blend_maps(W, F, V[:, :2], F, maps)[0]
    away = np.abs(u - 0.5) > 0.2                                        # from the seam
    err = np.abs(out - truth)[away].mean()
    single = [np.abs(m - truth)[away].mean() for m in maps]
    np.testing.assert_allclose(single, [1.0, 0.5, 0.5])
    assert err < 1e-4, err                       # measured 6.5e-8 (the log edge-strain kernel of σ = 0.02 left ~1 % per other scan)
    assert np.abs(out - truth).mean() < min(np.abs(m - truth).mean() for m in maps) / 3


def test_combine_weights_falls_back_to_the_stress_kernel_where_no_scan_matches():
    from service.methods.tracking.maps import combine_weights
    strength = np.array([[[0.5, 0.5, 0.0], [0.0, 0.0, 0.0]]])        # vertex 1: no flow match
    shape = np.array([[[0.2, 0.8, 0.0], [0.1, 0.3, 0.6]]], np.float32)
    W = combine_weights(strength, shape)
    np.testing.assert_allclose(W[0, 0], [0.2, 0.8, 0.0], atol=1e-6)    # 0.5·0.2 : 0.5·0.8
    np.testing.assert_allclose(W[0, 1], [0.1, 0.3, 0.6], atol=1e-6)
    W = combine_weights(strength, None)                               # §7.3: the neutral
    np.testing.assert_allclose(W[0, 1], [1.0, 0.0, 0.0])

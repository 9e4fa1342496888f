"""Tests for service.geometry.marker_filter: Gaussian-weighted local polynomial smoothing."""

import numpy as np
import pytest

from service.geometry.marker_filter import filter_markers


def _signal(frames=300, fps=30.0):
    """Smooth 3-D trajectories of 2 markers (F,2,3), mm: sines of 0.5-0.7 Hz and a drift."""
    t = np.arange(frames) / fps
    a = np.stack([3 * np.sin(2 * np.pi * 0.5 * t), 2 * np.cos(2 * np.pi * 0.7 * t), 0.5 * t], -1)
    return np.stack([a, -a + 10.0], axis=1)


def test_polynomials_up_to_the_degree_pass_exactly_even_at_the_ends_and_over_gaps():
    t = np.arange(40, dtype=np.float64)
    x = np.stack([1 + 0.5 * t - 0.02 * t ** 2, 3 - t, 0 * t], -1)[:, None, :]
    gapped = x.copy()
    gapped[[10, 11]] = np.nan                                        # a 2-frame gap
    out = filter_markers(gapped, 2.0, degree=2)
    np.testing.assert_allclose(out, x, atol=1e-9)
    # degree 1 keeps lines exactly, but not the parabola
    lin = x.copy()
    lin[..., 0] = 1 + 0.5 * t[:, None]
    np.testing.assert_allclose(filter_markers(lin, 2.0, degree=1), lin, atol=1e-9)
    assert np.abs(filter_markers(x, 2.0, degree=1) - x).max() > 0.01


def test_white_noise_on_a_known_signal_is_reduced():
    """σ = 0.3 mm noise on smooth motion: RMS error 0.30 → below 0.15 mm (s = 2 frames,
    degree 2; white-noise gain of the kernel ≈ 0.48, plus a little bias)."""
    truth = _signal()
    rng = np.random.default_rng(0)
    noisy = truth + rng.normal(0, 0.3, truth.shape)
    out = filter_markers(noisy, 2.0)
    rms = np.sqrt(np.mean((out - truth) ** 2))
    assert np.sqrt(np.mean((noisy - truth) ** 2)) == pytest.approx(0.3, rel=0.05)
    assert rms < 0.15, rms
    # the noise of a constant signal falls by the kernel's white-noise gain (interior)
    flat = rng.normal(0, 1.0, (4000, 1, 3))
    gain = np.std(filter_markers(flat, 2.0)[50:-50])
    assert 0.40 < gain < 0.55, gain


def test_occlusion_short_gaps_are_filled_long_ones_stay_missing():
    truth = _signal()
    rng = np.random.default_rng(1)
    x = truth + rng.normal(0, 0.3, truth.shape)
    x[100:102, 0] = np.nan                   # 2 frames: filled from both sides
    x[200:240, 0] = np.nan                   # 40 frames: left to the spatial completion
    x[:, 1][5] = np.nan                      # the other marker's single missing frame
    out = filter_markers(x, 2.0)
    assert np.isfinite(out[100:102, 0]).all()
    assert np.abs(out[100:102, 0] - truth[100:102, 0]).max() < 0.5
    assert np.isnan(out[200:240, 0]).all()
    assert np.isfinite(out[:, 1]).all()
    visible = np.isfinite(x).all(axis=2)
    err = np.linalg.norm(out - truth, axis=-1)[visible]
    assert np.sqrt(np.mean(err ** 2)) < 0.3          # 3-D RMS was 0.3·√3 ≈ 0.52


def test_zero_window_and_bad_arguments():
    x = _signal(20)
    np.testing.assert_array_equal(filter_markers(x, 0.0), x)
    with pytest.raises(ValueError, match="frames, markers, 3"):
        filter_markers(x[..., :2], 2.0)
    with pytest.raises(ValueError, match="sigma_frames"):
        filter_markers(x, -1.0)
    with pytest.raises(ValueError, match="degree"):
        filter_markers(x, 2.0, degree=5)


def test_filter_performance_smooths_the_expression_under_a_shaking_head():
    """A head jittering by ~1 mm per frame (not smooth in time) over a smooth expression:
    filtering the world markers blurs the jitter into the surface; filtering in the
    head-aligned frame removes the noise and keeps each frame's pose."""
    from scipy.spatial.transform import Rotation

    from service.geometry.marker_filter import filter_performance

    rng = np.random.default_rng(2)
    F, M = 120, 40
    rest = rng.normal(0, 40.0, (M, 3))
    t = np.arange(F) / 30.0
    expr = np.sin(2 * np.pi * 0.5 * t)[:, None, None] * rng.normal(0, 2.0, (1, M, 3))
    R = Rotation.from_rotvec(rng.normal(0, 0.01, (F, 3))).as_matrix()          # ~0.6° jitter
    shift = rng.normal(0, 1.0, (F, 3))
    clean = np.einsum("fij,fmj->fmi", R, rest + expr) + shift[:, None]
    noisy = clean + rng.normal(0, 0.3, clean.shape)
    noisy[30:32, 5] = np.nan
    err = lambda x: np.sqrt(np.nanmean(np.sum((x - clean) ** 2, axis=-1)))    # noqa: E731
    assert err(noisy) == pytest.approx(0.3 * np.sqrt(3), rel=0.05)
    assert err(filter_markers(noisy, 2.0)) > err(noisy)                      # the jitter blurred in
    assert err(filter_performance(noisy, 2.0)) < 0.6 * err(noisy)
    np.testing.assert_allclose(filter_performance(clean, 0.0), clean)

"""Tests for service.geometry.marker_filter: Gaussian-weighted local polynomial smoothing."""

import numpy as np
import pytest

from service.geometry.marker_filter import AUTO_BANDWIDTHS, filter_markers, filter_markers_auto


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


def _onset_rest_and_sine(frames=300, fps=30.0):
    """(F,3,3) mm: a marker at rest that jumps by 8 mm in ~0.3 s at 4 s, a slow 3-D sine
    (:func:`_signal`'s first marker), a marker at rest."""
    t = np.arange(frames) / fps
    onset = np.stack([np.where(t < 4, 0.0, 8 * np.tanh((t - 4) * 6)), 0 * t, 0 * t], -1)
    return np.stack([onset, _signal(frames, fps)[:, 0], np.zeros_like(onset)], axis=1)


def test_auto_window_beats_every_fixed_window_of_the_take():
    """σ = 0.3 mm on a fast onset, a slow sine and a still marker: the risk-chosen windows
    beat every fixed window over the take (the onset needs a narrow window, the still
    marker the widest) and stay within 10 % of each marker's own best fixed window (an
    oracle that knows the truth)."""
    truth = _onset_rest_and_sine()
    noisy = truth + np.random.default_rng(3).normal(0, 0.3, truth.shape)
    rms = lambda x: np.sqrt(np.mean(np.sum((x - truth) ** 2, -1), axis=0))      # noqa: E731
    out, chosen = filter_markers_auto(noisy)
    fixed = np.stack([rms(filter_markers(noisy, s)) for s in AUTO_BANDWIDTHS[1:]])
    total = lambda e: np.sqrt(np.mean(e ** 2, axis=-1))                      # noqa: E731
    assert total(rms(out)) < total(fixed).min(), (total(rms(out)), total(fixed))
    assert (rms(out) < 1.1 * fixed.min(axis=0)).all(), (rms(out), fixed.min(axis=0))
    assert (rms(out) < 0.45 * rms(noisy)).all()
    # the onset's frames take narrower windows than the still marker's
    assert chosen[110:135, 0].mean() < chosen[110:135, 2].mean()
    assert chosen[:, 2].mean() > 6.0


def test_auto_keeps_clean_markers_and_matches_the_risk_it_estimates():
    """Noise-free motion is returned as given (σ̂ = 0: no window has less risk than the
    sample itself); SURE is unbiased: with σ known, the estimated risk of a fixed window
    over a still marker's noise equals its measured squared error on average."""
    truth = _onset_rest_and_sine()
    out, chosen = filter_markers_auto(truth)
    np.testing.assert_array_equal(out, truth)
    assert (chosen == 0).all()
    from service.geometry.marker_filter import _local_fit

    rng = np.random.default_rng(4)
    noise = rng.normal(0, 0.3, (2000, 50, 3))
    fit, hat = _local_fit(noise, 2.0, 2, None, None)
    sure = np.sum(noise ** 2, -1) - 2 * np.sum(noise * fit, -1) + np.sum(fit ** 2, -1) \
        - 3 * 0.09 + 6 * 0.09 * hat                              # ‖x − x̂‖² − 3σ² + 6σ²h
    assert np.mean(sure) == pytest.approx(np.mean(np.sum(fit ** 2, -1)), rel=0.02)


def test_auto_fills_short_gaps_where_it_smooths_and_passes_through_filter_performance():
    truth = _onset_rest_and_sine()
    noisy = truth + np.random.default_rng(5).normal(0, 0.3, truth.shape)
    noisy[50:52, 2] = np.nan                               # inside the still marker's wide windows
    out = filter_markers(noisy, "auto")
    assert np.isfinite(out[50:52, 2]).all() and np.abs(out[50:52, 2]).max() < 0.3
    from service.geometry.marker_filter import filter_performance

    rng = np.random.default_rng(6)
    clean = rng.normal(0, 40.0, (20, 3)) + np.repeat(truth, 7, axis=1)[:, :20]
    world = clean + rng.normal(0, 0.3, clean.shape)
    err = lambda x: np.sqrt(np.nanmean(np.sum((x - clean) ** 2, -1)))           # noqa: E731
    assert err(filter_performance(world, "auto")) < min(0.5 * err(world),
                                                        err(filter_performance(world, 3.0)))
    with pytest.raises(ValueError, match="auto"):
        filter_markers(noisy, "smooth")


def _modes_take(frames=240, markers=30, seed=7):
    """A take whose expression lives in 3 known orthonormal directions of the 3M marker
    coordinates (a fast onset, a slow sine and a slower one), σ = 0.3 mm noise on it, and
    a basis whose first columns are those directions (the rest: any orthonormal
    completion), as a prior's modes would be."""
    rng = np.random.default_rng(seed)
    n = 3 * markers
    basis, _ = np.linalg.qr(rng.normal(size=(n, n)))
    t = np.arange(frames) / 30.0
    amplitudes = np.stack([6 * np.tanh((t - 4) * 6), 4 * np.sin(2 * np.pi * 0.5 * t),
                           3 * np.sin(2 * np.pi * 0.2 * t)], -1)               # (F,3) mm
    truth = (amplitudes @ basis[:, :3].T).reshape(frames, markers, 3)
    noisy = truth + rng.normal(0, 0.3, truth.shape)
    return truth, noisy, basis


def test_filter_modes_in_the_identity_basis_is_the_per_coordinate_filter():
    from service.geometry.marker_filter import MODE_BANDWIDTHS, filter_modes

    _, noisy, _ = _modes_take(frames=90, markers=6)
    expected, _ = filter_markers_auto(noisy, 0.3, MODE_BANDWIDTHS)
    np.testing.assert_array_equal(filter_modes(noisy, np.eye(18), 0.3), expected)


def test_filter_modes_takes_the_noise_of_the_still_modes_away():
    """Three moving modes among 90: per coordinate every window must follow the onset; per
    mode the 87 still ones take the widest window. 3-D RMS error against the truth (seeded):
    per coordinate ~0.29 mm, per mode ~0.13 (bound 0.6×)."""
    from service.geometry.marker_filter import filter_modes

    truth, noisy, basis = _modes_take()
    rms = lambda x: np.sqrt(np.mean(np.sum((x - truth) ** 2, -1)))             # noqa: E731
    per_coordinate = rms(filter_markers_auto(noisy)[0])
    per_mode = rms(filter_modes(noisy, basis))
    assert per_mode < 0.8 * per_coordinate, (per_mode, per_coordinate)
    with pytest.raises(ValueError, match="basis"):
        filter_modes(noisy, basis[:-3, :-3])


def test_filter_performance_in_modes_under_head_motion_and_occlusion():
    """World markers of the take under a moving head: ``"auto"`` with the modes aligns each
    frame onto the modes' rest with their weights, filters the complete frames per mode and
    puts each pose back — better than per coordinate (the shape's 3-D RMS error, seeded: 0.118
    against 0.141 mm; bound 0.9×); a frame with an occluded marker gets the per-coordinate
    fit (the same alignment weights: the same values but where σ̂, a median over the
    coordinate axes, moved with the frame's orientation and chose another window: 0.04 mm
    on one marker here)."""
    from scipy.spatial.transform import Rotation

    from service.geometry.marker_filter import MarkerModes, filter_performance
    from service.geometry.marker_prior import MarkerPrior
    from service.geometry.rigid import rigid_align

    truth, noisy, basis = _modes_take()
    F, M, _ = truth.shape
    rng = np.random.default_rng(8)
    rest = rng.normal(0, 40.0, (M, 3))
    weights = rng.uniform(0.5, 1.0, M)
    # a prior whose eigenvectors are the basis (eigenvalues decreasing along it)
    covariance = (basis * np.geomspace(100.0, 0.01, 3 * M)) @ basis.T
    modes = MarkerModes.of(rest, MarkerPrior(np.zeros((M, 3)), covariance), weights)
    assert MarkerModes.of(rest, None, weights) is None
    np.testing.assert_allclose(np.abs(np.sum(modes.vectors[:, :3] * basis[:, :3], axis=0)), 1.0, atol=1e-9)
    R = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.01, (F, 3)), axis=0)).as_matrix()
    shift = np.cumsum(rng.normal(0, 0.5, (F, 3)), axis=0)
    world = lambda x: np.einsum("fij,fmj->fmi", R, rest + x) + shift[:, None]     # noqa: E731
    clean, observed = world(truth), world(noisy)
    observed[100:103, 4] = np.nan
    def err(x):    # of the shape: each frame rigidly fitted to the truth first (the pose is as measured)
        fitted = np.stack([rigid_align(np.where(np.isfinite(f), f, np.nan), c).apply(f) for f, c in zip(x, clean)])
        return np.sqrt(np.nanmean(np.sum((fitted - clean) ** 2, -1)))

    in_modes = filter_performance(observed, "auto", modes=modes)
    per_coordinate = filter_performance(observed, "auto", weights=weights)
    assert err(in_modes) < 0.9 * err(per_coordinate), (err(in_modes), err(per_coordinate))
    np.testing.assert_allclose(in_modes[100:103], per_coordinate[100:103], atol=0.05)
    assert np.isnan(in_modes[100:103, 4]).all() == np.isnan(per_coordinate[100:103, 4]).all()
    from service.geometry.marker_filter import filter_modes

    gapped = noisy.copy()
    gapped[50, 3] = np.nan
    assert np.isnan(filter_modes(gapped, basis)[50]).all()
    # a fixed window is the same filter in any basis: the modes change nothing
    np.testing.assert_array_equal(filter_performance(observed, 2.0, modes=modes),
                                  filter_performance(observed, 2.0))


def test_the_oracle_choice_keeps_a_noise_free_take_and_bounds_sure_from_below():
    """``truth=``: each window chosen by its true error. Given the samples themselves as the
    truth, the sample (s = 0, no error) is chosen everywhere; given the clean take beside a
    noisy one, its error is below SURE's (seeded: 3-D RMS 0.152 against 0.159 mm) and per
    mode too (0.089 against 0.102)."""
    from service.geometry.marker_filter import filter_modes

    truth = _onset_rest_and_sine()
    noisy = truth + np.random.default_rng(3).normal(0, 0.3, truth.shape)
    out, chosen = filter_markers_auto(noisy, truth=noisy)
    np.testing.assert_array_equal(out, noisy)
    assert (chosen == 0).all()
    rms = lambda x, t: np.sqrt(np.mean(np.sum((x - t) ** 2, -1)))               # noqa: E731
    sure, oracle = filter_markers_auto(noisy)[0], filter_markers_auto(noisy, truth=truth)[0]
    assert rms(oracle, truth) < rms(sure, truth), (rms(oracle, truth), rms(sure, truth))
    truth, noisy, basis = _modes_take()
    assert rms(filter_modes(noisy, basis, truth=truth), truth) < rms(filter_modes(noisy, basis), truth)

"""The learned marker prior and its MAP denoiser (service/geometry/marker_prior.py)."""

import numpy as np
import pytest

from service.geometry.marker_prior import (
    AdaptiveDenoiser, MarkerDenoiser, MarkerPrior, PriorCompletion, PriorEigen, ShellDenoiser, floor_directions,
    frame_noise, gaspari_cohn, marker_denoiser, noise_confidence, shell_completion, temporal_noise,
)
from service.geometry.thin_shell import marker_noise_ratio, shell_prior_scale, soft_handles


def _grid_surface(n=8, spacing=10.0):
    """Markers on an n×n grid (mm) and a shell-like energy: the squared graph Laplacian
    (bending), whose null space holds the rigid translations."""
    g = np.arange(n) * spacing
    X, Y = np.meshgrid(g, g, indexing="ij")
    rest = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], axis=1)
    D = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
    A = (np.abs(D - spacing) < 1e-9).astype(float)
    L = np.diag(A.sum(1)) - A
    return rest, L @ L / spacing ** 4


def _modes(rest, centres, width=18.0):
    """Local smooth deformations (K,M,3): a Gaussian bump per centre, out of plane plus a
    little in plane (a left and a right 'brow' that training only shows together)."""
    out = []
    for c in centres:
        w = np.exp(-((rest[:, :2] - c) ** 2).sum(1) / (2 * width ** 2))
        out.append(np.stack([0.3 * w, 0.2 * w, w], axis=1) * 3.0)
    return np.asarray(out)


def _data(seed=0):
    rest, G = _grid_surface()
    left, right, mid = _modes(rest, [(15.0, 20.0), (55.0, 20.0), (35.0, 55.0)])
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, size=(60, 1))
    b = rng.uniform(0, 1, size=(60, 1))
    # training: the two sides together (symmetric) and the middle, one at a time
    train = np.concatenate([a[:, :, None] * (left + right), b[:, :, None] * mid])
    # held out: one side alone, combinations, amplitudes 30 % beyond training
    c = rng.uniform(0, 1.3, size=(40, 3))
    test = c[:, 0, None, None] * left + c[:, 1, None, None] * mid + 0.3 * c[:, 2, None, None] * right
    return rest, G, train, test, rng


def _rms(x):
    return float(np.sqrt(np.mean(x ** 2)))


def test_the_prior_denoises_better_than_interpolation_and_the_shell_prior():
    """Seeded: the learned prior (tapered, fitted on symmetric training) recovers held-out
    one-sided, combined and amplified deformations from σ = 0.3 mm noise far better than
    exact interpolation and than the shell prior alone at its best ratio."""
    rest, G, train, test, rng = _data()
    sigma = 0.3
    noisy = test + rng.normal(scale=sigma, size=test.shape)
    prior = MarkerPrior.fit_tapered(train, rest)
    den = MarkerDenoiser.build(prior, G, sigma, np.nan, shell_weight=0.0)
    e_interp = _rms(noisy - test)
    e_prior = _rms(den(noisy) - test)
    tau = shell_prior_scale(G, train)
    e_shell = min(_rms(soft_handles(G, noisy, marker_noise_ratio(s, tau)) - test) for s in (0.1, 0.3, 1.0))
    assert e_interp == pytest.approx(0.3, abs=0.01)
    assert e_prior < 0.35 * e_interp, (e_prior, e_interp)        # measured 0.070 vs 0.301
    assert e_prior < 0.6 * e_shell, (e_prior, e_shell)           # measured 0.070 vs 0.157
    # the plain PPCA of the same training crushes the one-sided deformation it never saw
    ppca = MarkerDenoiser.build(MarkerPrior.fit_ppca(train, 0.001), G, sigma, np.nan, 0.0)
    assert _rms(ppca(test) - test) > 2 * _rms(den(test) - test)   # measured 0.280 vs 0.034


def test_sigma_to_zero_is_exact_interpolation():
    rest, G, train, test, rng = _data(1)
    prior = MarkerPrior.fit_tapered(train, rest)
    u = test[:5] + rng.normal(scale=0.3, size=test[:5].shape)
    tiny = MarkerDenoiser.build(prior, G, 1e-6, 1.0)
    np.testing.assert_allclose(tiny(u), u, atol=1e-6)
    u[2, [3, 17]] = np.nan
    zero = MarkerDenoiser.build(prior, G, 0.0, np.nan)
    np.testing.assert_array_equal(zero(u), soft_handles(G, u, 0.0))       # the paper's solve
    out = tiny(u)
    np.testing.assert_allclose(np.delete(out[2], [3, 17], axis=0), np.delete(u[2], [3, 17], axis=0), atol=1e-6)


def test_occluded_markers_are_completed_by_the_prior():
    """NaN markers drop out of the data term; the prior completes them from the visible
    ones better than the shell's minimum-energy completion; a single frame (M,3) works;
    a frame with no visible marker is refused."""
    rest, G, train, test, rng = _data(2)
    prior = MarkerPrior.fit_tapered(train, rest)
    den = MarkerDenoiser.build(prior, G, 0.3, np.nan, 0.0)
    noisy = test + rng.normal(scale=0.3, size=test.shape)
    hidden = np.zeros(test.shape[:2], bool)
    hidden[:, 8:12] = True                                   # a burst over one row of markers
    hidden[::2, 40:44] = True                                # and, every other frame, another
    occluded = np.where(hidden[..., None], np.nan, noisy)
    out = den(occluded)
    assert np.isfinite(out).all()
    e_prior = _rms((out - test)[hidden])
    e_shell = _rms((soft_handles(G, occluded, 0.0) - test)[hidden])
    assert e_prior < 0.5 * e_shell, (e_prior, e_shell)           # measured 0.096 vs 0.236
    # the batched per-pattern solve equals the frame-by-frame one and the dense MAP
    # normal equations (D_V + σ²Q) x = D_V m + σ²Qμ solved directly
    np.testing.assert_allclose(den(occluded[1]), out[1], atol=1e-10)
    Q = prior.precision()
    d = np.repeat(~hidden[0], 3).astype(float)
    direct = np.linalg.solve(np.diag(d) + 0.09 * Q, d * np.nan_to_num(occluded[0].ravel()) + 0.09 * Q @ prior.mean.ravel())
    np.testing.assert_allclose(out[0].ravel(), direct, atol=1e-9)
    with pytest.raises(ValueError, match="all markers"):
        den(np.full((1,) + test.shape[1:], np.nan))


def test_tapered_covariance_keeps_near_and_drops_far_correlations_and_round_trips():
    rest, G, train, _, _ = _data()
    prior = MarkerPrior.fit_tapered(train, rest, length_fraction=0.5, floor_fraction=0.01)
    C, M = prior.covariance, len(rest)
    assert np.linalg.eigvalsh(C).min() > 0
    S = np.cov((train - train.mean(0)).reshape(len(train), -1).T, bias=True)
    D = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
    L = 0.5 * np.sqrt(((rest - rest.mean(0)) ** 2).sum(1).mean())
    far = np.kron(D >= 2 * L, np.ones((3, 3), bool))
    assert np.abs(S[far]).max() > 0.1 and np.abs(C[far]).max() == 0.0
    assert gaspari_cohn(np.array([0.0, 2.0, 3.0])).tolist() == [1.0, 0.0, 0.0]
    off = ~np.eye(3 * M, dtype=bool)
    near = np.kron(D == 0, np.ones((3, 3), bool)) & off     # same marker, other coordinate
    np.testing.assert_allclose(C[near], S[near], atol=1e-12)
    back = MarkerPrior.from_arrays(prior.arrays())
    np.testing.assert_array_equal(back.covariance, C)
    np.testing.assert_array_equal(back.mean, prior.mean)
    assert MarkerPrior.from_arrays({}) is None
    with pytest.raises(ValueError, match="at least 2 frames"):
        MarkerPrior.fit_tapered(train[:1], rest)


def test_frame_noise_recovers_a_known_sigma_per_frame_with_and_without_occlusion():
    """Seeded synthetic markers (held-out one-sided, combined and amplified deformations)
    plus white noise of known σ: every frame's estimate is within 30 % of σ and the
    request's median within 3 % (measured: medians 0.101 / 0.297 / 0.997 for σ 0.1 / 0.3 /
    1.0; per-frame extremes 0.75σ–1.26σ), occluded bursts included; clean markers give
    ~0 (they lie in the prior's span)."""
    rest, G, train, test, rng = _data()
    prior = MarkerPrior.fit_tapered(train, rest)
    W = floor_directions(prior)
    assert W.shape == (3 * len(rest), 155) and np.allclose(W.T @ W, np.eye(155), atol=1e-12)
    for sigma in (0.1, 0.3, 1.0):
        noisy = test + rng.normal(scale=sigma, size=test.shape)
        for u in (noisy, np.where(np.arange(len(rest))[None, :, None] // 4 == 2, np.nan, noisy)):
            s = frame_noise(prior, u, W)
            assert s.shape == (len(test),)
            assert np.all(np.abs(s / sigma - 1) < 0.3), (sigma, s.min(), s.max())
            assert np.median(s) == pytest.approx(sigma, rel=0.03)
        assert frame_noise(prior, noisy[0]) == pytest.approx(frame_noise(prior, noisy)[0], rel=1e-12)
    assert frame_noise(prior, test).max() < 1e-6


def test_temporal_noise_recovers_a_known_sigma_of_a_smooth_performance():
    """A 90-frame, 30 frames/s performance of smooth expression curves plus white noise σ:
    the MAD of second differences gives σ within 3 % (measured 0.0986 / 0.2962 for 0.1 /
    0.3) and < 0.002 mm on the clean performance; too short or empty input is refused."""
    rest, _, _, _, rng = _data()
    left, right, mid = _modes(rest, [(15.0, 20.0), (55.0, 20.0), (35.0, 55.0)])
    t = np.arange(90) / 30.0
    amp = np.stack([0.5 * (1 - np.cos(2 * np.pi * t / 3)), 0.5 * (1 - np.cos(2 * np.pi * t / 2)),
                    0.3 * np.sin(2 * np.pi * t / 4) ** 2], axis=1)
    perf = np.einsum("fk,kmd->fmd", amp, np.stack([left, right, mid]))
    assert temporal_noise(perf) < 0.002
    for sigma in (0.1, 0.3):
        noisy = perf + rng.normal(scale=sigma, size=perf.shape)
        assert temporal_noise(noisy) == pytest.approx(sigma, rel=0.03)
        noisy[10:20, :5] = np.nan                                  # occlusion drops out
        assert temporal_noise(noisy) == pytest.approx(sigma, rel=0.03)
    with pytest.raises(ValueError):
        temporal_noise(perf[:2])


def test_noise_confidence_is_the_wiener_filters_degrees_of_freedom_fraction():
    """Hand-computed on C = diag(1, 3, 0.25): σ = 1 gives (1/2 + 3/4 + 1/5) / 3 = 0.48333…;
    σ = 0 gives 1."""
    prior = MarkerPrior(np.zeros((1, 3)), np.diag([1.0, 3.0, 0.25]))
    np.testing.assert_allclose(noise_confidence(prior, np.array([0.0, 1.0])), [1.0, (0.5 + 0.75 + 0.2) / 3],
                               rtol=1e-14)


def test_marker_denoiser_picks_one_rule_for_every_method():
    """σ = 0: exact interpolation (soft_handles at λ = 0, bit for bit); σ > 0 with a prior:
    MarkerDenoiser.build's solve; without one: the shell prior's soft constraints; "auto":
    the MAP solve at the request's median per-frame estimate; "auto" needs a prior."""
    rest, G, train, test, rng = _data(3)
    prior = MarkerPrior.fit_tapered(train, rest)
    u = test[:6] + rng.normal(scale=0.3, size=test[:6].shape)
    u[1, [4, 9]] = np.nan
    exact = marker_denoiser(G, 0.0, np.nan, prior)
    assert isinstance(exact, PriorCompletion) and exact.interpolates
    np.testing.assert_array_equal(exact(u[[0, 2]]), soft_handles(G, u[[0, 2]], 0.0))   # every marker seen
    eigen = PriorEigen.of(prior)
    np.testing.assert_array_equal(exact(u), shell_completion(G, eigen, u, eigen.conditional_mean(u)))
    without = marker_denoiser(G, 0.0, np.nan)
    assert isinstance(without, ShellDenoiser) and without.interpolates
    np.testing.assert_array_equal(without(u), soft_handles(G, u, 0.0))
    learned = marker_denoiser(G, 0.3, 2.0, prior)
    assert isinstance(learned, MarkerDenoiser) and not learned.interpolates
    np.testing.assert_array_equal(learned(u), MarkerDenoiser.build(prior, G, 0.3, 2.0)(u))
    shell = marker_denoiser(G, 0.3, 2.0)
    np.testing.assert_array_equal(shell(u), soft_handles(G, u, marker_noise_ratio(0.3, 2.0), shell.operator))
    auto = marker_denoiser(G, "auto", np.nan, prior)
    assert isinstance(auto, AdaptiveDenoiser) and not auto.interpolates
    sigma = auto.request_noise(u)
    assert sigma == pytest.approx(float(np.median(frame_noise(prior, u))), rel=1e-12)
    assert sigma == pytest.approx(0.3, rel=0.1)
    np.testing.assert_allclose(auto(u), MarkerDenoiser.build(prior, G, sigma, np.nan, 0.0)(u), atol=1e-9)
    with pytest.raises(ValueError, match="learned marker prior"):
        marker_denoiser(G, "auto", np.nan)


def test_shell_completion_takes_over_where_the_prior_is_uncertain():
    """An occluded marker is completed by the shell's minimum energy instead of the prior's
    conditional mean exactly when its conditional variance ratio (given the visible ones) is
    above the threshold: a prior of independent markers says nothing about a hidden one
    (ratio 1), a hidden marker amid visible correlated neighbours is determined (ratio
    < 0.2 here), one deep inside a hidden 4×4 corner is not; visible markers never move."""
    from service.geometry.marker_prior import SHELL_COMPLETION_RATIO, PriorEigen, shell_completion

    independent = PriorEigen.of(MarkerPrior(np.zeros((4, 3)), 2.0 * np.eye(12)))
    np.testing.assert_allclose(independent.conditional_variance_ratio(np.arange(3, 9)), [1.0, 1.0], rtol=1e-12)
    rest, G, train, test, rng = _data(4)
    eigen = PriorEigen.of(MarkerPrior.fit_tapered(train, rest))
    u = test[:3] + rng.normal(scale=0.3, size=test[:3].shape)
    u[0, 27] = np.nan                                       # one marker amid visible neighbours
    corner = np.ravel_multi_index(np.meshgrid(range(4), range(4), indexing="ij"), (8, 8)).ravel()
    u[1, corner] = np.nan                                   # a 4×4 corner of the 8×8 grid
    ratio = {f: eigen.conditional_variance_ratio(np.flatnonzero(np.repeat(~np.isfinite(u[f]).all(-1), 3)))
             for f in (0, 1)}
    assert ratio[0][0] < SHELL_COMPLETION_RATIO and ratio[1].max() > SHELL_COMPLETION_RATIO
    assert np.all((ratio[1] >= 0) & (ratio[1] <= 1))
    x = eigen.map(u, 0.3)
    assert shell_completion(G, eigen, u, x, ratio=np.inf) is x
    y = shell_completion(G, eigen, u, x)
    seen = np.isfinite(u).all(-1)
    np.testing.assert_array_equal(y[seen], x[seen])
    np.testing.assert_array_equal(y[0], x[0])               # determined: the prior's
    redo = corner[ratio[1] > SHELL_COMPLETION_RATIO]
    assert 0 < len(redo) < len(corner)
    expected = x[1].copy()
    expected[redo] = np.nan
    np.testing.assert_allclose(y[1], soft_handles(G, expected, 0.0), atol=1e-12)
    assert np.abs(y[1, redo] - x[1, redo]).max() > 1e-3


def test_conditional_mean_is_the_gaussian_conditional_and_keeps_the_visible_markers():
    """Operator identity: the precision form equals μ_U + C_UV C_VV⁻¹ (m_V − μ_V) computed
    from the covariance; visible markers pass bit for bit; a frame without occlusion is
    unchanged; it is the σ → 0 limit of the MAP estimate."""
    rest, G, train, test, rng = _data(4)
    prior = MarkerPrior.fit_tapered(train, rest)
    eigen = PriorEigen.of(prior)
    u = test[:3].copy()
    u[0, [5, 6, 30]] = np.nan
    u[1, 40:44] = np.nan
    x = eigen.conditional_mean(u)
    for f in (0, 1):
        hid = np.repeat(~np.isfinite(u[f]).all(axis=1), 3)
        C, mu, m = prior.covariance, prior.mean.ravel(), u[f].ravel()
        direct = mu[hid] + C[np.ix_(hid, ~hid)] @ np.linalg.solve(C[np.ix_(~hid, ~hid)], m[~hid] - mu[~hid])
        np.testing.assert_allclose(x[f].ravel()[hid], direct, atol=1e-8)
        np.testing.assert_array_equal(x[f].ravel()[~hid], m[~hid])
    np.testing.assert_array_equal(x[2], u[2])
    np.testing.assert_allclose(x, eigen.map(u, 1e-5), atol=1e-4)


def test_prior_completion_fills_an_occlusion_burst_better_than_minimum_energy():
    """σ = 0 (the default): visible markers exact, a burst of hidden ones completed from the
    prior far closer to the truth than the shell's minimum-energy fill (seeded)."""
    rest, G, train, test, rng = _data(2)
    prior = MarkerPrior.fit_tapered(train, rest)
    hidden = np.zeros(test.shape[:2], bool)
    hidden[:, 8:12] = True
    hidden[::2, 40:44] = True
    occluded = np.where(hidden[..., None], np.nan, test)
    out = PriorCompletion(G, prior)(occluded)
    np.testing.assert_array_equal(out[~hidden], test[~hidden])
    e_prior = _rms((out - test)[hidden])
    e_shell = _rms((soft_handles(G, occluded, 0.0) - test)[hidden])
    assert e_prior < 0.5 * e_shell, (e_prior, e_shell)
    np.testing.assert_allclose(PriorCompletion(G, prior)(occluded[1]), out[1], atol=1e-10)   # one frame (M,3)
    with pytest.raises(ValueError, match="at least one"):
        PriorCompletion(G, prior)(np.full_like(test[0], np.nan))

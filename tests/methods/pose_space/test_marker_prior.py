"""Tests for the markers' posterior (model.marker_posterior) and its leave-one-clip-out
off-mode variance (model.residual_variance): known answers on synthetic markers."""

import numpy as np
import pytest

from service.methods.pose_space.model import marker_posterior, marker_statistics, residual_variance

M = 12


def _modes(rng, r=3):
    return rng.normal(0.0, 2.0, (r, M, 3))


def test_without_modes_it_is_the_wiener_gain():
    rng = np.random.default_rng(0)
    u = rng.normal(0.0, 1.0, (4, M, 3))
    tau2 = rng.uniform(0.1, 2.0, M)
    inmode, resid = marker_posterior(u, np.zeros((M, 3)), np.zeros((0, M, 3)), tau2, 0.5)
    np.testing.assert_allclose(inmode, 0.0)
    np.testing.assert_allclose(resid, u * (tau2 / (tau2 + 0.25))[None, :, None], rtol=1e-12)


def test_a_noise_per_frame_filters_each_frame_with_its_own():
    """σ (F,): frame k's posterior is the one at σ_k (bit for bit); without modes the gain
    τ²/(τ² + σ_k²) per frame."""
    rng = np.random.default_rng(3)
    modes, mean = _modes(rng), rng.normal(0.0, 1.0, (M, 3))
    tau2 = rng.uniform(0.1, 2.0, M)
    u = mean + rng.normal(0.0, 2.0, (3, M, 3))
    u[2, 4] = np.nan
    sigma = np.array([0.01, 0.3, 1.0])
    inmode, resid = marker_posterior(u, mean, modes, tau2, sigma)
    for k, s in enumerate(sigma):
        one = marker_posterior(u[k:k + 1], mean, modes, tau2, float(s))
        np.testing.assert_array_equal(inmode[k:k + 1], one[0])
        np.testing.assert_array_equal(resid[k:k + 1], one[1])
    inmode, resid = marker_posterior(u, np.zeros((M, 3)), np.zeros((0, M, 3)), tau2, sigma)
    gain = tau2[None, :, None] / (tau2[None, :, None] + sigma[:, None, None] ** 2)
    np.testing.assert_allclose(resid, u * gain, rtol=1e-12)


def test_it_is_the_dense_gaussian_posterior_mean():
    """E[u_v | x_v] = μ_v + Σ_vv (Σ_vv + σ²I)⁻¹ (x_v − μ_v), Σ = LLᵀ + diag(τ²), at the visible
    markers, and μ_o + L_o ẑ at the occluded ones (ẑ = Lᵀ (Σ_vv + σ²I)⁻¹ (x_v − μ_v))."""
    rng = np.random.default_rng(1)
    modes, mean = _modes(rng), rng.normal(0.0, 1.0, (M, 3))
    tau2, s = rng.uniform(0.05, 1.0, M), 0.3
    u = mean + rng.normal(0.0, 2.0, (3, M, 3))
    u[1, [2, 7]] = np.nan
    inmode, resid = marker_posterior(u, mean, modes, tau2, s)
    L = modes.reshape(len(modes), -1).T
    S = L @ L.T + np.diag(np.repeat(tau2, 3))
    for f in range(3):
        v = np.repeat(np.isfinite(u[f]).all(axis=1), 3)
        d = (u[f] - mean).ravel()[v]
        y = np.linalg.solve(S[np.ix_(v, v)] + s * s * np.eye(v.sum()), d)
        est = mean.ravel()[v] + S[np.ix_(v, v)] @ y
        np.testing.assert_allclose((inmode[f] + resid[f]).ravel()[v], est, atol=1e-9)
        occ = mean.ravel()[~v] + L[~v] @ (L[v].T @ y)
        np.testing.assert_allclose(inmode[f].ravel()[~v], occ, atol=1e-9)
        assert np.isnan(resid[f].ravel()[~v]).all() and np.isfinite(inmode[f]).all()


def test_noise_is_removed_inside_the_modes_and_occluded_markers_recovered():
    rng = np.random.default_rng(2)
    modes, mean = _modes(rng), np.zeros((M, 3))
    z = rng.normal(0.0, 1.0, (200, 3))
    truth = np.einsum("fk,kmc->fmc", z, modes)
    noisy = truth + rng.normal(0.0, 0.3, truth.shape)
    inmode, resid = marker_posterior(noisy, mean, modes, np.full(M, 1e-6), 0.3)
    err = np.sqrt(np.mean((inmode + resid - truth) ** 2))
    assert err < 0.5 * 0.3                       # 3 modes of 36 coordinates: ~0.3·√(3/36)
    # exact in-mode data, no noise: occluded markers come back from the visible ones
    occ = truth[:5].copy()
    occ[:, [0, 5, 9]] = np.nan
    inmode, resid = marker_posterior(occ, mean, modes, np.full(M, 1e-9), 1e-6)
    np.testing.assert_allclose(inmode, truth[:5], atol=1e-5)


def test_off_mode_signal_above_the_noise_is_kept():
    rng = np.random.default_rng(3)
    modes = _modes(rng)
    off = np.zeros((1, M, 3))
    off[0, 4] = (5.0, 0.0, 0.0)                   # a new expression at one marker
    tau2 = np.full(M, 4.0)                       # the leave-one-clip-out prior says: possible
    inmode, resid = marker_posterior(off, np.zeros((M, 3)), modes, tau2, 0.3)
    assert np.abs(inmode + resid - off).max() < 0.3


def test_residual_variance_by_leaving_one_clip_out():
    """Clip A moves marker 0, clip B marker 1 (each along x): leaving A out, B's modes do not
    contain marker 0, so A's displacement is all residual (and the other way round)."""
    a = np.zeros((4, M, 3))
    a[:, 0, 0] = [1.0, 2.0, 3.0, 4.0]
    b = np.zeros((2, M, 3))
    b[:, 1, 0] = [2.0, -2.0]
    tau2 = residual_variance(np.concatenate([a, b]), [4, 2], floor_mm=1e-3)
    # leave A out: mean of B is 0 (marker 0); A's residual at marker 0 = its x values
    # leave B out: A's mean at marker 1 is 0, B's residual at marker 1 = ±2
    assert tau2[0] == pytest.approx((1 + 4 + 9 + 16) / 3 / 6)
    assert tau2[1] == pytest.approx((4 + 4) / 3 / 6)
    np.testing.assert_allclose(tau2[2:], 1e-6)
    with pytest.raises(ValueError, match="sum to"):
        residual_variance(np.concatenate([a, b]), [4, 3])


def test_marker_statistics_reproduce_the_covariance():
    rng = np.random.default_rng(4)
    u = rng.normal(0.0, 1.0, (50, M, 3)) @ np.diag([1.0, 2.0, 0.5])
    mean, modes = marker_statistics(u, max_modes=64)
    L = modes.reshape(len(modes), -1).T
    np.testing.assert_allclose(L @ L.T, np.cov(u.reshape(50, -1).T), atol=1e-9)


def test_the_model_denoises_and_completes_markers_and_transfers_its_prior(wpsd_exact, ps_data):
    """On the sample actor: the posterior's shell input of noisy / occluded training markers is
    closer to the clean one than the raw markers', and a self-transfer keeps the statistics."""
    import dataclasses

    from service.methods.pose_space.model import PoseSpaceEvaluator, PoseSpaceModel
    from service.methods.pose_space.transfer import transfer

    actor, clips = ps_data
    d = wpsd_exact.data
    assert d.params.marker_prior == "posterior" and d.marker_residual_var.shape == (d.n_markers,)
    raw = PoseSpaceEvaluator(dataclasses.replace(d, params=d.params.model_copy(update={"marker_prior": "none"})),
                             wpsd_exact.evaluator.base)
    clean = clips[1].markers[[4, 10, 16]]
    _, u0 = wpsd_exact.evaluator.deformation(clean)
    rng = np.random.default_rng(5)
    noisy = clean + rng.normal(0.0, 0.3, clean.shape)
    occ = clean.copy()
    occ[:, rng.choice(d.n_markers, 15, replace=False)] = np.nan
    # measured: 0.84 (noisy) and 0.84 (occluded) of the raw markers' error; the raw markers'
    # hidden ones are completed by the base's own learned prior at σ = 0 (PriorCompletion;
    # 0.49 against the shell's minimum-energy fill before it)
    for bad, bound in ((noisy, 0.9), (occ, 0.9)):
        _, u_post = wpsd_exact.evaluator.deformation(bad)
        _, u_raw = raw.deformation(bad)
        e_post, e_raw = np.sqrt(np.mean((u_post - u0) ** 2)), np.sqrt(np.mean((u_raw - u0) ** 2))
        assert e_post < bound * e_raw
    lm = np.random.default_rng(0).choice(np.flatnonzero(actor.regions["face"]), 40, replace=False)
    moved = transfer(wpsd_exact, actor, np.stack([lm, lm], 1), d.pose_weights)
    for k in ("marker_mean", "marker_modes", "marker_residual_var"):
        np.testing.assert_allclose(getattr(moved.data, k), getattr(d, k), atol=1e-6)
    assert isinstance(moved, PoseSpaceModel)


def test_posterior_displacements_with_marker_noise_count_the_denoiser_offset_once(ps_data):
    """σ > 0: the learned prior's denoiser is affine, D(x) = P x + o; the posterior's two
    parts (in-mode, residual) are denoised separately, so their sum must equal one call on
    the parts' sum — one offset, not two."""
    from service.methods.pdm.base_surface import training_head_pose
    from service.methods.pose_space.corrections import large_scale_surface
    from service.methods.pose_space.model import posterior_displacements

    actor, clips = ps_data
    markers = np.concatenate([c.markers for c in clips]).astype(np.float64)
    rest = actor.marker_positions()
    pose, _ = training_head_pose(markers, rest, [str(k) for k in range(len(markers))])
    aligned = pose.remove(markers)
    base = large_scale_surface(actor).with_marker_noise(0.3, samples=aligned)
    assert not base.denoise.interpolates
    assert np.abs(base.handle_displacements(rest)).max() > 1e-3                # D(0) = o ≠ 0
    mean, modes = marker_statistics(aligned - rest)
    frames = aligned[[3, 20, 31]]
    var = np.full(len(rest), 0.2)
    inmode, resid = marker_posterior(frames - rest, mean, modes, var, 0.3)
    got = posterior_displacements(base, frames, mean, modes, var, 0.3)
    np.testing.assert_allclose(got, base.handle_displacements(rest + inmode + resid), atol=1e-9)



def test_a_noise_per_frame_passes_clean_markers_and_still_filters_noisy_ones(wpsd_exact, pdm_data):
    """posterior_noise = "frame" (σ = the frame's σ̂ clipped to [0.01, 0.3] mm): clean
    markers of a trained expression reach the shell as given (σ̂ at the floor), where the fixed
    σ = 0.3 mm shrinks them; clean markers of an expression the model never saw (sneer: σ̂ reads
    its off-span part as noise, capped at 0.3 mm) are filtered as with the fixed σ; noisy
    markers are still filtered."""
    import dataclasses

    from service.methods.pose_space.model import PoseSpaceEvaluator

    _, clips = pdm_data
    d, base = wpsd_exact.data, wpsd_exact.evaluator.base

    def evaluator(**update):
        return PoseSpaceEvaluator(dataclasses.replace(d, params=d.params.model_copy(update=update)), base)

    fixed, frame, raw = evaluator(), evaluator(posterior_noise="frame"), evaluator(marker_prior="none")

    def err(ev, markers, clean):
        return float(np.sqrt(np.mean((ev.deformation(markers)[1] - raw.deformation(clean)[1]) ** 2)))

    smile = next(c for c in clips if c.name == "train_smile").markers[[6, 10, 14]]
    # measured: 1.3e-6 mm (frame) against 9.0e-4 mm (fixed)
    assert err(frame, smile, smile) < 1e-4 < err(fixed, smile, smile)
    sneer = next(c for c in clips if c.name == "train_sneer").markers[[6, 10, 14]]
    np.testing.assert_allclose(frame.deformation(sneer)[1], fixed.deformation(sneer)[1], atol=1e-9)
    noisy = smile + np.random.default_rng(6).normal(0.0, 0.3, smile.shape)
    # measured: 0.250 (frame), 0.248 (fixed), 0.296 mm (markers as given)
    assert err(frame, noisy, smile) < 0.9 * err(raw, noisy, smile)

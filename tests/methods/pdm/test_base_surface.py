"""Tests for service.methods.pdm.base_surface: head pose, handles, smooth neutral + thin shell."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.geometry.tangent_frames import FrameField, tangent_frames
from service.methods.pdm import base_surface as bs


def _markers(seed=0, M=40, frames=6):
    rng = np.random.default_rng(seed)
    rest = rng.normal(scale=40.0, size=(M, 3))
    R = Rotation.random(frames, random_state=seed).as_matrix()
    t = rng.normal(scale=20.0, size=(frames, 3))
    world = np.einsum("fij,mj->fmi", R, rest) + t[:, None]
    return rest, R, t, world


def test_head_alignment_recovers_the_rigid_motion_and_round_trips():
    rest, R, t, world = _markers()
    pose = bs.head_alignment(world, rest)
    # x_n = R_pose x + t_pose inverts world = R rest + t
    np.testing.assert_allclose(np.einsum("fij,fjk->fik", pose.R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(pose.remove(world), np.broadcast_to(rest, world.shape), atol=1e-10)
    np.testing.assert_allclose(pose.restore(pose.remove(world)), world, atol=1e-10)
    np.testing.assert_allclose(pose[2:4].R, pose.R[2:4])


@pytest.mark.parametrize("scale", [80.0, 200.0, 1000.0])
def test_the_float32_restore_is_within_its_stated_bound_of_the_float64_one(scale):
    """HeadPose.restore32 (synthesis's output path): per point within 2⁻²⁰ ‖X − t‖ of the
    float64 restore, written into ``out`` (issue 23)."""
    rng = np.random.default_rng(int(scale))
    R = Rotation.random(3, random_state=int(scale)).as_matrix()
    pose = bs.HeadPose(R, rng.normal(scale=scale / 4, size=(3, 3)))
    X = rng.normal(scale=scale, size=(3, 5000, 3))
    exact = pose.restore(X)
    out = np.empty(X.shape, np.float32)
    got = pose.restore32(X, out=out)
    assert got is out and got.dtype == np.float32
    err = np.linalg.norm(got - exact, axis=-1)
    bound = 2.0 ** -20 * np.linalg.norm(X - pose.t[:, None, :], axis=-1)
    assert (err <= bound).all(), float((err / bound).max())
    # and it is no worse than a few roundings of the float32 result itself
    assert np.abs(got - exact).max() <= 4 * np.finfo(np.float32).eps * np.abs(exact).max()


def test_stability_weights_keep_the_head_pose_off_moving_markers():
    rest, R, t, world = _markers(seed=1, M=60)
    rng = np.random.default_rng(1)
    # a third of the markers (a "jaw") move by up to 12 mm on top of the head motion
    moving = np.arange(20)
    offset = np.zeros_like(world)
    offset[:, moving] = rng.normal(scale=6.0, size=(len(world), len(moving), 3)) + np.array([0, -8.0, 0])
    observed = world + np.einsum("fij,fmj->fmi", R, offset)
    plain = bs.head_alignment(observed, rest)
    w = bs.stability_weights(plain.remove(observed), rest)
    weighted = bs.head_alignment(observed, rest, w)
    err = lambda p: np.degrees(np.linalg.norm(Rotation.from_matrix(np.einsum("fij,fjk->fik", p.R, R)).as_rotvec(), axis=1)).max()
    assert w[moving].max() < 0.5 * w[20:].min()
    assert np.isclose(w.mean(), 1.0)
    assert err(weighted) < 0.35 * err(plain)          # measured: 0.45° vs 1.59°


def test_too_few_visible_markers_names_the_frame():
    rest, R, t, world = _markers(M=10)
    world[3, 3:] = np.nan
    with pytest.raises(bs.TooFewMarkers, match="frame 3 has 3 visible markers"):
        bs.head_alignment(world, rest)


def test_handle_vertices_pick_the_nearest_corner_and_reject_shared_handles():
    F = np.array([[0, 1, 2], [2, 1, 3]])
    h = bs.handle_vertices(F, np.array([0, 1]), np.array([[0.2, 0.7, 0.1], [0.1, 0.1, 0.8]]))
    np.testing.assert_array_equal(h, [1, 3])
    with pytest.raises(ValueError, match=r"markers \['A', 'B'\] share the thin-shell handle vertex 1"):
        bs.handle_vertices(F, np.array([0, 1]), np.array([[0.2, 0.7, 0.1], [0.1, 0.8, 0.1]]), ("A", "B"))


def test_base_surface_is_the_smooth_neutral_at_rest_and_completes_missing_markers(rig_mesh):
    V, F = rig_mesh
    rng = np.random.default_rng(0)
    handles = rng.choice(len(V), 30, replace=False)
    # a trivial UV layout is enough for the frame field (planar projection)
    uv = (V[:, :2] - V[:, :2].min(0)) / np.ptp(V[:, :2], axis=0).max()
    base = bs.BaseSurface.build(V, F, uv, F, handles, V[handles])
    assert np.abs(base.smooth - V).max() > 0.1                 # smoothed ...
    np.testing.assert_allclose(base.deform(np.zeros((1, 30, 3)))[0], base.smooth, atol=1e-5)
    aligned = V[handles] + rng.normal(scale=2.0, size=(30, 3))
    u_all = base.handle_displacements(aligned[None])[0]
    np.testing.assert_allclose(u_all, aligned - V[handles])
    hidden = aligned.copy()
    hidden[[3, 7]] = np.nan
    u = base.handle_displacements(hidden[None])[0]
    np.testing.assert_allclose(u[[0, 1, 2]], u_all[[0, 1, 2]])
    assert np.isfinite(u).all() and not np.allclose(u[[3, 7]], u_all[[3, 7]])


def test_frame_field_rotates_with_the_surface_and_matches_tangent_frames(rig_mesh):
    V, F = rig_mesh
    uv = (V[:, :2] - V[:, :2].min(0)) / np.ptp(V[:, :2], axis=0).max()
    ff = FrameField.build(V, F, uv, F)
    fr = ff.frames(V)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", fr, fr), np.broadcast_to(np.eye(3), fr.shape), atol=1e-12)
    assert np.linalg.det(fr).min() > 0.999999
    C = np.random.default_rng(1).normal(size=(2,) + V.shape)
    np.testing.assert_allclose(ff.to_world(np.stack([V, 1.1 * V]), C),
                               np.einsum("fnji,fnj->fni", ff.frames(np.stack([V, 1.1 * V])), C), atol=1e-12)
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    np.testing.assert_allclose(ff.frames(V @ R.T), fr @ R.T, atol=1e-9)     # rows rotate with V
    # against the per-pose angle-weighted frames: same up to the weighting
    ref = tangent_frames(V, F, uv, F)
    angle = np.degrees(np.arccos(np.clip(np.sum(fr[:, 2] * ref[:, 2], axis=1), -1, 1)))
    assert np.median(angle) < 0.5 and np.percentile(angle, 95) < 5.0


def test_marker_noise_softens_the_handles_and_denoises_the_feature_markers(rig_mesh):
    """σ = 0 is the exact interpolation; σ > 0 with samples learns τ and the marker prior
    and is that prior's MAP solve; with a stored τ and no prior (a model saved before the
    prior existed) it is soft_handles; denoised_markers puts P_ref + u_H on visible markers
    and keeps occluded ones NaN."""
    from service.geometry.marker_prior import MarkerDenoiser, MarkerPrior
    from service.geometry.thin_shell import shell_prior_scale, soft_handles

    V, F = rig_mesh
    rng = np.random.default_rng(1)
    handles = rng.choice(len(V), 30, replace=False)
    uv = (V[:, :2] - V[:, :2].min(0)) / np.ptp(V[:, :2], axis=0).max()
    exact = bs.BaseSurface.build(V, F, uv, F, handles, V[handles])
    samples = V[handles] + rng.normal(scale=1.0, size=(12, 30, 3))
    with pytest.raises(ValueError, match="prior scale"):
        exact.with_marker_noise(0.3)
    soft = exact.with_marker_noise(0.3, samples=samples)
    tau = shell_prior_scale(exact.energy, samples - V[handles])
    assert soft.prior_scale_mm == pytest.approx(tau)
    assert soft.noise_ratio == pytest.approx(0.09 / tau ** 2)
    prior = MarkerPrior.fit_tapered(samples - V[handles], V[handles])
    np.testing.assert_array_equal(soft.marker_prior.covariance, prior.covariance)
    aligned = samples[:3].copy()
    aligned[1, [4, 9]] = np.nan
    u = soft.handle_displacements(aligned)
    np.testing.assert_allclose(u, MarkerDenoiser.build(prior, exact.energy, 0.3, tau)(aligned - V[handles]), atol=1e-12)
    assert np.abs(u - np.nan_to_num(aligned - V[handles])).max() > 0.05      # not interpolated
    P = soft.denoised_markers(aligned, u)
    np.testing.assert_allclose(P[0], V[handles] + u[0])
    assert np.isnan(P[1, [4, 9]]).all() and np.isfinite(np.delete(P[1], [4, 9], axis=0)).all()
    # σ = 0 (also as restored from a stored model's τ and prior) is the paper's interpolation
    zero = soft.with_marker_noise(0.0, soft.prior_scale_mm, marker_prior=soft.marker_prior)
    np.testing.assert_allclose(zero.handle_displacements(aligned[:1]), aligned[:1] - V[handles], atol=1e-12)
    assert zero.denoised_markers(aligned, u) is aligned
    # restored with the stored prior: the same solve
    stored = exact.with_marker_noise(0.3, soft.prior_scale_mm, marker_prior=soft.marker_prior)
    np.testing.assert_allclose(stored.handle_displacements(aligned), u, atol=1e-12)
    # a model stored before the prior existed: τ alone, the shell prior's soft constraints
    old = exact.with_marker_noise(0.3, soft.prior_scale_mm)
    assert old.marker_prior is None and old.denoiser is None
    np.testing.assert_allclose(old.handle_displacements(aligned),
                               soft_handles(exact.energy, aligned - V[handles], 0.09 / tau ** 2), atol=1e-12)


def test_auto_marker_noise_denoises_with_the_requests_estimated_sigma(rig_mesh):
    """marker_noise_mm = "auto": the learned prior's MAP solve at the request's median
    per-frame σ̂ (frame_noise), features from the denoised markers; with_noise_estimate
    fixes σ for a request; without a prior "auto" is refused."""
    from service.geometry.marker_prior import AdaptiveDenoiser, MarkerDenoiser, frame_noise

    V, F = rig_mesh
    rng = np.random.default_rng(2)
    handles = rng.choice(len(V), 30, replace=False)
    uv = (V[:, :2] - V[:, :2].min(0)) / np.ptp(V[:, :2], axis=0).max()
    exact = bs.BaseSurface.build(V, F, uv, F, handles, V[handles])
    samples = V[handles] + rng.normal(scale=1.0, size=(40, 30, 3))
    auto = exact.with_marker_noise("auto", samples=samples)
    assert isinstance(auto.denoise, AdaptiveDenoiser) and np.isnan(auto.noise_ratio)
    aligned = samples[:5] + rng.normal(scale=0.2, size=(5, 30, 3))
    aligned[2, [3, 7]] = np.nan
    u = aligned - V[handles]
    sigma = float(np.median(frame_noise(auto.marker_prior, u)))
    fixed = MarkerDenoiser.build(auto.marker_prior, exact.energy, sigma, np.nan, 0.0)
    np.testing.assert_allclose(auto.handle_displacements(aligned), fixed(u), atol=1e-9)
    np.testing.assert_allclose(auto.with_noise_estimate(sigma).handle_displacements(aligned), fixed(u), atol=1e-9)
    assert auto.denoised_markers(aligned, fixed(u)) is not aligned
    with pytest.raises(ValueError, match="learned marker prior"):
        exact.with_marker_noise("auto", 1.0)

"""Tests for service.methods.pose_space.model: training and synthesis on the level-0 sample actor."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.methods.inputs import InvalidInput
from service.methods.pose_space import PsdParams, WpsdParams, train
from service.methods.pose_space.corrections import corrections


def _aligned_truth(model, clip, frames):
    ev = model.evaluator
    pose, u_H = ev.deformation(clip.markers[frames])
    return pose, u_H, pose.remove(clip.vertices[frames])


def test_exact_wpsd_reproduces_its_example_poses(wpsd_exact, ps_data):
    actor, clips = ps_data
    names = [f"{c.name}:{f}" for c in clips for f in range(c.frames)]
    assert len(wpsd_exact.data.basis_names) == 5
    for name in wpsd_exact.data.basis_names:
        clip = next(c for c in clips if c.name == name.split(":")[0])
        f = int(name.split(":")[1])
        out = wpsd_exact.synthesize(clip.markers[f:f + 1], ("mesh",), clamp=False)
        # the example mesh itself (float32 weights and output: 1e-4 mm); the shell alone is far off
        np.testing.assert_allclose(out["vertices"][0], clip.vertices[f], atol=2e-4)
    assert set(wpsd_exact.data.basis_names) <= set(names)


def test_corrections_rebuild_the_example_exactly(wpsd_exact, ps_data):
    from service.methods.pose_space.corrections import apply_corrections

    _, clips = ps_data
    ev = wpsd_exact.evaluator
    pose, u_H, aligned = _aligned_truth(wpsd_exact, clips[1], [0, 7, 13])
    c = corrections(ev.base, u_H, aligned)
    X = ev.base.deform(u_H)
    np.testing.assert_allclose(apply_corrections(ev.base, X, c), aligned, atol=1e-4)
    assert np.abs(c).max() > 0.5                       # the shell misses the wrinkles


def test_least_squares_psd_beats_the_thin_shell_on_training_frames(psd_lsq, ps_data):
    actor, clips = ps_data
    m = psd_lsq.metrics
    assert m["correction_fit_rms_mm"]["face"] < 0.5 * m["correction_signal_rms_mm"]["face"]
    assert m["basis_size"] == 5 and len(m["selection_relative_error"]) == 5
    assert np.all(np.diff(m["selection_relative_error"]) <= 1e-12)
    assert m["smoothing"] in PsdParams().smoothing_grid and len(m["validation"]) == len(PsdParams().smoothing_grid)
    fr = [f for f, _ in psd_lsq.stages]
    assert fr[0] == 0.0 and fr[-1] == 1.0 and np.all(np.diff(fr) >= 0)


@pytest.mark.parametrize("name", ["wpsd_exact", "wpsd_regression"])
def test_synthesis_is_invariant_to_head_pose(name, ps_data, request):
    """A rigid head motion of the markers moves the meshes with it and leaves the maps; with
    the marker regression too (it regresses head-aligned offsets on aligned markers)."""
    model = request.getfixturevalue(name)
    _, clips = ps_data
    markers = clips[2].markers[[4, 12]]
    R = Rotation.from_euler("xyz", [10, -25, 5], degrees=True).as_matrix()
    t = np.array([30.0, -5.0, 12.0])
    outputs = ("mesh", "mesh_detailed", "displacement")
    a = model.synthesize(markers, outputs)
    b = model.synthesize(markers @ R.T + t, outputs)
    for key in ("vertices", "vertices_detailed"):
        np.testing.assert_allclose(b[key], a[key] @ R.T + t, atol=2e-3)
    np.testing.assert_allclose(b["displacement"], a["displacement"], atol=1e-4)
    np.testing.assert_allclose(b["confidence"], a["confidence"], atol=1e-6)


def test_outputs_confidence_and_occlusion(wpsd_exact, ps_data):
    actor, clips = ps_data
    m = clips[0].markers[[5]]
    out = wpsd_exact.synthesize(m, ("mesh", "mesh_detailed", "displacement", "normal_map"))
    H = wpsd_exact.data.map_resolution
    assert out["vertices"].shape == (1, actor.n_vertices, 3) and out["normal_map"].shape == (1, H, H, 3)
    # a training frame is inside the range (1), its clean markers' noise factor a measured
    # bound (service.methods.confidence: 0.99997 here), times the size factor of its deformation
    g = wpsd_exact.evaluator.base.evidence.size_factor(wpsd_exact.evaluator.deformation(m)[1])[0]
    assert 0.9999 * g <= out["confidence"][0] <= g
    # exaggerated expression: features beyond the training range lower the confidence
    rest = actor.marker_positions()
    far = rest + 2.5 * (m[0] - rest)
    far_out = wpsd_exact.synthesize(far[None], ("mesh",))
    assert far_out["confidence"][0] < 0.8 and far_out["clamped"][0] > 0
    # occluded markers: NaN rows are completed by the shell
    occ = m.copy()
    occ[0, ::10] = np.nan
    o = wpsd_exact.synthesize(occ, ("mesh",))
    assert np.isfinite(o["vertices"]).all()
    face = actor.regions["face"]
    assert np.abs(o["vertices"][0, face] - out["vertices"][0, face]).mean() < 0.3


def test_bad_input_is_rejected(wpsd_exact, ps_data):
    actor, clips = ps_data
    with pytest.raises(InvalidInput, match=r"markers \(F,150,3\)"):
        wpsd_exact.synthesize(np.zeros((2, 3, 3)))
    with pytest.raises(InvalidInput, match="unknown outputs"):
        wpsd_exact.synthesize(clips[0].markers[:1], ("albedo",))
    with pytest.raises(InvalidInput, match="visible markers"):
        wpsd_exact.synthesize(np.full((1, 150, 3), np.nan))
    with pytest.raises(InvalidInput, match="no marker named"):
        train(actor, clips[:1], WpsdParams(feature_edges=(("nope", "x"),)))


def test_the_normal_mapper_is_built_with_the_evaluator(wpsd_exact, tmp_path):
    """No lazy caches in evaluators (issue 15): a loaded model's evaluator already holds the
    normal mapper at the map's size, before any normal map is asked for."""
    from service.methods.pose_space import PoseSpaceModel

    wpsd_exact.save(tmp_path / "m")
    ev = PoseSpaceModel.load(tmp_path / "m").evaluator
    H = wpsd_exact.data.map_resolution
    assert ev.normal_mapper is not None and ev.normal_mapper.shape == (H, H)


def test_noise_copies_without_noise_fit_the_same_weights(ps_data):
    """K copies of the training rows with σ = 0 add K identical blocks to the normal equations;
    with the relative ridge (λ · mean diagonal) the weights are unchanged."""
    actor, clips = ps_data
    kw = dict(basis_size=4, smoothing=1e-4, selection_vertices=256, validation_noise_mm=0.0)
    a = train(actor, clips[:2], WpsdParams(**kw))
    b = train(actor, clips[:2], WpsdParams(noise_copies=2, **kw))
    assert a.data.basis_names == b.data.basis_names
    np.testing.assert_allclose(b.data.weights, a.data.weights, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(b.data.poly_linear.toarray(), a.data.poly_linear.toarray(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(b.data.map_weights, a.data.map_weights, rtol=1e-4, atol=1e-6)


def test_noise_copies_damp_the_response_to_marker_noise(ps_data):
    """Fitted on noisy copies of its training frames, the model's corrections move less when
    0.3 mm noise is added to a training frame's markers (errors in variables)."""
    actor, clips = ps_data
    kw = dict(basis_size=4, smoothing=1e-4, selection_vertices=256)
    a = train(actor, clips[:2], WpsdParams(**kw))
    b = train(actor, clips[:2], WpsdParams(noise_copies=2, validation_noise_mm=0.3, **kw))
    m = clips[1].markers[[4, 10, 16]]
    noisy = m + np.random.default_rng(3).normal(0.0, 0.3, m.shape)

    def response(model):
        ev = model.evaluator
        c = []
        for x in (m, noisy):
            _, u = ev.deformation(x)
            f = ev.features(u)
            c.append(ev.corrections(ev.sq_distances(f), f))
        return float(np.sqrt(np.mean((c[1] - c[0]) ** 2)))

    assert response(b) < 0.8 * response(a)


def test_edge_visibility_and_reweighted_distances(wpsd_exact, ps_data):
    """ν = 1 on edges between visible markers, ≈ 0 at an occluded one; the reweighted eq. 3 is
    Σ α ν g² / Σ α ν per vertex, and all-visible frames keep eq. 3."""
    _, clips = ps_data
    ev = wpsd_exact.evaluator
    m = clips[1].markers[[3, 9]].copy()
    assert ev.edge_visibility(m) is None
    e = ev.graph.edges
    hidden = int(e[0, 0])
    m[0, hidden] = np.nan
    nu = ev.edge_visibility(m)
    at = (e == hidden).any(axis=1)
    assert np.allclose(nu[1], 1.0) and np.all(nu[0][at] < 0.2) and np.all(nu[0][~at] > 0.8)
    _, u = ev.deformation(m)
    f = ev.features(u)
    D2, plain = ev.sq_distances(f, nu), ev.sq_distances(f)
    np.testing.assert_allclose(D2[:, 1], plain[:, 1], rtol=1e-6)
    fb = wpsd_exact.data.basis_features
    A = ev.alpha
    v = int(np.argmax(A[:, np.flatnonzero(at)].sum(axis=1)))          # a vertex next to the hole
    row = A[v].toarray()[0]
    g2 = (f[0][None] - fb) ** 2                                      # (P,E)
    want = (g2 * row * nu[0]).sum(axis=1) / (row * nu[0]).sum()
    np.testing.assert_allclose(D2[v, 0], want, rtol=1e-10)
    assert not np.allclose(D2[v, 0], plain[v, 0])


@pytest.mark.parametrize("fixture", ["wpsd_exact", "psd_lsq"])
def test_float32_synthesis_is_within_1e_4_mm_of_float64(fixture, ps_data, request):
    """synthesize sums the RBF in float32 (the stored precision of the weights); the same
    evaluation in float64 agrees within 1e-4 mm (measured 1.5e-5: one float32 ulp of the
    output at the actor's 186 mm)."""
    from service.methods.pose_space import polynomial
    from service.methods.pose_space.corrections import apply_corrections

    model = request.getfixturevalue(fixture)
    ev, d = model.evaluator, model.data
    markers = ps_data[1][1].markers[[2, 9]]
    out = model.synthesize(markers, ("mesh", "mesh_detailed"))
    pose, u = ev.deformation(markers)
    f, _ = ev.limit(ev.features(u), d.params.extrapolation_margin)
    D2 = ev.sq_distances(f)
    c = np.einsum("nfp,npc->fnc", np.broadcast_to(np.sqrt(D2), (d.n_vertices,) + D2.shape[1:]),
                  d.weights.astype(np.float64))
    if d.poly_linear is not None:
        c += polynomial.evaluate(d.poly_const.astype(np.float64), d.poly_linear.astype(np.float64), f)
    medium = apply_corrections(ev.base, ev.base.deform(u), c)                      # float64 throughout
    h = (ev.map_sampler @ ev.fine_map(D2, f).T.astype(np.float64)).T
    detailed = medium + h[..., None] * ev.base.frames(medium)[..., 2, :]
    assert np.abs(out["vertices"] - pose.restore(medium)).max() < 1e-4
    assert np.abs(out["vertices_detailed"] - pose.restore(detailed)).max() < 1e-4


def test_confidence_fade_takes_a_pose_outside_the_training_toward_the_shell(wpsd_exact, ps_data):
    """With confidence_fade (default) a frame's vertex corrections are scaled by its
    range confidence κ: mesh = shell + κ·(unfaded mesh − shell), the fine map kept; κ = 1 inside
    the training box."""
    import dataclasses

    from service.methods.pose_space import PoseSpaceModel

    model = wpsd_exact
    d = model.data
    assert d.params.confidence_fade
    plain = PoseSpaceModel(dataclasses.replace(d, params=d.params.model_copy(update={"confidence_fade": False})),
                           model.evaluator)
    clip = ps_data[1][1]
    rest = d.rest_markers
    peak = clip.markers[[clip.frames // 2]]
    far = rest + 2.5 * (peak - rest)                      # the expression 2.5x beyond its peak
    markers = np.concatenate([clip.markers[[3]], far])
    a = model.synthesize(markers, ("mesh", "displacement"))
    b = plain.synthesize(markers, ("mesh", "displacement"))
    ev = model.evaluator
    pose, u = ev.deformation(markers)
    k = ev.confidence(ev.features(u))                     # the range confidence: it fades
    assert k[0] == 1.0 and 0.05 < k[1] < 0.9
    # reported: κ times the markers' input factor (service.methods.confidence), which does not fade
    n = ev.base.input_confidence(pose.remove(markers), u)
    np.testing.assert_allclose(a["confidence"], k * n, rtol=1e-6)
    g = ev.base.evidence.size_factor(u)                     # the size factor of the deformation
    assert n[0] / g[0] > 0.999 and n[1] < g[1] < g[0]       # noise factor measured 0.99985, and below 1
    np.testing.assert_array_equal(a["vertices"][0], b["vertices"][0])
    shell = pose.restore(ev.base.deform(u))
    np.testing.assert_allclose(a["vertices"][1], shell[1] + k[1] * (b["vertices"][1] - shell[1]), atol=1e-4)
    np.testing.assert_array_equal(a["displacement"], b["displacement"])
    assert np.abs(b["vertices"][1] - shell[1]).max() > 0.5          # there was a correction to fade


# --- the marker regression before the RBFs (params.marker_regression, marker_regression.py)

def test_regression_model_reproduces_its_example_poses(wpsd_regression, wpsd_exact, ps_data):
    """Exact interpolation of the residual corrections plus the regression gives the example
    meshes back (the regression is added the same way in training and synthesis); the
    regression alone carries most of the correction on the training frames."""
    _, clips = ps_data
    d = wpsd_regression.data
    assert d.regression is not None and d.regression.L.shape == (3 * d.n_vertices, 3 * d.n_markers)
    for name in d.basis_names[:3]:
        clip = next(c for c in clips if c.name == name.split(":")[0])
        f = int(name.split(":")[1])
        out = wpsd_regression.synthesize(clip.markers[f:f + 1], ("mesh", "mesh_detailed", "displacement"),
                                         clamp=False)
        np.testing.assert_allclose(out["vertices"][0], clip.vertices[f], atol=2e-4)
        # the detailed mesh is the same mesh plus the fine map (≤ its largest value) along normals
        gap = np.linalg.norm(out["vertices_detailed"][0] - out["vertices"][0], axis=-1).max()
        assert gap <= np.abs(out["displacement"][0]).max() + 1e-3
    m, m0 = wpsd_regression.metrics, wpsd_exact.metrics
    assert m["correction_signal_rms_mm"]["face"] < 0.5 * m0["correction_signal_rms_mm"]["face"]


def test_a_filtered_take_reports_the_noise_of_its_markers_as_captured(wpsd_exact, ps_data):
    """As the PDM's (tests/methods/pdm/test_model_confidence.py): with the frames as captured
    beside the filtered ones, the confidence's noise factor reads the capture's σ̂ and every
    other output is the same, bit for bit."""
    _, clips = ps_data
    filtered = clips[0].markers[[3, 5, 7]]
    captured = filtered + np.random.default_rng(3).normal(scale=0.5, size=filtered.shape) * [[[0]], [[1]], [[1]]]
    plain = wpsd_exact.synthesize(filtered, ("mesh",))
    out = wpsd_exact.synthesize(filtered, ("mesh",), captured=captured)
    np.testing.assert_array_equal(out["vertices"], plain["vertices"])
    np.testing.assert_allclose(out["confidence"][0], plain["confidence"][0], rtol=1e-5)
    assert np.all(out["confidence"][1:] < 0.5 * plain["confidence"][1:])

"""The PDM's per-frame confidence and fade (issue 17) on the small sample model."""

from __future__ import annotations

import numpy as np

from service.methods.confidence import CONFIDENCE, VERTEX_CONFIDENCE


def test_confidence_on_training_frames_is_within_a_measured_bound_and_the_detail_is_the_polynomials(
        pdm_model, pdm_data):
    """Training frames lie inside the validity hull (range confidence 1: nothing is faded,
    the detail is the raw polynomials' — but for the medium band's rest onset near the
    neutral, model.rest_onset, which is not the range's); the reported confidence is that
    times the input factor n g of their clean markers (service.methods.confidence): n a
    measured bound, 0.99980–0.99997 on these frames (σ̂ of clean markers is small, not 0),
    times the size factor g of their deformation, which a training frame reports too
    (measured 0.49–1.0 here: this actor's strong training expressions are 2.4 times the
    prior's RMS size)."""
    import dataclasses

    from service.methods.pdm.model import PdmModel

    _, clips = pdm_data
    frames = clips[3].markers[::6][:4]
    ev = pdm_model.evaluator
    pdm_model = PdmModel(pdm_model.data, dataclasses.replace(ev, onset=lambda values, *_: values))
    out = pdm_model.synthesize(frames, ("mesh", "displacement"))
    raw = pdm_model.synthesize(frames, ("mesh", "displacement"), clamp=False)
    g = ev.base.evidence.size_factor(ev.deformation(frames)[1])
    assert np.all(out[CONFIDENCE] >= 0.999 * g) and np.all(out[CONFIDENCE] <= g + 1e-6) and g.min() < 0.6
    np.testing.assert_array_equal(out[VERTEX_CONFIDENCE], np.repeat(out[CONFIDENCE][:, None], pdm_model.n_vertices, 1))
    assert out[VERTEX_CONFIDENCE].shape == (len(frames), pdm_model.n_vertices)
    assert np.array_equal(out["vertices"], raw["vertices"])
    assert np.array_equal(out["displacement"], raw["displacement"])


def test_confidence_decreases_with_the_distance_beyond_training(pdm_model, pdm_data):
    _, clips = pdm_data
    peak = clips[3].markers[10]                        # surprise, near its peak
    pose = pdm_model.evaluator.deformation(peak[None])[0]
    aligned = pose.remove(peak[None])[0]
    rest = pdm_model.evaluator.base.rest_markers
    frames = np.concatenate([pose.restore((rest + k * (aligned - rest))[None]) for k in (1.0, 2.0, 4.0, 8.0)])
    c = pdm_model.synthesize(frames, ("mesh",))[CONFIDENCE]
    # the training frame: range confidence 1 and noise factor ~1, so its size factor alone
    assert c[0] / _size_factor(pdm_model, frames[:1])[0] > 0.99 and np.all(np.diff(c) < 0) and c[-1] < 0.5
    # far outside the detail fades to the fallback: the medium offsets are the neutral's
    far = pdm_model.synthesize(frames[-1:] , ("mesh",))
    assert far[CONFIDENCE][0] < c[0]


def test_the_medium_fallback_is_the_thin_shell_of_the_detailed_neutral(pdm_model, pdm_data):
    """Issue 17: at confidence 0 the mesh is the *no detail* result, the detailed neutral
    deformed by the linear thin shell (``V + B_det u_H``); the fallback is 0 at the neutral."""
    from service.geometry.thin_shell import thin_shell_basis
    from service.methods.pdm.base_surface import BaseSurface

    actor, clips = pdm_data
    ev = pdm_model.evaluator
    rest = ev.base.rest_markers[None]
    assert np.abs(ev.shell_fallback(np.zeros((1, pdm_model.n_markers, 3)), ev.base.smooth[None])).max() < 1e-5
    peak = clips[3].markers[10]
    pose = ev.deformation(peak[None])[0]
    aligned = pose.remove(peak[None])[0]
    far = pose.restore((rest[0] + 8.0 * (aligned - rest[0]))[None])
    out = pdm_model.synthesize(far, ("mesh",))
    w = out[VERTEX_CONFIDENCE][0]
    pose, u_H, _ = ev.deformation(far)
    det = BaseSurface.from_smooth(actor.vertices, actor.faces, actor.uv, actor.uv_faces, ev.base.handles,
                                  ev.base.rest_markers)
    shell = pose.restore(det.deform(u_H))[0]
    faded = w == 0
    assert faded.mean() > 0.2
    assert np.abs(out["vertices"][0][faded] - shell[faded]).max() < 1e-3          # mm (float32 frames)
    assert np.allclose(thin_shell_basis(actor.vertices, actor.faces, ev.base.handles, dtype=np.float32),
                       ev.base.basis + ev.shell_correction, atol=1e-5)


def test_auto_marker_noise_lowers_each_frames_confidence_by_its_noise_estimate(pdm_model, pdm_data):
    """marker_noise_mm = "auto" on the same model: the request's markers are denoised with
    the median σ̂ of its frames, and each frame's confidence is the validity's times
    noise_confidence(σ̂ of that frame): a noisy frame's drops, a clean one's barely moves."""
    import dataclasses

    from service.geometry.marker_prior import frame_noise, noise_confidence
    from service.methods.pdm.model import PdmModel

    _, clips = pdm_data
    ev = pdm_model.evaluator
    base = ev.base.with_marker_noise("auto", ev.base.prior_scale_mm, marker_prior=pdm_model.data.marker_prior)
    model = PdmModel(pdm_model.data, dataclasses.replace(ev, base=base))
    frames = clips[3].markers[::6][:4].copy()
    frames[2:] += np.random.default_rng(0).normal(scale=0.5, size=frames[2:].shape)
    out = model.synthesize(frames, ("mesh",))
    pose = ev.deformation(frames)[0]
    sigma = frame_noise(base.marker_prior, pose.remove(frames) - base.rest_markers)
    assert np.all(sigma[:2] < 0.1) and np.all(np.abs(sigma[2:] / 0.5 - 1) < 0.3), sigma
    # the same request denoised at its fixed σ̂: the same meshes and confidence
    fixed = PdmModel(pdm_model.data, dataclasses.replace(ev, base=base.with_noise_estimate(float(np.median(sigma)))))
    ref = fixed.synthesize(frames, ("mesh",))
    np.testing.assert_array_equal(out["vertices"], ref["vertices"])
    np.testing.assert_array_equal(out[CONFIDENCE], ref[CONFIDENCE])
    factor = noise_confidence(base.marker_prior, sigma)
    validity, g = _range_confidence(fixed, frames), _size_factor(fixed, frames)
    np.testing.assert_allclose(out[CONFIDENCE], validity * factor * g, rtol=1e-5)
    assert factor[0] > 0.95 and factor[2] < 0.5 and out[CONFIDENCE][2] / g[2] < 0.5 * out[CONFIDENCE][0] / g[0]


def _size_factor(model, frames):
    """The size factor g (F,) of world markers (F,M,3): of the request's handle
    displacements u_H (service.methods.confidence.MarkerEvidence.size_factor)."""
    ev = model.evaluator
    base, _ = ev.request_base(frames)
    return base.evidence.size_factor(ev.deformation(frames, base)[1])


def _range_confidence(model, frames):
    """The validity's per-frame confidence (F,) of world markers (F,M,3), the fade's."""
    ev = model.evaluator
    base, _ = ev.request_base(frames)
    _, _, S = ev.deformation(frames, base)
    d1, d2, _ = ev.vertex_band.parameters(S, None)
    return ev.validity.confidence(ev.validity.gauge(d1, d2))[0]


def test_exact_interpolation_also_reports_the_noise_factor_without_fading_by_it(pdm_model, pdm_data):
    """marker_noise_mm = 0 (the default): each frame's confidence is the validity's times
    n(σ̂) of its own markers times the size factor g of its deformation
    (service.methods.confidence), so σ = 0.5 mm noisy frames report well under half a
    clean frame's of the same size; the fade stays the validity's (a clean frame's mesh is
    the same alone or beside noisy ones)."""
    from service.geometry.marker_prior import frame_noise, noise_confidence

    _, clips = pdm_data
    ev = pdm_model.evaluator
    assert ev.base.noise_mm == 0 and ev.base.evidence is not None
    frames = clips[3].markers[::6][:4].copy()
    frames[2:] += np.random.default_rng(1).normal(scale=0.5, size=frames[2:].shape)
    out = pdm_model.synthesize(frames, ("mesh",))
    pose = ev.deformation(frames)[0]
    factor = noise_confidence(ev.base.marker_prior, frame_noise(ev.base.marker_prior,
                                                                pose.remove(frames) - ev.base.rest_markers))
    g = _size_factor(pdm_model, frames)
    np.testing.assert_allclose(out[CONFIDENCE], _range_confidence(pdm_model, frames) * factor * g, rtol=1e-5)
    assert np.all(factor[:2] > 0.999) and np.all(factor[2:] < 0.5)
    assert (out[CONFIDENCE] / g)[2:].max() < 0.5 * (out[CONFIDENCE] / g)[:2].min()
    np.testing.assert_array_equal(pdm_model.synthesize(frames[:1], ("mesh",))["vertices"][0], out["vertices"][0])


def test_a_filtered_take_reports_the_noise_of_its_markers_as_captured(pdm_model, pdm_data):
    """``captured``: the frames a synthesis job filtered in time, as captured. The filtered
    frames (here the clean ones, as a perfect filter would give) read σ̂ ≈ 0; with their
    noisy capture beside them the noise factor is n(σ̂ of the capture), every other output
    bit for bit the same (the denoiser keeps the filtered frames' σ̂), so the noisy takes'
    frames report well under half the clean ones' confidence."""
    from service.geometry.marker_prior import frame_noise, noise_confidence
    from service.methods.inputs import InvalidInput
    from service.methods.pdm.base_surface import head_alignment

    _, clips = pdm_data
    ev = pdm_model.evaluator
    filtered = clips[3].markers[::6][:4].copy()
    captured = filtered.copy()
    captured[2:] += np.random.default_rng(2).normal(scale=0.5, size=captured[2:].shape)
    outputs = ("mesh", "displacement")
    plain = pdm_model.synthesize(filtered, outputs)
    out = pdm_model.synthesize(filtered, outputs, captured=captured)
    for key in ("vertices", "displacement", "clamped"):
        np.testing.assert_array_equal(out[key], plain[key])
    pose = head_alignment(captured, ev.base.rest_markers, pdm_model.data.pose_weights)
    sigma = frame_noise(ev.base.marker_prior, pose.remove(captured) - ev.base.rest_markers)
    factor = noise_confidence(ev.base.marker_prior, sigma)
    expected = _range_confidence(pdm_model, filtered) * factor * _size_factor(pdm_model, filtered)
    np.testing.assert_allclose(out[CONFIDENCE], expected, rtol=1e-5)
    np.testing.assert_allclose(out[VERTEX_CONFIDENCE], np.repeat(out[CONFIDENCE][:, None], pdm_model.n_vertices, 1),
                               rtol=1e-6)
    np.testing.assert_allclose(out[CONFIDENCE][:2], plain[CONFIDENCE][:2], rtol=1e-5)   # clean: as before
    assert np.all(sigma[:2] < 0.1) and np.all(sigma[2:] > 0.35)
    assert np.all(out[CONFIDENCE][2:] < 0.5 * plain[CONFIDENCE][2:])
    try:
        pdm_model.synthesize(filtered, outputs, captured=captured[:3])
    except InvalidInput as error:
        assert "(3, " in str(error) and "(4, " in str(error)
    else:
        raise AssertionError("a captured take of other frames must be refused")

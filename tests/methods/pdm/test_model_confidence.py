"""The PDM's per-frame confidence and fade (issue 17) on the small sample model."""

from __future__ import annotations

import numpy as np

from service.methods.confidence import CONFIDENCE, VERTEX_CONFIDENCE


def test_confidence_is_one_on_training_frames_and_the_detail_is_the_polynomials(pdm_model, pdm_data):
    _, clips = pdm_data
    frames = clips[3].markers[::6][:4]
    out = pdm_model.synthesize(frames, ("mesh", "displacement"))
    raw = pdm_model.synthesize(frames, ("mesh", "displacement"), clamp=False)
    assert np.all(out[CONFIDENCE] == 1) and np.all(out[VERTEX_CONFIDENCE] == 1)
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
    assert c[0] > 0.99 and np.all(np.diff(c) < 0) and c[-1] < 0.5
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

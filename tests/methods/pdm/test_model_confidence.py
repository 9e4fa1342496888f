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

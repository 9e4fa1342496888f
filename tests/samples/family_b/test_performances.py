"""Family b's performances: own training set, combinations outside it, amplified range."""

import numpy as np

from service.samples.family_b import performances as P
from service.samples import performances as family_a


def test_combinations_lie_outside_family_b_training_clips(rig):
    names = rig.expression_names
    peaks = [P.vector(names, s) for s in P.TRAINING.values()]
    amp = P.training_amplitudes(names)
    s = np.linspace(0, 1, 201)
    for key in (k for k in P.COMBINATIONS if k):
        w = P.vector(names, key)
        nearest = min(np.abs(w[None] - s[:, None] * p[None]).max(axis=1).min() for p in peaks)
        assert nearest >= 0.45 and np.all(w <= amp + 1e-12)
    perf = P.heldout_combinations(names, 1)
    frames = np.concatenate([c.weights for c in P.training_clips(names, 1)])
    far = np.abs(perf.weights[:, None] - frames[None]).max(axis=2).min(axis=1)
    assert far.max() >= 0.45 and np.all(perf.weights <= amp + 1e-12)


def test_amplified_is_25_to_40_percent_beyond_training_and_in_range_is_within(rig):
    names = rig.expression_names
    amp = P.training_amplitudes(names)
    w = P.heldout_amplified(names, 1).weights
    # at each training expression's peak key: every active weight 1.25-1.40 × its training peak
    ratio = w.max(axis=0)[amp > 0] / amp[amp > 0]
    assert ratio.min() >= 1.25 - 1e-9 and ratio.max() <= 1.40 + 1e-9
    assert np.all(P.heldout_in_range(names, 1).weights <= amp + 1e-12)
    assert np.all(P.database(names, 1).weights <= amp + 1e-12)


def test_family_b_timing_and_training_set_are_its_own(rig):
    names = rig.expression_names
    clips = P.training_clips(names, 1)
    assert P.FPS != family_a.FPS and clips[0].frames == P.CLIP_FRAMES != 20
    assert {c.name for c in clips} != {f"train_{k}" for k in family_a.TRAINING_EXPRESSIONS}
    assert all(np.abs(c.weights[[0, -1]]).max() == 0 for c in clips)        # neutral at both ends
    R, t = clips[0].rotation, clips[0].translation
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    sizes = [make(names, 1).frames for make in (P.heldout_in_range, P.heldout_out_of_range,
                                                 P.heldout_combinations, P.heldout_amplified)]
    assert min(sizes) >= 60 and max(sizes) <= 160            # like family a's held-out sizes

"""Family a's generalization performances: combinations outside the training clips, amplified range."""

import numpy as np
import pytest

from service.samples import performances as P


def _nearest_scaled_clip(w, peaks):
    """min over clips c and s ∈ [0,1] of ‖w − s·peak_c‖∞ (a training clip is s·peak, s ∈ [0,1])."""
    s = np.linspace(0, 1, 201)
    return min(np.abs(w[None] - s[:, None] * p[None]).max(axis=1).min() for p in peaks)


def test_combinations_lie_outside_every_training_clip_but_within_its_amplitudes(rig):
    names = rig.expression_names
    peaks = [P._weight_vector(names, s) for s in P.TRAINING_EXPRESSIONS.values()]
    amp = P.training_amplitudes(names)
    keys = [P._weight_vector(names, k) for k in P.COMBINATION_KEYS if k]
    assert len(keys) >= 6
    for w in keys:
        assert _nearest_scaled_clip(w, peaks) >= 0.5      # half a full blendshape away, at least
        assert np.all(w <= amp + 1e-12)                   # a combination, not an extrapolation
    perf = P.heldout_combinations(names, 1)
    # every frame of the performance is within the amplitudes, and its peaks are far from training
    assert np.all(perf.weights <= amp + 1e-12)
    frames = np.concatenate([c.weights for c in P.training_clips(names, 1)])
    far = np.abs(perf.weights[:, None] - frames[None]).max(axis=2).min(axis=1)
    assert far.max() >= 0.5 and np.mean(far > 0.3) > 0.3


def test_amplified_goes_25_to_40_percent_beyond_each_training_expression(rig):
    names = rig.expression_names
    amp = P.training_amplitudes(names)
    keys = P.amplified_keys(1)[1:-1]
    assert len(keys) == len(P.AMPLIFIED_EXPRESSIONS)
    for name, key in zip(P.AMPLIFIED_EXPRESSIONS, keys):
        peak = P._weight_vector(names, P.TRAINING_EXPRESSIONS[name])
        w = P._weight_vector(names, key)
        ratio = w[peak > 0] / peak[peak > 0]
        assert np.ptp(ratio) < 1e-12 and 1.25 <= ratio[0] <= 1.40     # the whole expression scaled
        top = np.argmax(peak)
        assert w[top] / amp[top] >= 1.25                               # its main weight beyond training
    perf = P.heldout_amplified(names, 1)
    assert perf.weights.max() > 1.25 and perf.frames < 160
    assert P.amplified_keys(1) == P.amplified_keys(1) != P.amplified_keys(2)


@pytest.mark.parametrize("make", [P.heldout_in_range, P.heldout_out_of_range])
def test_existing_heldout_performances_are_unchanged(rig, make):
    """The new performances draw from their own generators: the old ones keep their frames."""
    perf = make(rig.expression_names, 1)
    assert perf.frames == {"heldout_in_range": 154, "heldout_out_of_range": 84}[perf.name]

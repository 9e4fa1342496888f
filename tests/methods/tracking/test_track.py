"""Stage helpers of :mod:`service.methods.tracking.track`."""

from __future__ import annotations

import cv2
import numpy as np

from service.methods.tracking.params import TrackingParams
from service.methods.tracking.track import TemporalFlows


class _Input:
    """The part of a TrackingInput TemporalFlows reads: frame_images (T,C,H,W) uint8."""

    def __init__(self, T=4, size=48, seed=2):
        rng = np.random.default_rng(seed)
        base = cv2.GaussianBlur(rng.uniform(0, 255, (size, size + 8)).astype(np.float32), (0, 0), 1.5)
        base = cv2.normalize(base, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)
        self.frame_images = np.stack([base[:, t:t + size] for t in range(T)])[:, None]


def test_temporal_flows_are_computed_once_within_the_budget_and_again_beyond_it():
    inp = _Input()
    kept = TemporalFlows(inp, TrackingParams(), budget_mb=10.0)
    e = kept(1)
    assert kept(1) is e and kept.computed == 1
    assert e.source == ("frame", 1) and e.target == ("frame", 2)
    # each frame moves the texture 1 px left: the backward flow t → t+1 is (−1, 0)
    np.testing.assert_allclose(np.median(e.forward[0].flow[10:-10, 10:-10], axis=(0, 1)), [-1.0, 0.0], atol=0.05)
    assert kept.bytes == 4 * 48 * 48 * (2 + 1) * 2      # two directions, float32 flow + confidence
    kept.release([0, 1])
    assert kept.bytes == 0 and not kept.kept
    none = TemporalFlows(inp, TrackingParams(), budget_mb=0.0)
    a, b = none(0), none(0)
    assert a is not b and none.computed == 2 and none.bytes == 0
    np.testing.assert_array_equal(a.forward[0].flow, b.forward[0].flow)

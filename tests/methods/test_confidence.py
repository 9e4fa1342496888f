"""The confidence vocabulary (service/methods/confidence.py), by hand."""

from __future__ import annotations

import numpy as np
import pytest

from service.methods.confidence import exponential, fade, falloff, frame_confidence


def test_falloff_is_a_compact_smoothstep():
    e = np.array([-1.0, 0.0, 0.25, 0.5, 1.0, 5.0])
    # 1 − (3t² − 2t³): t = 0.25 → 1 − 0.15625
    assert falloff(e, 1.0) == pytest.approx([1, 1, 0.84375, 0.5, 0, 0])
    assert falloff(e, 0.0) == pytest.approx([1, 1, 0, 0, 0, 0])


def test_exponential_and_frame_mean_and_fade():
    assert exponential(np.array([0.0, 2.0]), 2.0) == pytest.approx([1.0, np.exp(-1)])
    assert frame_confidence(np.array([[1.0, 0.0], [0.5, 0.5]]), np.array([3.0, 1.0])) == pytest.approx([0.75, 0.5])
    assert fade(np.array(4.0), np.array(1.0), np.array(0.25)) == pytest.approx(1.75)

"""Marker frames past the training: a training pose's motion scaled beyond it."""

from __future__ import annotations

import numpy as np


def beyond(evaluator, markers: np.ndarray, scale: float) -> np.ndarray:
    """World markers (F,M,3) of ``markers``' (F,M,3) head-aligned displacement from the rest
    markers times ``scale``, in the frames' own head poses (``scale`` 1: ``markers``)."""
    rest = evaluator.base.rest_markers
    pose = evaluator.deformation(markers)[0]
    return pose.restore(rest + scale * (pose.remove(markers) - rest))

"""Confidence of a synthesized frame: how far its deformation lies outside the training data.

One vocabulary for every marker-driven method (issue 17, "never worse than the input"):

* ``confidence`` (F,) float32 in [0, 1], one value per synthesized frame: 1 when the
  frame's deformation lies inside what the model was trained on, decreasing with the
  distance beyond it; ``confidence_vertices`` (F,n) float32 the same per vertex (the
  per-region confidence, at the finest region the method can resolve; the PDM's);
* a method whose detail can go wrong outside its training data fades that detail toward
  its *safe fallback* (the PDM: the thin shell of the detailed neutral and the static neutral map)
  by the confidence: ``fallback + c · (detail − fallback)`` (:func:`fade`), so a frame of
  confidence 0 is exactly the fallback — never worse than the input's large-scale motion.

Two rules of the excess e ≥ 0 (0 inside the training data) are declared here:
:func:`falloff` (compact: exactly 0 from ``e ≥ width`` on, used to fade; the PDM's, with e
the relative distance outside the hull of the point's training parameters,
:mod:`service.methods.pdm.validity`) and :func:`exponential` (``exp(−e/scale)``, pose space's
per-frame confidence, which fades its vertex corrections: ``pose_space.model``, confidence fade).
"""

from __future__ import annotations

import numpy as np

#: result keys (API.md: per-frame arrays of the synthesize response)
CONFIDENCE = "confidence"
VERTEX_CONFIDENCE = "confidence_vertices"


def falloff(excess: np.ndarray, width: float, dtype=np.float64) -> np.ndarray:
    """Compact C¹ falloff (…) in [0, 1]: 1 for excess ≤ 0, 0 for excess ≥ width,
    ``1 − (3t² − 2t³)`` with ``t = excess / width`` between (a smoothstep), of ``dtype``
    (float64, or float32 for a per-texel pass: within 2 ulp of float32 of the float64 value).

    ``width = inf`` is 1 everywhere (no fade); ``width = 0`` a step at 0.
    """
    e = np.asarray(excess, dtype)
    if width <= 0:
        return (e <= 0).astype(dtype)
    t = np.clip(e / e.dtype.type(width), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def exponential(excess: np.ndarray, scale: float) -> np.ndarray:
    """``exp(−excess / scale)`` (…): 1 at excess 0, 1/e at one ``scale`` beyond."""
    return np.exp(-np.asarray(excess, np.float64) / scale)


def frame_confidence(point_confidence: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per-frame confidence (F,) as the ``weights``-weighted (P,) mean of point confidences (F,P)."""
    w = np.asarray(weights, np.float64)
    return np.asarray(point_confidence, np.float64) @ (w / w.sum())


def fade(detail: np.ndarray, fallback: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """``fallback + confidence · (detail − fallback)`` (broadcast): the detail at confidence 1,
    the fallback at 0."""
    return fallback + confidence * (detail - fallback)

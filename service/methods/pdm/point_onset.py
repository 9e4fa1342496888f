"""The medium band's rest onset and its fit-skill gain at the UV points, compiled (issue 17).

After the validity kernel (:func:`.point_validity.valid_points`) the medium PDM's values D̃
(P,3) at the UV points are faded in from the frame's fallback f (the thin shell of the
detailed neutral) near rest (:func:`.model.rest_onset`, the NumPy reference): where the
gauge ρ < ``start``, ``f + w (D̃ − f)`` with ``w = 1 − falloff(ρ, start)``; a model with a
per-point gain g (:mod:`.fit_skill`, ``fit_skill_floor``) multiplies that weight by g, and
points of g < 1 get ``f + g (D̃ − f)`` at any ρ (points of g = 1, and every point of a model
without a gain, exactly as before: the same operations, bit for bit).

As NumPy passes (a mask, its indices, a gather and a scatter of the points near rest) that
was 0.47 ms of CPU for 45,600 points (the level-1 sample actor's, load 10; +0.57 ms on the
level-1 mesh frame, 22.62 → 23.19 ms, ``benchmarks/realtime_ab.py``). Here one Numba kernel
over point ranges, each point read and written once, with the same float32 operations in
the same order (no fast-math), so the values are the reference's bit for bit
(tests/methods/pdm/test_rest_onset.py); the mesh frame measured 19.90 → 19.67 ms of CPU
against main (``benchmarks/realtime_ab.py --rev 6b6c527 --calls 30``, load 3.5). Numba is imported here, so this module is imported where an
evaluator is built, never by ``facesynth serve``'s start.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64

from service.geometry import ranges
from service.methods.pdm.validity_scalars import falloff


@njit(nogil=True, cache=True, error_model="numpy")
def onset_points(lo, hi, values, fallback, rho, start, gain):
    """Points [lo, hi) of ``values`` (P,3) float32, in place: ``f + w (v − f)``, f the
    ``fallback`` (P,3), ``w = g (1 − falloff(ρ, start))`` where ``rho`` (P,) < ``start``
    (float32; :func:`.validity_scalars.falloff`, float32; ρ ≥ 0), else ``w = g`` where the
    point's ``gain`` g (P,) float32 (:mod:`.fit_skill`) is below 1; other points unchanged."""
    one = np.float32(1)
    for p in range(uint64(lo), uint64(hi)):
        r = rho[p]
        g = gain[p]
        if r < start or g < one:
            w = (one - falloff(r, start)) * g if r < start else g
            f0, f1, f2 = fallback[p, 0], fallback[p, 1], fallback[p, 2]
            values[p, 0] = f0 + w * (values[p, 0] - f0)
            values[p, 1] = f1 + w * (values[p, 1] - f1)
            values[p, 2] = f2 + w * (values[p, 2] - f2)


def point_onset(values: np.ndarray, fallback: np.ndarray | None, rho: np.ndarray, start: float,
                gain: np.ndarray | None = None, threads: int | None = None) -> np.ndarray:
    """``values`` (F,P,3) float32 in place (:func:`onset_points`) towards ``fallback`` (F,P,3)
    (None: 0) for ρ (F,P), the onset's ``start`` and the points' ``gain`` (P,) (None: 1)."""
    F, P = np.shape(rho)
    zeros = np.zeros((P, 3), np.float32) if fallback is None else None
    gain = np.ones(P, np.float32) if gain is None else np.ascontiguousarray(gain, np.float32)
    for f in range(F):
        fb = zeros if fallback is None else np.ascontiguousarray(fallback[f], np.float32)
        ranges.run(onset_points, P, values[f], fb, np.ascontiguousarray(rho[f], np.float32),
                   np.float32(start), gain, threads=threads)
    return values

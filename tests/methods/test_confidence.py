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


def _evidence(seed=0):
    """A tapered prior fitted on the seeded grid synthetic of the marker-prior tests, its
    held-out frames (one-sided, combined, amplified) and the generator."""
    from service.geometry.marker_prior import MarkerPrior
    from service.methods.confidence import MarkerEvidence
    from tests.geometry.test_marker_prior import _data

    rest, _, train, test, rng = _data(seed)
    return MarkerEvidence.of(MarkerPrior.fit_tapered(train, rest)), test, rng


def test_input_factor_falls_monotonically_with_injected_noise():
    """Seeded: the same 10 held-out frames with σ = 0, 0.05, 0.1, 0.2, 0.4, 0.8 mm of
    noise; every frame's factor falls with σ and is the Wiener fraction of its σ̂. Measured
    on this synthetic (its prior's variance is small: the factor falls fast): exact frames
    1.000, σ = 0.05 mm 0.40–0.55, σ = 0.4 mm 0.049–0.061."""
    from service.geometry.marker_prior import noise_confidence

    ev, test, rng = _evidence()
    u = test[:10]
    e = rng.normal(size=u.shape)
    f = np.stack([ev.noise_factor(u + s * e) for s in (0.0, 0.05, 0.1, 0.2, 0.4, 0.8)])          # (6,10)
    assert np.all(np.diff(f, axis=0) < 0), f
    assert f[0].min() >= 0.999 and 0.35 < f[1].min() and f[1].max() < 0.6 and f[4].max() < 0.07
    noisy = u + 0.2 * e
    np.testing.assert_allclose(ev.noise_factor(noisy), noise_confidence(ev.prior, ev.noise(noisy)), rtol=1e-12)
    assert ev.noise_factor(noisy[3]) == pytest.approx(ev.noise_factor(noisy)[3])                       # one frame


def test_occlusion_enters_the_input_factor_only_through_the_noise_estimate():
    """No occlusion term (measured against, MarkerEvidence): hiding 8 of 64 markers of a
    σ = 0.1 mm noisy frame moves σ̂ (the occluded markers are filled by the prior and σ̂² is
    divided by the visible fraction) and the factor by 5 % (measured 0.230 → 0.242; bound
    10 %), not by the hidden share; other frames are
    unchanged, and the factor is n(σ̂) of the occluded frame's own estimate."""
    from service.geometry.marker_prior import noise_confidence

    ev, test, rng = _evidence(1)
    u = test[:4] + rng.normal(scale=0.1, size=test[:4].shape)
    moving = np.argsort((test[0] ** 2).sum(axis=-1))[-8:]         # frame 0's largest displacements
    occ = u.copy()
    occ[0, moving] = np.nan
    full, hidden = ev.noise_factor(u), ev.noise_factor(occ)
    assert hidden[0] == pytest.approx(float(noise_confidence(ev.prior, ev.noise(occ[:1]))[0]), rel=1e-12)
    assert abs(hidden[0] / full[0] - 1) < 0.1, (hidden[0], full[0])
    # the other frames only through the prior's near-exact fill of the batch (σ = 1e-3 mm)
    np.testing.assert_allclose(hidden[1:], full[1:], rtol=2e-3)


def test_size_factor_by_hand():
    """g = exp(−‖u_H‖ / (κ s)), s = sqrt(‖μ‖² + tr C): for μ with ‖μ‖² = 25 and C = 4 I₆
    (two markers), s = 7 mm; 1 at the neutral, 1/e at ‖u_H‖ = κ s, per frame."""
    from service.geometry.marker_prior import MarkerPrior
    from service.methods.confidence import SIZE_SCALE, MarkerEvidence

    ev = MarkerEvidence.of(MarkerPrior(np.array([[3.0, 0, 0], [0, 4.0, 0]]), 4.0 * np.eye(6)))
    assert ev.scale_mm == pytest.approx(7.0)
    v = np.array([[0.6, 0.0, 0.0], [0.0, 0.0, 0.8]])                 # ‖v‖ = 1 mm
    u_H = np.stack([0.0 * v, 7.0 * SIZE_SCALE * v, 14.0 * SIZE_SCALE * v])
    np.testing.assert_allclose(ev.size_factor(u_H), [1.0, np.exp(-1.0), np.exp(-2.0)], rtol=1e-12)
    assert ev.size_factor(u_H[1]) == pytest.approx(np.exp(-1.0))                         # one frame


def test_size_factor_scale_is_the_training_rms_within_the_floor_and_falls_with_the_size():
    """Seeded: for the tapered prior s² = mean_f ‖x_f‖² + f tr S exactly (the taper keeps
    the diagonal, the floor adds f tr S), so s is the training frames' RMS size within
    √(1 + f); g falls strictly as a held-out frame's u_H is scaled 0 → 8 times, from 1; and
    the input factor is n(σ̂) g."""
    from service.geometry.marker_prior import TAPER_FLOOR_FRACTION, MarkerPrior
    from service.methods.confidence import MarkerEvidence
    from tests.geometry.test_marker_prior import _data

    rest, _, train, test, rng = _data(2)
    ev = MarkerEvidence.of(MarkerPrior.fit_tapered(train, rest))
    x = train.reshape(len(train), -1)
    trS = ((x - x.mean(axis=0)) ** 2).sum(axis=1).mean()
    assert ev.scale_mm ** 2 == pytest.approx((x ** 2).sum(axis=1).mean() + TAPER_FLOOR_FRACTION * trS, rel=1e-12)
    g = ev.size_factor(np.stack([t * test[0] for t in (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)]))
    assert g[0] == 1.0 and np.all(np.diff(g) < 0) and g[-1] < 0.5, g
    u = test[:3] + rng.normal(scale=0.1, size=test[:3].shape)
    np.testing.assert_allclose(ev.factor(u, test[:3]), ev.noise_factor(u) * ev.size_factor(test[:3]), rtol=1e-12)

"""Tests for the medium band's cross-validated fit skill and its gain (service.methods.pdm.fit_skill)
and the gain in the rest onset's kernel (service.methods.pdm.point_onset)."""

import numpy as np
import pytest

from service.methods.pdm.fit_skill import fit_skill, skill_gain
from service.methods.pdm.model import REST_ONSET, rest_onset
from service.methods.pdm.point_onset import point_onset
from service.methods.pdm.polynomial import evaluate, loo_residuals


def _line():
    """The hand-computed line of test_polynomial: d1 = 0, 1, 2, 3, f = 0, 1, 2, 4, PRESS
    residuals 2/3, −1/7, −4/7, 1, so PRESS = 4/9 + 1/49 + 16/49 + 1 = 790/441."""
    d1 = np.array([[0.0], [1.0], [2.0], [3.0]])
    f = np.array([[[0.0]], [[1.0]], [[2.0]], [[4.0]]])
    return d1, f, loo_residuals(d1, np.zeros_like(d1), f, "linear", ridge=0.0)


def test_skill_hand_computed_against_a_zero_fallback():
    """Fallback 0: its error Σ f² = 21, so skill = 1 − (790/441)/21."""
    _, f, e = _line()
    np.testing.assert_allclose(fit_skill(e, f, np.zeros_like(f)), [1 - 790 / 441 / 21], rtol=0, atol=1e-12)


def test_gain_is_one_where_the_fit_is_exact():
    """An exact polynomial: every left-out frame predicted, skill 1, gain 1 for any floor."""
    rng = np.random.default_rng(0)
    d1, d2 = rng.uniform(-2, 2, (25, 40)), rng.uniform(-2, 2, (25, 40))
    f = evaluate(rng.normal(size=(40, 3, 6)), d1, d2)
    skill = fit_skill(loo_residuals(d1, d2, f, ridge=0.0), f, np.zeros_like(f))
    np.testing.assert_allclose(skill, 1.0, atol=1e-12)
    for floor in (-1.0, 0.0, 0.5):
        np.testing.assert_array_equal(skill_gain(skill, floor), np.float32(1))


def test_gain_is_zero_where_the_fit_explains_nothing():
    """A fallback whose error is the PRESS error (b = f − e): skill 0, gain 0 at floor 0; a
    fallback that is exact (b = f) while the fit is not: skill −inf, gain 0 at any floor; a
    point that neither moves nor misses (f = b, e = 0): skill 1."""
    _, f, e = _line()
    np.testing.assert_allclose(fit_skill(e, f, f - e), [0.0], atol=1e-15)
    assert skill_gain(fit_skill(e, f, f - e), 0.0)[0] == 0.0
    assert fit_skill(e, f, f)[0] == -np.inf and skill_gain([-np.inf], 0.5)[0] == 0.0
    assert fit_skill(np.zeros_like(f), f, f)[0] == 1.0


def test_gain_hand_values():
    np.testing.assert_allclose(skill_gain([-0.2, 0.25, 0.5, 0.75, 1.0], 0.5), [0, 0, 0, 0.5, 1], atol=1e-7)
    np.testing.assert_allclose(skill_gain([-0.2, 0.25, 1.0], 0.0), [0, 0.25, 1], atol=1e-7)
    with pytest.raises(ValueError):
        skill_gain([0.5], 1.0)


def test_onset_with_gain():
    """Gain g: ρ ≥ start gives f + g (v − f), ρ < start multiplies the onset's weight by g; the
    kernel is the NumPy reference bit for bit, and a gain of ones changes nothing (bit for bit)."""
    fb = np.array([[[1.0, 2.0, 3.0]] * 3], np.float32)
    detail = np.array([[[0.8, -0.4, 0.2]] * 3], np.float32)
    rho = np.array([[REST_ONSET / 2, 1.0, 2.0]], np.float32)
    gain = np.array([0.5, 0.25, 1.0], np.float32)
    out = rest_onset(fb + detail, rho, fb, gain=gain)
    np.testing.assert_allclose(out[0, 0], fb[0, 0] + 0.25 * detail[0, 0], atol=1e-6)
    np.testing.assert_allclose(out[0, 1], fb[0, 1] + 0.25 * detail[0, 1], atol=1e-6)
    np.testing.assert_array_equal(out[0, 2], (fb + detail)[0, 2])

    rng = np.random.default_rng(7)
    F, P = 3, 5000
    values = rng.normal(0, 2, (F, P, 3)).astype(np.float32)
    fallback = rng.normal(0, 1, (F, P, 3)).astype(np.float32)
    rho = rng.uniform(0, 2 * REST_ONSET, (F, P)).astype(np.float32)
    gain = np.where(rng.random(P) < 0.5, 1, rng.random(P)).astype(np.float32)
    for fb in (fallback, None):
        ref = rest_onset(values.copy(), rho, fb, gain=gain)
        for threads in (1, 3):
            np.testing.assert_array_equal(point_onset(values.copy(), fb, rho, REST_ONSET, gain, threads=threads), ref)
        np.testing.assert_array_equal(point_onset(values.copy(), fb, rho, REST_ONSET, np.ones(P, np.float32)),
                                      rest_onset(values.copy(), rho, fb))


"""Tests for the medium band's rest onset (service.methods.pdm.model.rest_onset and its
kernel, service.methods.pdm.point_onset): the detail faded in from the thin shell near rest."""

import numpy as np

from service.methods.pdm.model import REST_ONSET, rest_onset
from service.methods.pdm.point_onset import point_onset


def test_rest_onset_fades_the_detail_in_from_the_fallback():
    """ρ = 0: exactly the fallback (the thin shell, the neutral at rest), so a frame whose
    polynomial intercept would push a vertex off the neutral is held back to it; ρ = start / 2:
    half the detail (smoothstep(½) = ½); ρ ≥ start: the values bit for bit."""
    fb = np.array([[[1.0, 2.0, 3.0]] * 4], np.float32)
    detail = np.array([[[0.7, -0.1, 0.3]] * 4], np.float32)
    values = fb + detail
    rho = np.array([[0.0, REST_ONSET / 2, REST_ONSET, 2.0]], np.float32)
    out = rest_onset(values.copy(), rho, fb)
    np.testing.assert_array_equal(out[0, 0], fb[0, 0])
    np.testing.assert_allclose(out[0, 1], fb[0, 1] + 0.5 * detail[0, 1], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(out[0, 2:], values[0, 2:])
    np.testing.assert_array_equal(rest_onset(values.copy(), rho, None)[0, 0], [0.0, 0.0, 0.0])


def test_the_kernel_is_the_numpy_onset_bit_for_bit():
    """point_onset's kernel against rest_onset on seeded random frames (ρ across the onset,
    some exactly 0), with and without a per-frame fallback, on 1 and 3 threads."""
    rng = np.random.default_rng(7)
    F, P = 3, 5000
    values = rng.normal(0, 2, (F, P, 3)).astype(np.float32)
    fb = rng.normal(0, 1, (F, P, 3)).astype(np.float32)
    rho = rng.uniform(0, 2 * REST_ONSET, (F, P)).astype(np.float32)
    rho[:, :10] = 0.0
    for fallback in (fb, None):
        ref = rest_onset(values.copy(), rho, fallback)
        for threads in (1, 3):
            np.testing.assert_array_equal(point_onset(values.copy(), fallback, rho, REST_ONSET, threads=threads), ref)

"""The medium band's validity on compiled kernels (service.methods.pdm.point_validity)
against the NumPy float32 operators it replaces in synthesis (:class:`SectorLookup`,
:meth:`Validity.gauge`, :meth:`Validity.evaluate` of the vertex band), bit for bit, and a
hand-computed case."""

from __future__ import annotations

import numpy as np
import pytest

from service.methods.pdm.point_validity import PointValidity
from tests.methods.pdm.test_realtime_paths import frames  # noqa: F401  S inside and beyond the hull


def test_gauge_is_the_numpy_gauge_and_sector_lookup_bit_for_bit(pdm_model, frames):
    ev = pdm_model.evaluator
    v = ev.validity
    d1, d2, _ = ev.vertex_band.parameters(frames, None)
    rho, (lower, t) = ev.point_validity.gauge(d1, d2)
    lookup = v.lookup(d1, d2)
    want = v.gauge(d1, d2, lookup)
    assert rho.dtype == np.float32 and lower.dtype == np.uint32
    assert np.array_equal(rho, want) and want.min() < 1 < want.max()
    assert np.array_equal(lower, lookup.lower % lookup.K) and np.array_equal(t, lookup.t)
    two = ev.point_validity.gauge(d1, d2, threads=2)
    assert np.array_equal(two[0], rho) and np.array_equal(two[1][0], lower)


@pytest.mark.parametrize("with_fallback", [True, False])
def test_values_are_the_numpy_validity_of_the_vertex_band_bit_for_bit(pdm_model, frames, with_fallback):
    """D̃ towards the per-frame shell fallback (the sector box acting) and towards 0 (no box),
    inside the hull and far outside, against ``Validity.evaluate("vertex", …)``."""
    ev = pdm_model.evaluator
    v = ev.validity
    d1, d2, _ = ev.vertex_band.parameters(frames, None)
    fallback = ev.shell_fallback(frames[..., :3], None) if with_fallback else None
    lookup = v.lookup(d1, d2)
    want = v.evaluate("vertex", ev.vertex_band.coeffs, d1, d2, v.gauge(d1, d2, lookup), lookup, fallback)
    rho, sectors = ev.point_validity.gauge(d1, d2)
    got = ev.point_validity.values(d1, d2, rho, sectors, fallback)
    assert got.dtype == np.float32 and np.array_equal(got, want)
    plain = ev.vertex_band.evaluate(d1, d2)
    changed = np.any(want != plain, axis=-1)
    assert changed[2:].mean() > 0.3                                  # the far frames fade
    assert np.array_equal(ev.point_validity.values(d1, d2, rho, sectors, fallback, threads=2), got)


def test_hand_computed_continuation_and_fade():
    """One linear point D(d) = (2 d1, 0, 0) in a round hull of radius 2 (8 sectors), fallback
    0, envelope large: inside it is the polynomial; at d = (3, 0) (ρ = 1.5) the linear
    continuation is exact, L = 6, and falloff(0.5, width 1) = 1 − 0.25 · 2 = 0.5 gives 3;
    beyond ρ = 2 the fallback; with envelope 1 the inside value is limited to 1.25."""
    P, D = 1, 8
    terms = np.zeros((3, 3, P), np.float32)
    terms[0, 0, 0] = 2.0                                           # a_d1 of channel x
    pv = PointValidity(np.full((P, D), 2.0, np.float32), np.empty((P, 0), np.float32),
                       np.full(P, 100.0, np.float32), np.empty((0, P, 2, 3), np.float32), terms,
                       np.array([1, 0, 0], np.uint8), np.array([0, 1, 0], np.uint8), 1.0, 1.0)
    d1 = np.array([[1.0], [3.0], [5.0], [0.0]], np.float32)
    d2 = np.array([[0.0], [0.0], [0.0], [1.0]], np.float32)
    rho, sectors = pv.gauge(d1, d2)
    np.testing.assert_allclose(rho[:, 0], [0.5, 1.5, 2.5, 0.5], rtol=1e-6)
    np.testing.assert_array_equal(sectors[0][:, 0], [0, 0, 0, 2])  # θ = 0, 0, 0, π/2
    out = pv.values(d1, d2, rho, sectors)
    np.testing.assert_allclose(out[:, 0, 0], [2.0, 3.0, 0.0, 0.0], atol=1e-6)
    assert not out[:, 0, 1:].any()
    small = PointValidity(pv.hull, pv.sectors, np.ones(P, np.float32), pv.box, terms, pv.pi, pv.pj, 1.0, 1.0)
    np.testing.assert_allclose(small.values(d1[:1], d2[:1], rho[:1], (sectors[0][:1], sectors[1][:1]))[0, 0],
                               [1.25, 0, 0], rtol=1e-6)


"""Tests for service.methods.pdm.texel_band: the blocked per-frame evaluation."""

import numpy as np

from service.methods.pdm import texel_band
from service.methods.pdm.validity import valid_values


def test_blocked_synthesis_is_parameters_then_evaluate_bit_for_bit(pdm_model, pdm_data, monkeypatch):
    _, clips = pdm_data
    band = pdm_model.evaluator.fine
    rest = pdm_model.evaluator.base.rest_markers
    peak = clips[3].markers[[10, 12]]
    pose = pdm_model.evaluator.deformation(peak)[0]
    far = pose.restore(rest + 2.5 * (pose.remove(peak) - rest))     # beyond the trained range
    _, _, S = pdm_model.evaluator.deformation(far)
    monkeypatch.setattr(texel_band, "BLOCK_POINTS", 700)            # many blocks at 128²
    assert len(band.field.blocks(texel_band.BLOCK_POINTS)) > 5
    for margin in (pdm_model.params.extrapolation_margin, None):
        d1, d2, frac = band.parameters(S, margin)
        values, got = band.synthesize(S, margin)
        assert np.array_equal(values, band.evaluate(d1, d2)) and np.array_equal(got, frac)
    assert frac.min() == 0 and band.parameters(S, pdm_model.params.extrapolation_margin)[2].min() > 0.05


def test_blocked_validity_is_the_whole_band_validity_bit_for_bit(pdm_model, pdm_data, monkeypatch):
    _, clips = pdm_data
    ev = pdm_model.evaluator
    rest = ev.base.rest_markers
    peak = clips[3].markers[[10, 12]]
    pose = ev.deformation(peak)[0]
    far = pose.restore(rest + 2.5 * (pose.remove(peak) - rest))     # outside the validity region
    _, _, S = ev.deformation(np.concatenate([peak, far]))
    d1, d2, _ = ev.vertex_band.parameters(S, None)
    rho = ev.validity.gauge(d1, d2)
    monkeypatch.setattr(texel_band, "BLOCK_POINTS", 700)            # many blocks at 128²
    for name, band in (("fine", ev.fine), ("albedo", ev.albedo)):
        assert len(band.field.blocks(texel_band.BLOCK_POINTS)) > 3, name
        t1, t2, _ = band.parameters(S, None)
        rho_t = ev.validity.texels(name, rho)
        whole = valid_values(band.coeffs, band.evaluate(t1, t2), t1, t2, rho_t, ev.validity.envelope[name],
                             ev.validity.fallback(name, band.coeffs), ev.validity.width, ev.validity.slope)
        values, frac = band.synthesize(S, None, ev.validity.band(name, band.coeffs, rho))
        assert np.array_equal(values, whole), name
        assert np.array_equal(frac, np.mean(rho_t > 1, axis=-1)), name
        assert frac[:2].max() < frac[2:].min() and frac[2:].min() > 0.05, name   # the far frames are outside


def test_a_band_built_from_stored_terms_uses_them_and_equals_the_copy():
    """TexelBand.build with ``terms`` (K,C,P) (a model's cache) takes them as they are, and
    the band is the one built from the coefficients (P,C,K) element for element."""
    from service.methods.pdm.deformation import ParameterField

    rng = np.random.default_rng(3)
    coeffs = rng.normal(size=(50, 3, 6)).astype(np.float32)
    field = ParameterField(np.zeros(50, np.int64), np.zeros((1, 3), np.int64), np.ones((6, 50), np.float32),
                           np.ones((1, 5)), np.ones((1, 5)), np.ones((1, 5)), np.array([50]))
    copied = texel_band.TexelBand.build(64, np.arange(50), coeffs, field)
    stored = np.ascontiguousarray(coeffs.transpose(2, 1, 0))
    band = texel_band.TexelBand.build(64, np.arange(50), None, field, terms=stored)
    assert band.terms is stored and np.shares_memory(band.coeffs, stored)
    np.testing.assert_array_equal(band.terms, copied.terms)
    np.testing.assert_array_equal(band.coeffs, copied.coeffs)
    assert copied.terms.flags.c_contiguous

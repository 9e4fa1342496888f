"""Tests for service.methods.pdm.texel_validity: a one-channel band's gauge, polynomial,
continuation and fade on compiled kernels, pinned bit for bit against the NumPy operators
(:func:`~service.methods.pdm.validity.texel_gauge`, :func:`~service.methods.pdm.validity.valid_scalar_polynomial`)."""

import numpy as np
import pytest
import scipy.sparse as sp

from service.methods.pdm.polynomial import ORDERS
from service.methods.pdm.texel_validity import TexelValidity, polynomial_flags, texel_gauge as gauge_kernel
from service.methods.pdm.validity import MARGIN, sure_bound, texel_gauge, valid_scalar_polynomial
from tests.methods.pdm.test_realtime_paths import frames  # noqa: F401  S inside and beyond the hull


def _operator(rng, P, Q, inner=0):
    """(P,Q) CSR float64 with 1-3 non-negative entries a row (barycentric-like, some 0);
    the first ``inner`` rows on the first 10 columns only."""
    nnz = rng.integers(1, 4, size=P)
    rows = np.repeat(np.arange(P), nnz)
    cols = np.concatenate([rng.choice(10 if p < inner else Q, k, replace=False) for p, k in enumerate(nnz)])
    vals = rng.uniform(0, 1, size=len(rows))
    vals[rng.random(len(rows)) < 0.05] = 0.0
    return sp.csr_matrix((vals, (rows, cols)), shape=(P, Q))


def _case(order, seed=7, P=600, Q=50, F=3):
    """Corner cases of the scalar path (zeros of both signs, NaN coefficients, envelopes 0,
    subnormal, huge and at the bound, ρ exactly 1) on a random operator."""
    rng = np.random.default_rng(seed)
    K = ORDERS[order]
    coeffs = rng.normal(size=(P, 1, K)).astype(np.float32)
    coeffs[:40] = 0.0
    coeffs[20:40] = -0.0                                                 # D = −0 where d > 0
    coeffs[40:60, 0, :K - 1] = 0.0
    coeffs[40:60, 0, -1] = -0.0
    coeffs[40:50, 0, 0] = -1e-30                                        # −0 after rounding
    coeffs[60, 0, K // 2] = np.nan
    d1, d2 = rng.normal(size=(2, F, P)).astype(np.float32) * 3
    d1[:, 20:40], d2[:, 20:40] = np.abs(d1[:, 20:40]), np.abs(d2[:, 20:40])
    R = _operator(rng, P, Q, inner=70)
    point_rho = (np.abs(rng.normal(size=(F, Q))) * 1.1).astype(np.float32)
    point_rho[:, ::9] = 1.0
    point_rho[:, :10] *= 0.05                  # the block [1, 70) is inside: its −0 values stay
    envelope = np.abs(rng.normal(size=P)).astype(np.float32)
    envelope[100:110] = 0.0
    envelope[110:120] = 1e-40
    envelope[120:130] = 3e38
    from service.methods.pdm.polynomial import evaluate

    detail = np.abs(evaluate(coeffs, d1, d2)[..., 0] - coeffs[:, 0, -1])
    envelope[130:200] = (detail[0, 130:200] / np.float32(1.25)).astype(np.float32)   # at the bound
    return coeffs, d1, d2, R, point_rho, envelope


@pytest.mark.parametrize("order", sorted(ORDERS))
@pytest.mark.parametrize("width, slope", [(1.0, 1.0), (0.5, 0.0), (0.0, 1.0)])
def test_compiled_band_is_the_numpy_scalar_path_bit_for_bit_per_block(order, width, slope):
    coeffs, d1, d2, R, point_rho, envelope = _case(order)
    P = len(coeffs)
    with np.errstate(over="ignore"):                                     # 1.25 × 3e38 is inf
        sure = sure_bound(envelope)
        tv = TexelValidity.build(R, coeffs.transpose(2, 1, 0), envelope, sure, width, slope, MARGIN)
    rho = texel_gauge(R, point_rho)
    fallback = coeffs[:, :, -1]
    cuts = [0, 1, 70, 71, 333, P]                                        # one-point blocks too
    got = np.full((len(d1), P), np.nan, np.float32)
    for s, e in zip(cuts, cuts[1:]):
        count = tv.evaluate(d1[:, s:e], d2[:, s:e], point_rho.astype(np.float64), s, e, got[:, s:e])
        with np.errstate(over="ignore"):
            want = valid_scalar_polynomial(coeffs[s:e], d1[:, s:e], d2[:, s:e], rho[:, s:e], envelope[s:e],
                                           fallback[s:e], width, slope, sure=sure[s:e])[..., 0]
        assert np.array_equal(got[:, s:e].view(np.uint32), want.view(np.uint32)), (s, e)
        assert np.array_equal(count, np.count_nonzero(rho[:, s:e] > 1, axis=-1))
    assert (rho > 1).mean() > 0.1 and np.isnan(got).any() and (got == 0).sum() > 30
    assert np.signbit(got[got == 0]).any() and not np.signbit(got[got == 0]).all()


def test_gauge_pads_short_rows_with_weight_zero_bit_for_bit():
    """Rows of 1, 2 and 3 entries: ρ the SciPy float64 row sum rounded to float32."""
    rng = np.random.default_rng(3)
    R = _operator(rng, 500, 40)
    assert set(np.diff(R.indptr)) == {1, 2, 3}
    point_rho = (np.abs(rng.normal(size=40)) * 2).astype(np.float32)
    terms = rng.normal(size=(6, 1, 500)).astype(np.float32)
    tv = TexelValidity.build(R, terms, np.ones(500, np.float32), np.ones(500, np.float32), 1.0, 1.0, MARGIN)
    rho, out, flag = np.empty(500, np.float32), np.empty(500, np.float32), np.empty(500, bool)
    count = gauge_kernel(0, 500, point_rho.astype(np.float64), tv.corner, tv.weight, rho)
    want = texel_gauge(R, point_rho[None])[0]
    assert np.array_equal(rho, want) and count == np.count_nonzero(want > 1) > 0
    zero = np.zeros(500, np.float32)
    polynomial_flags(0, 500, zero, zero, rho, tv.terms, tv.sure, True, out, flag)
    assert np.array_equal(out, terms[5, 0]) and np.array_equal(flag, want > 1)     # d = 0: the constant


def test_build_rejects_operators_it_cannot_pad():
    R = sp.csr_matrix(np.ones((2, 5)))
    with pytest.raises(ValueError, match="entries a row"):
        TexelValidity.build(R, np.zeros((6, 1, 2), np.float32), np.ones(2), np.ones(2), 1.0, 1.0, MARGIN)


def test_the_models_fine_band_runs_compiled_as_the_numpy_blocks(pdm_model, frames):
    """The trained model's fine band: its compiled validity is made at build, and synthesis
    through it is synthesis through the NumPy operators, values and clamped fraction bit for
    bit, inside the hull and far out."""
    import dataclasses

    ev = pdm_model.evaluator
    v = ev.validity
    assert "fine" in v.compiled and "albedo" not in v.compiled                   # one channel only
    d1, d2, _ = ev.vertex_band.parameters(frames, None)
    bv = v.band("fine", ev.fine.coeffs, v.gauge(d1, d2))
    assert bv.compiled is v.compiled["fine"]
    got, frac = ev.fine.synthesize(frames, None, bv)
    want, want_frac = ev.fine.synthesize(frames, None, dataclasses.replace(bv, compiled=None))
    assert np.array_equal(got.view(np.uint32), want.view(np.uint32)) and np.array_equal(frac, want_frac)
    assert frac[2:].min() > 0.05 and frac[:2].max() < frac[2:].min()


def test_padded_rows_are_the_numpy_scatter_of_the_csr_rows():
    """Seeded CSR of 0–3 entries a row (an empty row included): the compiled fill equals the
    NumPy scatter it replaced — each row's entries in order, padded with weight 0 on the
    row's first entry, 0 for an empty row — element for element."""
    from service.methods.pdm.texel_validity import CORNERS, padded_rows

    rng = np.random.default_rng(7)
    nnz = rng.integers(0, CORNERS + 1, 400)
    nnz[:2] = (0, CORNERS)
    indptr = np.concatenate([[0], np.cumsum(nnz)]).astype(np.int32)
    R = sp.csr_matrix((rng.random(indptr[-1]), rng.integers(0, 90, indptr[-1]).astype(np.int32), indptr),
                      shape=(400, 90))
    corner = np.zeros((CORNERS, 400), np.uint32)
    weight = np.zeros((CORNERS, 400), np.float64)
    slot = np.arange(R.nnz) - np.repeat(R.indptr[:-1], nnz)
    row = np.repeat(np.arange(400), nnz)
    corner[slot, row], weight[slot, row] = R.indices, R.data
    for c in range(1, CORNERS):
        corner[c] = np.where(nnz > c, corner[c], corner[0])
    got_c, got_w = np.empty_like(corner), np.empty_like(weight)
    padded_rows(R.indptr, R.indices, R.data, got_c, got_w)
    np.testing.assert_array_equal(got_c, corner)
    np.testing.assert_array_equal(got_w, weight)
    assert got_w[:, 0].tolist() == [0.0, 0.0, 0.0] and np.all(got_w[:, 1] > 0)

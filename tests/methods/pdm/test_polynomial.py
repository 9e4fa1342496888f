"""Per-texel polynomial fitting of deformation-driven PDMs (ma2008 §4.2, eq. 1)."""

from pathlib import Path

import numpy as np
import pytest

from service.methods.pdm.polynomial import (
    ORDERS,
    TERM_POWERS,
    design_matrix,
    evaluate,
    fit,
    fit_residual_rms,
    loo_residuals,
    regularization_weights,
    relative_ridge_weights,
)


def _params(rng, T, P):
    """Deformation parameters in the paper's range (Figure 3: about -2 … 2)."""
    return rng.uniform(-2, 2, (T, P)), rng.uniform(-2, 2, (T, P))


def _exact(order, T=30, P=500, C=3, seed=0):
    rng = np.random.default_rng(seed)
    d1, d2 = _params(rng, T, P)
    a = rng.normal(size=(P, C, ORDERS[order]))
    return d1, d2, a, evaluate(a, d1, d2)


def _lstsq(d1, d2, f, order="biquadratic"):
    """Reference: np.linalg.lstsq on the rows of one texel, (T,), (T,), (T,C) → (C,K)."""
    return np.linalg.lstsq(design_matrix(d1, d2, order), f, rcond=None)[0].T


# --- 8. term order -----------------------------------------------------------------------


def test_design_matrix_biquadratic_term_order_is_eq1():
    np.testing.assert_array_equal(design_matrix(2.0, 3.0, "biquadratic"), [4, 9, 6, 2, 3, 1])


def test_design_matrix_linear_and_bicubic_term_order():
    np.testing.assert_array_equal(design_matrix(2.0, 3.0, "linear"), [2, 3, 1])
    np.testing.assert_array_equal(
        design_matrix(2.0, 3.0, "bicubic"), [8, 27, 12, 18, 4, 9, 6, 2, 3, 1]
    )
    for order, K in ORDERS.items():
        assert len(TERM_POWERS[order]) == K and TERM_POWERS[order][-1] == (0, 0)


def test_design_matrix_shapes():
    rng = np.random.default_rng(1)
    d1, d2 = _params(rng, 4, 5)
    assert design_matrix(d1, d2, "bicubic").shape == (4, 5, 10)
    assert design_matrix(d1[0], d2[0]).dtype == np.float64


# --- regularization rows ------------------------------------------------------------------


def test_relative_ridge_weights_are_ridge_times_column_norms():
    w = relative_ridge_weights("biquadratic", np.array([4.0, 0.25, 1.0, 2.0, 0.5, 7.0]), 0.1)
    np.testing.assert_allclose(w, [0.4, 0.025, 0.1, 0.2, 0.05, 0.0])       # constant: 0
    w = relative_ridge_weights("linear", np.array([[1.0, 4.0, 9.0], [2.0, 1.0, 3.0]]), 1.0)
    np.testing.assert_allclose(w, [[1, 4, 0], [2, 1, 0]])
    with pytest.raises(ValueError, match="column norms"):
        relative_ridge_weights("linear", np.ones(6), 1.0)


def test_fit_ridge_is_invariant_to_the_units_and_frame_count():
    """The issue-17 fix: rescaling d1, d2 (mm → cm, or two actors' different ranges) or
    repeating every frame leaves the fitted PDM's values unchanged (the paper's γ/σ rows do
    not: their weight against the data is γ²/(T σ^{4(i+j)}))."""
    d1, d2, _, f = _exact("biquadratic", T=25, P=30)
    f = f + np.random.default_rng(7).normal(size=f.shape)
    c = fit(d1, d2, f, ridge=0.5)
    c_cm = fit(d1 / 10, d2 / 4, f, ridge=0.5)
    np.testing.assert_allclose(evaluate(c_cm, d1[3] / 10, d2[3] / 4), evaluate(c, d1[3], d2[3]), atol=1e-9)
    c_twice = fit(np.tile(d1, (2, 1)), np.tile(d2, (2, 1)), np.tile(f, (2, 1, 1)), ridge=0.5)
    np.testing.assert_allclose(c_twice, c, atol=1e-9)


def test_fit_single_term_shrinks_by_one_over_one_plus_ridge_squared():
    """Hand-computed: a linear fit of f = 3 d1 with d2 = 0 and d1 of zero mean: the d1
    normal equation decouples, (1 + ρ²) Σd1² a = 3 Σd1², so a = 3 / (1 + ρ²)."""
    d1 = np.array([[-2.0], [-1.0], [1.0], [2.0]])
    d2 = np.zeros_like(d1)
    coeffs = fit(d1, d2, 3 * d1, order="linear", ridge=0.5)
    np.testing.assert_allclose(coeffs[0, 0], [3 / 1.25, 0.0, 0.0], atol=1e-12)


# --- 1. exact recovery -------------------------------------------------------------------


@pytest.mark.parametrize("gamma", [1e-12, 0.0])
def test_fit_recovers_exact_biquadratic(gamma):
    d1, d2, a, f = _exact("biquadratic")
    coeffs = fit(d1, d2, f, ridge=gamma)
    assert coeffs.shape == (500, 3, 6) and coeffs.dtype == np.float64
    np.testing.assert_allclose(coeffs, a, atol=1e-6)
    np.testing.assert_allclose(fit_residual_rms(coeffs, d1, d2, f), 0, atol=1e-9)


def test_fit_accepts_float32_and_single_channel():
    d1, d2, a, f = _exact("biquadratic", C=1)
    c64 = fit(d1, d2, f[..., 0], ridge=1e-12)
    assert c64.shape == (500, 1, 6)
    d1_32, d2_32, f_32 = (x.astype(np.float32) for x in (d1, d2, f[..., 0]))
    c32 = fit(d1_32, d2_32, f_32, ridge=1e-12)
    assert c32.dtype == np.float64
    # float32 rounding of the inputs (~1e-7 relative), not of the arithmetic
    np.testing.assert_allclose(c32, a, atol=1e-4)


# --- 2. gamma → 0 is plain least squares ----------------------------------------------------


@pytest.mark.parametrize("gamma", [1e-12, 0.0])
def test_fit_small_gamma_equals_lstsq_on_noisy_data(gamma):
    d1, d2, _, f = _exact("biquadratic", T=40, P=50)
    f = f + np.random.default_rng(2).normal(scale=0.3, size=f.shape)
    coeffs = fit(d1, d2, f, ridge=gamma)
    for p in (0, 7, 19, 33, 49):
        np.testing.assert_allclose(coeffs[p], _lstsq(d1[:, p], d2[:, p], f[:, p]), atol=1e-8)


def test_fit_equals_stacked_lstsq_with_regularization_rows():
    """γ > 0: the normal equations solve ma2008 §4.2's stacked system [Φ; diag(w)] a = [f; 0]."""
    d1, d2, _, f = _exact("biquadratic", T=25, P=20)
    f = f + np.random.default_rng(3).normal(size=f.shape)
    gamma = 0.5
    coeffs = fit(d1, d2, f, ridge=gamma)
    for p in (0, 11, 19):
        Phi = design_matrix(d1[:, p], d2[:, p])
        w = relative_ridge_weights("biquadratic", np.linalg.norm(Phi, axis=0), gamma)
        A = np.vstack([Phi, np.diag(w)[:-1]])                                  # 5 γ rows
        b = np.vstack([f[:, p], np.zeros((5, 3))])
        np.testing.assert_allclose(coeffs[p], np.linalg.lstsq(A, b, rcond=None)[0].T, atol=1e-10)


# --- 3. regularization ---------------------------------------------------------------------


def test_fit_constant_parameter_terms_go_to_zero():
    """d2 never varies: its own terms (d2², d2) are absorbed by the unregularized constant;
    d1 d2 = 0.7 d1 is parallel to d1, and the relative ridge shares the d1 slope between
    them (a3 + 0.7 a2 = the true a3); the PDM reproduces the data."""
    rng = np.random.default_rng(5)
    T, P = 30, 40
    d1 = rng.uniform(-2, 2, (T, P))
    d2 = np.full((T, P), 0.7)                                      # d2 never varies
    a0, a3, a5 = rng.normal(size=(3, P, 1))
    f = a0 * d1[..., None] ** 2 + a3 * d1[..., None] + a5         # (T,P,1)
    coeffs = fit(d1, d2, f, ridge=1e-3)
    assert np.all(np.isfinite(coeffs))
    np.testing.assert_allclose(coeffs[..., [1, 4]], 0, atol=1e-7)      # d2², d2
    np.testing.assert_allclose(coeffs[..., 3] + 0.7 * coeffs[..., 2], a3, atol=1e-4)
    np.testing.assert_allclose(evaluate(coeffs, d1, d2), f, atol=1e-4)


def test_fit_larger_gamma_shrinks_nonconstant_coefficients_monotonically():
    d1, d2, _, f = _exact("biquadratic", T=30, P=60)
    f = f + np.random.default_rng(6).normal(scale=0.5, size=f.shape)
    norms = np.linalg.norm(design_matrix(d1, d2), axis=0)                       # (P,6)
    scale = relative_ridge_weights("biquadratic", norms, 1.0)[:, None, :5]      # (P,1,5)
    norms = []
    for gamma in (1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0):
        coeffs = fit(d1, d2, f, ridge=gamma)
        norms.append(np.linalg.norm(scale * coeffs[..., :5], axis=-1))      # (P,C) penalty
    norms = np.array(norms)
    assert np.all(np.diff(norms, axis=0) <= 1e-12)
    assert np.all(norms[-1] < 0.05 * norms[0])
    # the unregularized constant absorbs the mean when everything else is shrunk away
    np.testing.assert_allclose(fit(d1, d2, f, ridge=1e6)[..., 5], f.mean(axis=0), atol=1e-6)


# --- 4. other orders ------------------------------------------------------------------------


@pytest.mark.parametrize("order", ["linear", "bicubic"])
def test_fit_recovers_exact_data_of_its_order(order):
    d1, d2, a, f = _exact(order, T=30, P=200)
    coeffs = fit(d1, d2, f, order=order, ridge=1e-12)
    assert coeffs.shape == (200, 3, ORDERS[order])
    np.testing.assert_allclose(coeffs, a, atol=1e-6)


def test_bicubic_fit_of_biquadratic_data_has_no_cubic_terms():
    d1, d2, a, f = _exact("biquadratic", T=30, P=200)
    coeffs = fit(d1, d2, f, order="bicubic", ridge=1e-12)
    np.testing.assert_allclose(coeffs[..., :4], 0, atol=1e-7)        # d1³, d2³, d1²d2, d1d2²
    np.testing.assert_allclose(coeffs[..., 4:], a, atol=1e-6)        # same term order as eq. 1


# --- 5. missing measurements ----------------------------------------------------------------


def test_fit_ignores_nan_rows():
    d1, d2, _, f = _exact("biquadratic", T=30, P=40)
    rng = np.random.default_rng(7)
    f = f + rng.normal(scale=0.2, size=f.shape)
    seen = rng.random((30, 40)) > 0.3
    f_nan = np.where(seen[..., None], f, np.nan)
    coeffs = fit(d1, d2, f_nan, ridge=1e-2)
    for p in range(0, 40, 7):
        k = seen[:, p]
        ref = fit(d1[k, p : p + 1], d2[k, p : p + 1], f[k, p : p + 1], ridge=1e-2)
        np.testing.assert_allclose(coeffs[p], ref[0], rtol=1e-10, atol=1e-12)


def test_fit_ignores_nan_per_channel_and_nan_parameters():
    d1, d2, _, f = _exact("biquadratic", T=30, P=20)
    rng = np.random.default_rng(8)
    f = f + rng.normal(scale=0.2, size=f.shape)
    f_nan = f.copy()
    f_nan[rng.random(f.shape) < 0.2] = np.nan                      # channels differ
    d1_nan = d1.copy()
    d1_nan[3, ::2] = np.nan                                        # parameter missing too
    coeffs = fit(d1_nan, d2, f_nan, ridge=0.1)
    for p in (0, 5, 12):
        for c in range(3):
            k = np.isfinite(f_nan[:, p, c]) & np.isfinite(d1_nan[:, p])
            one = np.s_[k, p : p + 1]
            ref = fit(d1[one], d2[one], f[one][..., c], ridge=0.1)
            np.testing.assert_allclose(coeffs[p, c], ref[0, 0], rtol=1e-10, atol=1e-12)


def test_fit_underdetermined_and_unseen_texels_do_not_crash():
    d1, d2, _, f = _exact("biquadratic", T=20, P=3, C=1)
    f = f.copy()
    f[3:, 0] = np.nan                                              # 3 rows < 6 coefficients
    f[:, 1] = np.nan                                               # never seen
    coeffs = fit(d1, d2, f, ridge=0.0)
    assert np.all(np.isfinite(coeffs))
    np.testing.assert_allclose(evaluate(coeffs, d1[:3], d2[:3])[:, 0], f[:3, 0], atol=1e-9)
    np.testing.assert_array_equal(coeffs[1], 0)                    # no data: zero map
    rms = fit_residual_rms(coeffs, d1, d2, f)
    assert np.isnan(rms[1, 0]) and rms[0, 0] < 1e-9 and rms[2, 0] < 1e-9
    assert np.all(np.isfinite(fit(d1, d2, f, ridge=1e-3)))


def test_fit_singular_without_regularization_matches_lstsq_prediction():
    rng = np.random.default_rng(9)
    d1 = rng.uniform(-2, 2, (25, 4))
    d2 = np.full((25, 4), 0.3)                                     # rank-deficient Φ
    f = rng.normal(size=(25, 4, 2))
    coeffs = fit(d1, d2, f, ridge=0.0)
    assert np.all(np.isfinite(coeffs))
    for p in range(4):
        Phi = design_matrix(d1[:, p], d2[:, p])
        ref = np.linalg.lstsq(Phi, f[:, p], rcond=None)[0]
        np.testing.assert_allclose(Phi @ coeffs[p].T, Phi @ ref, atol=1e-8)


# --- 6. chunking ----------------------------------------------------------------------------


def test_fit_chunking_does_not_change_result():
    d1, d2, _, f = _exact("biquadratic", T=30, P=100)
    f = f + np.random.default_rng(10).normal(size=f.shape)
    f[np.random.default_rng(11).random(f.shape) < 0.1] = np.nan
    np.testing.assert_allclose(fit(d1, d2, f, chunk=7), fit(d1, d2, f), rtol=0, atol=1e-12)


# --- 7. evaluation --------------------------------------------------------------------------


def test_evaluate_shapes_one_and_several_frames():
    rng = np.random.default_rng(12)
    P, C, F = 50, 3, 4
    coeffs = rng.normal(size=(P, C, 6))
    d1, d2 = _params(rng, F, P)
    one = evaluate(coeffs, d1[0], d2[0])
    many = evaluate(coeffs, d1, d2)
    assert one.shape == (P, C) and many.shape == (F, P, C) and many.dtype == np.float64
    np.testing.assert_allclose(many[0], one, rtol=1e-15)
    ref = np.einsum("fpk,pck->fpc", design_matrix(d1, d2), coeffs)
    np.testing.assert_allclose(many, ref, rtol=1e-12, atol=1e-12)


def test_evaluate_rejects_wrong_texel_count():
    with pytest.raises(ValueError):
        evaluate(np.zeros((5, 1, 6)), np.zeros(4), np.zeros(4))
    with pytest.raises(ValueError):
        evaluate(np.zeros((5, 1, 7)), np.zeros(5), np.zeros(5))


def test_fit_residual_rms_is_nan_aware_rms():
    rng = np.random.default_rng(13)
    T, P, C = 12, 10, 2
    d1, d2 = _params(rng, T, P)
    coeffs = rng.normal(size=(P, C, 6))
    f = evaluate(coeffs, d1, d2) + rng.normal(size=(T, P, C))
    f[rng.random(f.shape) < 0.3] = np.nan
    r = evaluate(coeffs, d1, d2) - f
    np.testing.assert_allclose(
        fit_residual_rms(coeffs, d1, d2, f), np.sqrt(np.nanmean(r**2, axis=0)), rtol=1e-12
    )


# --- the paper's γ rows (``gamma`` given; the fit of main before ``ridge`` existed) ---------


def _paper_problem():
    """The seeded problem of ``data/paper_gamma30_fit.npy``: (T,P) d1, d2 and (T,P,3) f with
    NaN rows per channel and in d1, and texels 0-2 with a d2 that never varies."""
    rng = np.random.default_rng(2008)
    T, P = 24, 40
    d1 = rng.normal(scale=2.0, size=(T, P))
    d2 = rng.normal(scale=0.5, size=(T, P))
    d2[:, :3] = 0.7
    f = rng.normal(size=(T, P, 3))
    f[rng.random(f.shape) < 0.15] = np.nan
    d1[rng.random(d1.shape) < 0.05] = np.nan
    return d1, d2, f


def test_fit_with_gamma_is_bit_identical_to_the_paper_rows_fit_before_ridge():
    """``data/paper_gamma30_fit.npy`` was written by main's ``fit(d1, d2, f, "biquadratic",
    30.0)`` (γ/(σ1^i σ2^j) rows, σ floor): giving ``gamma`` reproduces it exactly, whatever
    ``ridge`` says, so clients sending ``gamma: 30`` and models stored with it are unchanged."""
    d1, d2, f = _paper_problem()
    ref = np.load(Path(__file__).parent / "data" / "paper_gamma30_fit.npy")
    got = fit(d1, d2, f, "biquadratic", ridge=0.1, gamma=30.0)
    for ridge in (0.0, 5.0):                                           # ridge ignored: bit for bit
        assert np.array_equal(fit(d1, d2, f, "biquadratic", ridge=ridge, gamma=30.0), got)
    # the stored fit to LAPACK's rounding: OpenBLAS picks its kernels by CPU, so another
    # machine's solve differs in the last bits (measured on an AMD EPYC: coefficients that are
    # zero up to rounding, ~1e-43, differ; every other entry is equal)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14 * np.abs(ref).max())
    assert not np.allclose(fit(d1, d2, f, "biquadratic"), ref)        # default: the ridge


def test_regularization_weights_are_gamma_over_sigma_powers():
    w = regularization_weights("biquadratic", 2.0, 0.5, 0.1)
    np.testing.assert_allclose(w, [0.1 / 4, 0.1 / 0.25, 0.1 / 1.0, 0.1 / 2, 0.1 / 0.5, 0.0])
    w = regularization_weights("linear", np.array([1.0, 4.0]), np.array([2.0, 1.0]), 1.0)
    np.testing.assert_allclose(w, [[1, 0.5, 0], [0.25, 1, 0]])


def test_regularization_weights_floor_sigma():
    w = regularization_weights("linear", 0.0, 1.0, 1e-3, sigma_floor=1e-6)
    np.testing.assert_allclose(w, [1e3, 1e-3, 0.0])


def test_fit_gamma_equals_stacked_lstsq_with_paper_rows():
    """γ > 0: the normal equations solve ma2008 §4.2's stacked system [Φ; diag(w)] a = [f; 0]."""
    d1, d2, _, f = _exact("biquadratic", T=25, P=20)
    f = f + np.random.default_rng(3).normal(size=f.shape)
    coeffs = fit(d1, d2, f, gamma=0.5)
    for p in (0, 11, 19):
        w = regularization_weights("biquadratic", d1[:, p].std(), d2[:, p].std(), 0.5)
        A = np.vstack([design_matrix(d1[:, p], d2[:, p]), np.diag(w)[:-1]])   # 5 γ rows
        b = np.vstack([f[:, p], np.zeros((5, 3))])
        np.testing.assert_allclose(coeffs[p], np.linalg.lstsq(A, b, rcond=None)[0].T, atol=1e-10)


def test_fit_gamma_single_term_hand_computed():
    """Linear fit of f = 3 d1, d2 = 0, d1 = (-2, -1, 1, 2): σ1² = 2.5, Σd1² = 10, so the d1
    equation is (10 + γ²/2.5) a = 30; γ = 5: a = 30 / 20 = 1.5 (the ridge mode with ρ = 0.5
    gives 3 / 1.25 = 2.4, test above)."""
    d1 = np.array([[-2.0], [-1.0], [1.0], [2.0]])
    coeffs = fit(d1, np.zeros_like(d1), 3 * d1, order="linear", gamma=5.0)
    np.testing.assert_allclose(coeffs[0, 0, [0, 2]], [1.5, 0.0], atol=1e-12)


def test_fit_gamma_default_sigma_is_std_of_parameters_over_frames():
    d1, d2, _, f = _exact("biquadratic", T=20, P=30)
    f = f + np.random.default_rng(4).normal(size=f.shape)
    sigma = np.stack([d1.std(axis=0), d2.std(axis=0)], axis=1)
    np.testing.assert_allclose(
        fit(d1, d2, f, gamma=0.3), fit(d1, d2, f, gamma=0.3, sigma=sigma), rtol=1e-12, atol=1e-12
    )


def test_fit_gamma_constant_parameter_terms_go_to_zero():
    rng = np.random.default_rng(5)
    T, P = 30, 40
    d1 = rng.uniform(-2, 2, (T, P))
    d2 = np.full((T, P), 0.7)                                      # d2 never varies: σ floor
    a0, a3, a5 = rng.normal(size=(3, P, 1))
    f = a0 * d1[..., None] ** 2 + a3 * d1[..., None] + a5         # (T,P,1)
    coeffs = fit(d1, d2, f, gamma=1e-3)
    np.testing.assert_allclose(coeffs[..., [1, 2, 4]], 0, atol=1e-9)   # d2², d1 d2, d2
    np.testing.assert_allclose(coeffs[..., [0, 3, 5]], np.concatenate([a0, a3, a5], -1)[:, None], atol=1e-6)


def test_fit_rejects_negative_ridge_and_gamma():
    d1, d2, _, f = _exact("linear", T=6, P=2)
    with pytest.raises(ValueError, match="ridge"):
        fit(d1, d2, f, "linear", ridge=-0.1)
    with pytest.raises(ValueError, match="gamma"):
        fit(d1, d2, f, "linear", gamma=-1.0)


# --- the neutral anchor (issue 17: the polynomial at zero deformation is the neutral) -----


@pytest.mark.parametrize("order", sorted(ORDERS))
def test_anchored_fit_reproduces_the_anchor_exactly_at_zero_deformation(order):
    d1, d2, _, f = _exact(order, T=20, P=40)
    f = f + np.random.default_rng(3).normal(size=f.shape)
    f0 = np.random.default_rng(4).normal(size=f.shape[1:])
    for kw in ({"ridge": 0.1}, {"ridge": 0.0}, {"gamma": 30.0}):
        c = fit(d1, d2, f, order, anchor=f0, **kw)
        assert np.array_equal(evaluate(c, np.zeros(40), np.zeros(40)), f0)
        assert np.array_equal(c[..., -1], f0)


def test_anchored_fit_is_the_constrained_least_squares():
    """Constant fixed to f0, the other terms the plain least squares of f − f0 (ridge 0), and
    data that are exactly a polynomial through f0 are recovered."""
    d1, d2, a, f = _exact("biquadratic", T=30, P=25)
    f_noisy = f + np.random.default_rng(5).normal(size=f.shape)
    f0 = np.random.default_rng(6).normal(size=f.shape[1:])
    c = fit(d1, d2, f_noisy, anchor=f0, ridge=0.0)
    for p in (0, 7, 24):
        Phi = design_matrix(d1[:, p], d2[:, p])[:, :-1]
        ref = np.linalg.lstsq(Phi, f_noisy[:, p] - f0[p], rcond=None)[0].T
        np.testing.assert_allclose(c[p, :, :-1], ref, rtol=1e-8, atol=1e-9)
    exact = fit(d1, d2, f, anchor=a[..., -1], ridge=0.0)
    np.testing.assert_allclose(exact, a, rtol=1e-8, atol=1e-8)


def test_anchor_none_is_the_free_constant_fit_bit_for_bit_and_bad_anchor_is_refused():
    d1, d2, _, f = _exact("biquadratic", T=12, P=10)
    assert np.array_equal(fit(d1, d2, f, anchor=None), fit(d1, d2, f))
    assert np.array_equal(fit(d1, d2, f, gamma=30.0, anchor=None), fit(d1, d2, f, gamma=30.0))
    with pytest.raises(ValueError, match="anchor"):
        fit(d1, d2, f, anchor=np.zeros((10, 2)))
    with pytest.raises(ValueError, match="anchor"):
        fit(d1, d2, f, anchor=np.full((10, 3), np.nan))


# --- leave-one-frame-out residuals (PRESS) -------------------------------------------------


def test_loo_residuals_hand_computed_line():
    """d2 ≡ 0 (its term drops out), f a line in d1 plus misfit: d1 = 0, 1, 2, 3, f = 0, 1, 2, 4.
    The fit is f̂ = 1.3 d1 − 0.2 (residuals 0.2, −0.1, −0.4, 0.3), leverages 0.7, 0.3, 0.3, 0.7,
    so the PRESS residuals are 2/3, −1/7, −4/7, 1 (e.g. without frame 3 the line through the
    other three is f = d1, predicting 3 for 4)."""
    d1 = np.array([[0.0], [1.0], [2.0], [3.0]])
    f = np.array([[0.0], [1.0], [2.0], [4.0]])
    e = loo_residuals(d1, np.zeros_like(d1), f, "linear", ridge=0.0)
    np.testing.assert_allclose(e[:, 0, 0], [2 / 3, -1 / 7, -4 / 7, 1.0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("kw", [{"ridge": 0.0}, {"ridge": 0.3}, {"gamma": 2.0}, {"ridge": 0.3, "anchor": True}])
def test_loo_residuals_are_the_refits_without_each_frame(kw):
    """Against T explicit refits of the augmented system [Φ₋ₜ; diag(w)] a = [f₋ₜ; 0] by lstsq,
    with the ridge rows w of all frames held fixed (the PRESS identity's premise)."""
    rng = np.random.default_rng(3)
    T, P, C = 14, 6, 2
    d1, d2 = _params(rng, T, P)
    f = rng.normal(size=(T, P, C))
    anchor = rng.normal(size=(P, C)) if kw.get("anchor") else None
    kw = {k: v for k, v in kw.items() if k != "anchor"}
    e = loo_residuals(d1, d2, f, anchor=anchor, **kw)
    for p in range(P):
        Phi = design_matrix(d1[:, p], d2[:, p])
        if "gamma" in kw:
            w = regularization_weights("biquadratic", d1[:, p].std(), d2[:, p].std(), kw["gamma"])
        else:
            w = relative_ridge_weights("biquadratic", np.linalg.norm(Phi, axis=0), kw["ridge"])
        g = f[:, p] - (0 if anchor is None else anchor[p])
        cols = slice(0, 5) if anchor is not None else slice(None)
        for t in range(T):
            keep = np.arange(T) != t
            A = np.vstack([Phi[keep][:, cols], np.diag(w[cols])])
            b = np.vstack([g[keep], np.zeros((len(w[cols]), C))])
            a = np.linalg.lstsq(A, b, rcond=None)[0]
            np.testing.assert_allclose(e[t, p], g[t] - Phi[t, cols] @ a, rtol=1e-9, atol=1e-12)


def test_loo_residuals_of_an_exact_polynomial_are_zero():
    d1, d2, _, f = _exact("biquadratic", T=20, P=50, C=3)
    np.testing.assert_allclose(loo_residuals(d1, d2, f, ridge=0.0), 0.0, atol=1e-9)



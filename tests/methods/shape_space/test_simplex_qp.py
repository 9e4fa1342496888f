"""Tests for service.methods.shape_space.simplex_qp: the exact convex matching of bermano2014 §5.3."""

import itertools

import numpy as np
import pytest
from scipy.optimize import minimize

from service.methods.shape_space.simplex_qp import simplex_least_squares, solve_simplex_qp


def _problem(rng, k, N, spread=1.0):
    D = rng.normal(size=(k, N)) * spread
    a = rng.normal(size=k) * spread
    return D, a


def _objective(D, a, w, Om=None):
    r = D @ w - a
    return float(r @ (r if Om is None else Om * r))


def _enumerate(G, b):
    """Brute force: the best equality-constrained solution over all supports that is feasible."""
    N = len(b)
    best = (np.inf, None)
    for size in range(1, N + 1):
        for S in itertools.combinations(range(N), size):
            S = list(S)
            K = np.block([[G[np.ix_(S, S)], np.ones((size, 1))], [np.ones((1, size)), np.zeros((1, 1))]])
            try:
                z = np.linalg.solve(K, np.r_[b[S], 1.0])[:size]
            except np.linalg.LinAlgError:
                continue
            if np.all(z >= -1e-12):
                w = np.zeros(N)
                w[S] = np.maximum(z, 0)
                w /= w.sum()
                f = w @ G @ w - 2 * b @ w
                if f < best[0] - 1e-14:
                    best = (f, w)
    return best


@pytest.mark.parametrize("seed", range(12))
def test_matches_enumeration_of_all_supports(seed):
    rng = np.random.default_rng(seed)
    D, a = _problem(rng, k=9, N=7)
    G, b = D.T @ D, D.T @ a
    res = solve_simplex_qp(G, b, ridge=0.0)
    f_ref, w_ref = _enumerate(G, b)
    assert res.w.min() >= 0 and abs(res.w.sum() - 1) < 1e-14
    assert abs(res.objective - f_ref) <= 1e-8 * max(1.0, abs(f_ref))
    np.testing.assert_allclose(res.w, w_ref, atol=1e-9)


@pytest.mark.parametrize("seed", range(8))
def test_matches_slsqp_on_larger_weighted_problems(seed):
    rng = np.random.default_rng(100 + seed)
    D, a = _problem(rng, k=60, N=25, spread=3.0)
    Om = rng.uniform(0.0, 1.0, 60)                     # a region's component weights
    res = simplex_least_squares(D, a, Om, ridge=0.0)
    ref = minimize(lambda w: _objective(D, a, w, Om), np.full(25, 1 / 25),
                   jac=lambda w: 2 * D.T @ (Om * (D @ w - a)),
                   bounds=[(0, 1)] * 25, constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1}],
                   method="SLSQP", options={"ftol": 1e-15, "maxiter": 1000})
    w_ref = np.clip(ref.x, 0, None) / np.clip(ref.x, 0, None).sum()        # SLSQP's, made feasible
    f, f_ref = _objective(D, a, res.w, Om), _objective(D, a, w_ref, Om)
    assert f <= f_ref + 1e-8 * max(1.0, f_ref)        # never worse than SLSQP
    assert abs(f - f_ref) <= 1e-8 * max(1.0, f_ref)
    np.testing.assert_allclose(res.w, ref.x, atol=1e-5)
    # the KKT conditions hold to rounding: equal gradient on the support, not lower off it
    g = D.T @ (Om * (D @ res.w - a))
    on = res.w > 0
    assert np.ptp(g[on]) < 1e-9 * max(1.0, np.abs(g).max())
    assert g[~on].min() >= g[on].mean() - 1e-9 * max(1.0, np.abs(g).max())


def test_point_inside_the_hull_is_reproduced_exactly():
    rng = np.random.default_rng(5)
    D = rng.normal(size=(12, 6))
    w_true = np.array([0.5, 0.0, 0.3, 0.0, 0.2, 0.0])
    res = simplex_least_squares(D, D @ w_true)
    np.testing.assert_allclose(res.w, w_true, atol=1e-9)
    assert res.iterations <= 10


def test_column_equal_to_the_target_gets_all_the_weight():
    rng = np.random.default_rng(6)
    D = rng.normal(size=(30, 40))                     # more frames than dimensions: G singular
    res = simplex_least_squares(D, D[:, 17])
    assert res.w[17] > 1 - 1e-9 and np.count_nonzero(res.w > 1e-9) == 1


def test_more_frames_than_dimensions_stays_optimal():
    rng = np.random.default_rng(7)
    D, a = _problem(rng, k=5, N=30)
    res = simplex_least_squares(D, a)
    ref = minimize(lambda w: _objective(D, a, w), np.full(30, 1 / 30), bounds=[(0, 1)] * 30,
                   constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1}], method="SLSQP",
                   options={"ftol": 1e-15, "maxiter": 1000})
    assert _objective(D, a, res.w) <= ref.fun + 1e-8
    assert np.count_nonzero(res.w > 1e-9) <= 6        # a vertex of the reduced problem (Carathéodory)


def test_single_column_and_shape_errors():
    res = solve_simplex_qp(np.array([[2.0]]), np.array([0.3]))
    assert res.w.tolist() == [1.0]
    with pytest.raises(ValueError):
        solve_simplex_qp(np.eye(3), np.zeros(2))


def test_ridged_is_the_sum_with_the_identity_bit_for_bit():
    from service.methods.shape_space.simplex_qp import ridged

    rng = np.random.default_rng(5)
    D = rng.normal(size=(40, 25))
    G = D.T @ D
    c = 1e-8 * float(np.mean(np.diag(G)))
    got = ridged(G, c)
    np.testing.assert_array_equal(got, G + c * np.eye(len(G)))
    assert got is not G and not np.shares_memory(got, G)

"""Tests for service.methods.pose_space.rbf (bickel2008 §5.2-5.3, eq. 2 and 5)."""

import numpy as np
import pytest
import scipy.sparse as sp

from service.methods.pose_space import rbf
from service.methods.pose_space.weighting import equal_weights, weighted_sq_distances


def _features(P=7, E=12, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(scale=0.2, size=(P, E)), rng


def test_exact_interpolation_reproduces_every_example_pose():
    Fb, rng = _features()
    D = rng.normal(size=(1, 7, 30))                                           # PSD: one system
    r = np.linalg.norm(Fb[:, None] - Fb[None], axis=2)
    Phi = rbf.kernel(r)[None]
    W = rbf.solve_weights(Phi, D, exact=True)
    np.testing.assert_allclose(Phi @ W, D, atol=1e-9, rtol=0)
    # WPSD: one system per vertex with its own metric (eq. 5)
    A = sp.random(50, 12, density=0.4, random_state=3, format="csr") + sp.eye(50, 12, format="csr")
    A = sp.diags(1 / np.asarray(A.sum(axis=1)).ravel()) @ A
    Phi_v = np.sqrt(weighted_sq_distances(A.tocsr(), Fb, Fb))                 # (50,7,7)
    Dv = rng.normal(size=(50, 7, 3))
    Wv = rbf.solve_weights(Phi_v, Dv, exact=True)
    assert np.abs(Phi_v @ Wv - Dv).max() < 1e-9


def test_wpsd_with_equal_alpha_is_psd():
    Fb, rng = _features(P=5, E=9, seed=1)
    T = rng.normal(scale=0.2, size=(40, 9))                                   # training frames
    D = rng.normal(size=(40, 6, 3))                                           # 6 vertices
    f = rng.normal(scale=0.2, size=(3, 9))                                    # evaluated poses
    for lam in (0.0, 1e-3):
        # PSD: the global distance, one system for all vertices (C = 18)
        Phi = rbf.kernel(np.linalg.norm(T[:, None] - Fb[None], axis=2))[None]
        W = rbf.solve_weights(Phi, D.reshape(1, 40, 18), lam)
        psd = rbf.kernel(np.linalg.norm(f[:, None] - Fb[None], axis=2)) @ W[0]
        # WPSD with α = 1/E everywhere: per-vertex systems
        A = equal_weights(6, 9)
        Phi_v = rbf.kernel(np.sqrt(weighted_sq_distances(A, T, Fb)))          # (6,40,5)
        Wv = rbf.solve_weights(Phi_v, D.transpose(1, 0, 2), lam)
        wpsd = np.einsum("vfp,vpc->fvc", rbf.kernel(np.sqrt(weighted_sq_distances(A, f, Fb))), Wv)
        np.testing.assert_allclose(wpsd.reshape(3, 18), psd, atol=1e-9, rtol=1e-9)


def test_greedy_selection_starts_at_the_rest_pose_and_decreases_the_error():
    rng = np.random.default_rng(5)
    T = rng.normal(scale=0.2, size=(30, 8))
    T[3] = 0.0                                                                # the rest pose
    D = np.sin(3 * T @ rng.normal(size=(8, 4)))[None]                         # (1,30,4)
    column = lambda j: np.linalg.norm(T - T[j], axis=1)[None]
    sel, err = rbf.greedy_basis(column, D, size=10, first=3)
    assert sel[0] == 3 and len(set(sel)) == 10
    assert np.all(np.diff(err) <= 1e-12)                  # least squares: nested bases
    # the second pose is the worst-fit frame of the one-pose fit
    Phi = column(3)[..., None]
    W = rbf.fit_basis(Phi, D, [3], 0.0, False)
    res = rbf.residual_sq(Phi, D, W)
    res[3] = -1
    assert sel[1] == int(np.argmax(res))
    # a threshold stops early
    sel_t, err_t = rbf.greedy_basis(column, D, size=10, first=3, threshold=err[4] + 1e-12)
    assert len(sel_t) == 5 and err_t[-1] <= err[4] + 1e-12
    # exact mode interpolates the selected frames
    sel_e, _ = rbf.greedy_basis(column, D, size=6, first=3, exact=True)
    Phi_e = np.stack([column(j)[0] for j in sel_e], axis=1)[None]
    W = rbf.fit_basis(Phi_e, D, sel_e, 0.0, True)
    np.testing.assert_allclose((Phi_e @ W)[:, sel_e], D[:, sel_e], atol=1e-9)


def test_gram_factor_gives_the_same_residuals():
    rng = np.random.default_rng(6)
    D = rng.normal(size=(20, 300))
    Y = rbf.gram_factor(D @ D.T)
    Phi = rng.uniform(size=(1, 20, 4))
    r1 = rbf.residual_sq(Phi, D[None], rbf.solve_weights(Phi, D[None]))
    r2 = rbf.residual_sq(Phi, Y[None], rbf.solve_weights(Phi, Y[None]))
    np.testing.assert_allclose(r2, r1, rtol=1e-8)


def test_smoothing_shrinks_the_weights():
    Fb, rng = _features(P=6, E=5, seed=7)
    Phi = rbf.kernel(np.linalg.norm(Fb[:, None] - Fb[None], axis=2))[None]
    D = rng.normal(size=(1, 6, 2))
    n0 = np.linalg.norm(rbf.solve_weights(Phi, D, 0.0, exact=True))
    n1 = np.linalg.norm(rbf.solve_weights(Phi, D, 1e-2, exact=True))
    assert n1 < n0

"""Tests for service.methods.pose_space.polynomial (the [CBC*01] linear term of eq. 2 / eq. 5)."""

import numpy as np
import scipy.sparse as sp

from service.methods.pose_space import polynomial, rbf
from service.methods.pose_space.weighting import equal_weights, weighted_sq_distances


def _alpha(n=40, E=10, seed=3):
    A = sp.random(n, E, density=0.3, random_state=seed, format="csr") + sp.csr_matrix(np.eye(E)[np.arange(n) % E])
    return (sp.diags(1 / np.asarray(A.sum(axis=1)).ravel()) @ A).tocsr()


def test_support_index_by_hand():
    S = sp.csr_matrix(np.array([[0, 2.0, 0, 1.0], [0, 0, 3.0, 0]]))
    idx, mask = polynomial.support_index(S)
    np.testing.assert_array_equal(idx, [[1, 3], [2, 0]])
    np.testing.assert_array_equal(mask, [[True, True], [True, False]])
    Q = polynomial.design(np.array([[10.0, 11.0, 12.0, 13.0]]), idx, mask)
    np.testing.assert_array_equal(Q[:, 0], [[1.0, 11.0, 13.0], [1.0, 12.0, 0.0]])


def test_local_linear_detail_is_reproduced_exactly_only_with_the_polynomial():
    # detail that is a linear function of each vertex's supported features: d_v = c_v + a_v·f
    rng = np.random.default_rng(0)
    n, E, T, P = 40, 10, 60, 5
    A = _alpha(n, E)
    idx, mask = polynomial.support_index(A)
    coef = rng.normal(size=(n, 1 + idx.shape[1], 3)) * np.concatenate([np.ones((n, 1)), mask], 1)[..., None]
    F = rng.normal(scale=0.2, size=(T, E))
    Q = polynomial.design(F, idx, mask)
    D = Q @ coef                                                               # (n,T,3)
    basis = [0, 7, 19, 33, 51]
    Phi = np.sqrt(weighted_sq_distances(A, F, F[basis]))                       # (n,T,P)
    W = rbf.fit_basis(Phi, D, basis, 0.0, False, Q)
    f_new = rng.normal(scale=0.2, size=(4, E))
    const, lin = polynomial.to_sparse(W[:, P:], idx, mask, E)
    pred = (np.einsum("nfp,npc->fnc", np.sqrt(weighted_sq_distances(A, f_new, F[basis])), W[:, :P])
            + polynomial.evaluate(const, lin, f_new))
    truth = np.einsum("nfq,nqc->fnc", polynomial.design(f_new, idx, mask), coef)
    assert np.abs(pred - truth).max() < 1e-6
    W0 = rbf.fit_basis(Phi, D, basis, 0.0, False)                               # eq. 5 as printed
    pred0 = np.einsum("nfp,npc->fnc", np.sqrt(weighted_sq_distances(A, f_new, F[basis])), W0)
    assert np.abs(pred0 - truth).max() > 0.1


def test_exact_interpolation_with_the_polynomial_is_exact():
    rng = np.random.default_rng(1)
    n, E, P = 30, 8, 4                                  # P < 1 + |support|: minimum-norm solve
    A = _alpha(n, E, seed=5)
    idx, mask = polynomial.support_index(A)
    Fb = rng.normal(scale=0.2, size=(P, E))
    Phi = np.sqrt(weighted_sq_distances(A, Fb, Fb))
    D = rng.normal(size=(n, P, 3))
    W = rbf.fit_basis(Phi, D, np.arange(P), 0.0, True, polynomial.design(Fb, idx, mask))
    assert np.abs(rbf.columns(Phi, polynomial.design(Fb, idx, mask)) @ W - D).max() < 1e-9


def test_wpsd_with_equal_alpha_and_the_polynomial_is_psd_with_it():
    rng = np.random.default_rng(2)
    E, T, n = 6, 30, 4
    F = rng.normal(scale=0.2, size=(T, E))
    D = rng.normal(size=(T, n, 3))
    basis = [0, 5, 11]
    full = (np.arange(E)[None], np.ones((1, E), bool))
    Qg = polynomial.design(F, *full)
    Phi = np.linalg.norm(F[:, None] - F[basis][None], axis=2)[None]
    Wg = rbf.fit_basis(Phi, D.reshape(1, T, -1), basis, 0.0, False, Qg)[0]
    A = equal_weights(n, E)
    idx, mask = polynomial.support_index(A)
    Phi_v = np.sqrt(weighted_sq_distances(A, F, F[basis]))
    Wv = rbf.fit_basis(Phi_v, D.transpose(1, 0, 2), basis, 0.0, False, polynomial.design(F, idx, mask))
    psd = (rbf.columns(Phi, Qg)[0] @ Wg).reshape(T, n, 3)
    wpsd = (rbf.columns(Phi_v, polynomial.design(F, idx, mask)) @ Wv).transpose(1, 0, 2)
    np.testing.assert_allclose(wpsd, psd, atol=1e-7)

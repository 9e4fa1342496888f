"""Tests for service.geometry.sparse_solve: prefactored SuperLU solves."""

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from service.geometry.laplacian import cotangent_laplacian, mass_matrix
from service.geometry.sparse_solve import PIVOT_RTOL, Factor, factorize

RIG = np.load(Path(__file__).resolve().parents[2] / "service/samples/data/ict_face_rig.npz")


def test_factorize_two_by_two_by_hand():
    # [[4,1],[1,3]] x = [1,2]  =>  x = [1/11, 7/11]
    f = factorize(sp.csc_matrix([[4.0, 1.0], [1.0, 3.0]]))
    np.testing.assert_allclose(f.solve(np.array([1.0, 2.0])), [1 / 11, 7 / 11], rtol=0, atol=1e-15)
    np.testing.assert_allclose(f(np.array([1.0, 2.0])), [1 / 11, 7 / 11], rtol=0, atol=1e-15)


def _screened_laplacian():
    V = RIG["neutral"].astype(np.float64)
    F = RIG["triangles"].astype(np.int64)
    return (mass_matrix(V, F) - 10.0 * cotangent_laplacian(V, F)).tocsc()  # SPD


def test_factorize_spd_matches_dense_solve_single_and_multiple_rhs():
    A = _screened_laplacian()
    n = A.shape[0]
    rng = np.random.default_rng(0)
    f = factorize(A)
    assert isinstance(f, Factor) and f.n == n and f.spd
    b = rng.standard_normal(n)
    x = f(b)
    assert x.shape == (n,)
    assert np.abs(A @ x - b).max() < 1e-10 * np.abs(b).max()
    Bm = rng.standard_normal((n, 5)).astype(np.float32)   # any float dtype is accepted
    X = f.solve(Bm)
    assert X.shape == (n, 5) and X.dtype == np.float64
    assert np.abs(A @ X - Bm).max() < 1e-10 * np.abs(Bm).max()
    np.testing.assert_allclose(X[:, 2], f(Bm[:, 2].astype(np.float64)), rtol=0, atol=1e-12)


def test_factorize_spd_ordering_fills_less_than_colamd():
    A = _screened_laplacian()
    assert factorize(A).fill < factorize(A, spd=False).fill


def test_factorize_general_matrix_with_pivoting():
    rng = np.random.default_rng(1)
    n = 200
    A = sp.random(n, n, density=0.05, random_state=2, format="csc") + sp.identity(n) * 0.1
    A = A + sp.diags(rng.standard_normal(n - 1), 1)           # unsymmetric, indefinite
    b = rng.standard_normal(n)
    x = factorize(A, spd=False)(b)
    np.testing.assert_allclose(x, np.linalg.solve(A.toarray(), b), rtol=1e-9, atol=1e-9)


def test_factorize_rejects_singular_laplacian():
    V = RIG["neutral"].astype(np.float64)
    F = RIG["triangles"].astype(np.int64)
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        factorize(-cotangent_laplacian(V, F))                 # constants are in the kernel


def test_factorize_rejects_exactly_singular_and_bad_input():
    with pytest.raises(np.linalg.LinAlgError):
        factorize(sp.csc_matrix([[1.0, 0.0], [0.0, 0.0]]))
    with pytest.raises(ValueError, match="square"):
        factorize(sp.csc_matrix(np.ones((2, 3))))
    with pytest.raises(ValueError, match="non-finite"):
        factorize(sp.csc_matrix([[np.nan, 0.0], [0.0, 1.0]]))
    f = factorize(sp.identity(3, format="csc"))
    with pytest.raises(ValueError, match="right-hand side"):
        f(np.ones(4))
    assert f.pivot_ratio == 1.0 > PIVOT_RTOL


def test_cholmod_backend_matches_superlu_and_rejects_singular_and_indefinite():
    from service.geometry.laplacian import cotangent_laplacian
    from tests.methods.shape_space.conftest import grid_mesh

    V, F = grid_mesh()
    L = -cotangent_laplacian(V, F)                                   # PSD, singular
    A = sp.identity(len(V)) + 3.0 * L
    b = np.random.default_rng(1).normal(size=(len(V), 3))
    chol = factorize(A, backend="cholmod")
    assert chol.spd and np.isnan(chol.pivot_ratio) and chol.fill > A.nnz
    np.testing.assert_allclose(chol(b), factorize(A)(b), atol=1e-12)
    np.testing.assert_allclose(chol(b[:, 0]), factorize(A)(b[:, 0]), atol=1e-12)
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        factorize(L, backend="cholmod")
    with pytest.raises(np.linalg.LinAlgError, match="positive definite"):
        factorize(-A, backend="cholmod")
    with pytest.raises(ValueError, match="symmetric positive-definite"):
        factorize(A, spd=False, backend="cholmod")

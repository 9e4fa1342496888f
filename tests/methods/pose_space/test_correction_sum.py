"""Tests for service.methods.pose_space.correction_sum: the compiled per-vertex WPSD sum."""

import numpy as np
import scipy.sparse as sp

from service.methods.pose_space import polynomial
from service.methods.pose_space.correction_sum import CorrectionSum, aligned_support


def test_aligned_support_puts_alpha_and_polynomial_on_one_pattern_in_the_given_order():
    # 3 vertices, 4 edges; vertex 1's polynomial has an entry α lacks (edge 3) and an
    # explicit zero (edge 0), vertex 2 has no polynomial entries
    alpha = sp.csr_matrix(np.array([[0.5, 0.0, 0.5, 0.0],
                                    [0.0, 1.0, 0.0, 0.0],
                                    [0.2, 0.3, 0.0, 0.5]]))
    r = [0, 1, 2, 0, 1, 2, 3, 4, 5, 3]          # rows 3v + c
    c = [0, 0, 0, 2, 2, 2, 3, 3, 3, 0]          # vertex 0: edges 0 and 2; vertex 1: edge 3, and
    d = [1, 2, 3, 4, 5, 6, 7, 8, 9, 0.0]        # an explicit zero at edge 0
    L = sp.csr_matrix((d, (r, c)), shape=(9, 4))
    assert L.nnz == 10
    order = np.array([2, 0, 1])
    ptr, edge, values = aligned_support(alpha, L, order)
    np.testing.assert_array_equal(ptr, [0, 3, 5, 7])
    np.testing.assert_array_equal(edge, [0, 1, 3, 0, 2, 1, 3])
    np.testing.assert_array_equal(values, np.array([
        [0.2, 0, 0, 0], [0.3, 0, 0, 0], [0.5, 0, 0, 0],          # vertex 2
        [0.5, 1, 2, 3], [0.5, 4, 5, 6],                          # vertex 0
        [1.0, 0, 0, 0], [0.0, 7, 8, 9]], np.float32))            # vertex 1


def test_sum_is_eq_5_with_the_polynomial_and_fade_by_hand():
    rng = np.random.default_rng(4)
    n, E, P = 6, 5, 3
    alpha = sp.random(n, E, density=0.6, random_state=5, format="csr") + sp.eye(n, E)
    fb = rng.normal(size=(P, E))
    W = rng.normal(size=(n, P, 3)).astype(np.float32)
    idx, mask = polynomial.support_index(alpha)
    coef = rng.normal(size=(n, 1 + idx.shape[1], 3))
    const, lin = polynomial.to_sparse(coef, idx, mask, E)
    f = rng.normal(size=E)
    cs = CorrectionSum.build(alpha, W, fb, const, lin)
    A = alpha.toarray()
    D2 = np.array([[A[v] @ (f - fb[j]) ** 2 for j in range(P)] for v in range(n)])   # eq. 3
    ref = np.einsum("vjc,vj->vc", W.astype(np.float64), np.sqrt(D2)) + polynomial.evaluate(const, lin, f)[0]
    C, D = cs(f, 0.5, keep_distances=True)
    np.testing.assert_allclose(D, D2, rtol=2e-6)
    np.testing.assert_allclose(C.T, 0.5 * ref, rtol=1e-5, atol=1e-5)
    # more basis poses than one block of lanes (P > 8) take the extra pass
    fb12 = rng.normal(size=(12, E))
    W12 = rng.normal(size=(n, 12, 3)).astype(np.float32)
    C12 = CorrectionSum.build(alpha, W12, fb12)(f)
    D12 = np.array([[A[v] @ (f - fb12[j]) ** 2 for j in range(12)] for v in range(n)])
    np.testing.assert_allclose(C12.T, np.einsum("vjc,vj->vc", W12.astype(np.float64), np.sqrt(D12)),
                               rtol=1e-5, atol=1e-5)

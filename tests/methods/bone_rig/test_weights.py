import numpy as np

from service.methods.bone_rig.weights import project_simplex, simplex_qp


def test_project_simplex_hand_computed():
    # (0.5, 0.5, 0.5): θ = 1/6 → (1/3, 1/3, 1/3); (2, 0, -1): θ = 1 → (1, 0, 0);
    # (0.6, 0.3, 0.1) is on the simplex and stays
    X = np.array([[0.5, 0.5, 0.5], [2.0, 0.0, -1.0], [0.6, 0.3, 0.1], [0.8, 0.6, 0.0]])
    P = project_simplex(X)
    np.testing.assert_allclose(P, [[1 / 3, 1 / 3, 1 / 3], [1, 0, 0], [0.6, 0.3, 0.1], [0.6, 0.4, 0.0]],
                               atol=1e-15)


def test_simplex_qp_interior_and_vertex_optima():
    # Q = I, c: min ½|w|² − c·w on the simplex = projection of c onto the simplex
    rng = np.random.default_rng(3)
    c = rng.normal(size=(50, 5))
    Q = np.broadcast_to(np.eye(5), (50, 5, 5)).copy()
    w = simplex_qp(Q, c, np.full((50, 5), 0.2), iterations=200)
    np.testing.assert_allclose(w, project_simplex(c), atol=1e-10)
    # an ill-conditioned least-squares problem whose exact solution is a known convex weight
    A = rng.normal(size=(50, 30, 4))
    A[:, :, 3] = A[:, :, 2] + 1e-3 * rng.normal(size=(50, 30))            # nearly collinear columns
    w_true = rng.dirichlet(np.ones(4), size=50)
    b = np.einsum("nrc,nc->nr", A, w_true)
    Q = np.einsum("nrc,nrd->ncd", A, A)
    c = np.einsum("nrc,nr->nc", A, b)
    w = simplex_qp(Q, c, np.full((50, 4), 0.25), iterations=50)
    np.testing.assert_allclose(w, w_true, atol=1e-8)                      # the polish makes it exact
    assert np.all(w >= 0) and np.allclose(w.sum(axis=1), 1.0)


def test_active_set_finishes_exactly_from_a_poor_start():
    # one projected-gradient step is far from the optimum; the active-set phase must reach it
    rng = np.random.default_rng(7)
    c = rng.normal(size=(200, 8))
    Q = np.broadcast_to(np.eye(8), (200, 8, 8)).copy()
    w = simplex_qp(Q, c, np.full((200, 8), 1 / 8), iterations=1)
    np.testing.assert_allclose(w, project_simplex(c), atol=1e-12)
    # a general convex QP: the KKT conditions hold (μ ≥ 0 off the support, equal gradients on it)
    A = rng.normal(size=(200, 12, 8))
    Q = np.einsum("nrc,nrd->ncd", A, A)
    c = rng.normal(size=(200, 8)) * 3
    w = simplex_qp(Q, c, np.full((200, 8), 1 / 8), iterations=2)
    g = np.einsum("ncd,nd->nc", Q, w) - c
    on = w > 1e-12
    nu = -np.where(on, g, 0).sum(axis=1) / on.sum(axis=1)
    assert np.abs(np.where(on, g + nu[:, None], 0)).max() < 1e-9
    assert (np.where(on, 0, g + nu[:, None]) > -1e-9).all()

"""Cotangent/uniform Laplacians and mass matrices."""

import numpy as np

from service.geometry.laplacian import cotangent_laplacian, mass_matrix, uniform_laplacian


def test_cotangent_laplacian_single_right_triangle():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    F = np.array([[0, 1, 2]])
    # cot 90° = 0 at corner 0; cot 45° = 1 at corners 1 and 2
    expected = np.array([[-1.0, 0.5, 0.5], [0.5, -0.5, 0.0], [0.5, 0.0, -0.5]])
    np.testing.assert_allclose(cotangent_laplacian(V, F).toarray(), expected, atol=1e-15)


def test_cotangent_laplacian_kills_linear_functions_on_interior_vertices(rig):
    L = cotangent_laplacian(rig.neutral, rig.triangles)
    from service.geometry.topology import boundary_vertices
    interior = ~boundary_vertices(rig.triangles, rig.n_vertices)
    np.testing.assert_allclose(abs(L - L.T).max(), 0, atol=1e-12)
    np.testing.assert_allclose(L @ np.ones(rig.n_vertices), 0, atol=1e-9)
    lin = rig.neutral @ np.array([0.3, -1.2, 0.7])
    # planar-exact only; on a curved surface L x is the mean-curvature normal (∝ area)
    assert np.abs((L @ lin)[interior]).mean() < 0.05 * np.abs(lin).mean()


def test_mass_matrices_sum_to_surface_area(rig):
    from service.geometry.laplacian import triangle_areas
    area = triangle_areas(rig.neutral, rig.triangles).sum()
    for kind in ("barycentric", "voronoi"):
        np.testing.assert_allclose(mass_matrix(rig.neutral, rig.triangles, kind).sum(), area, rtol=1e-12)


def test_uniform_laplacian_rows_are_minus_valence():
    F = np.array([[0, 1, 2], [0, 2, 3]])
    L = uniform_laplacian(F, 4).toarray()
    np.testing.assert_array_equal(np.diag(L), [-3, -2, -3, -2])
    np.testing.assert_array_equal(L.sum(axis=1), 0)

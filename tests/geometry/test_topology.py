"""Edges, boundaries and k-rings."""

import numpy as np

from service.geometry.topology import boundary_vertices, edges, k_ring, k_ring_matrix


def test_edges_of_two_triangles():
    F = np.array([[0, 1, 2], [0, 2, 3]])
    E, corner_edge = edges(F)
    np.testing.assert_array_equal(E, [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]])
    # the edge opposite corner 0 of face 0 is (1,2)
    np.testing.assert_array_equal(E[corner_edge[0, 0]], [1, 2])


def test_ict_rig_boundary_and_euler_characteristic(rig):
    E, _ = edges(rig.triangles)
    chi = rig.n_vertices - len(E) + len(rig.triangles)
    assert chi == 2 - 4                          # a sphere with four holes (neck, mouth, eyes)
    assert boundary_vertices(rig.triangles, rig.n_vertices).sum() == 212   # boundary edges = vertices on loops


def test_k_ring_grows_by_rings():
    F = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 4]])
    np.testing.assert_array_equal(k_ring(F, 5, [1], 0), [1])
    np.testing.assert_array_equal(k_ring(F, 5, [1], 1), [0, 1, 2])
    np.testing.assert_array_equal(k_ring(F, 5, [1], 2), [0, 1, 2, 3, 4])
    R = k_ring_matrix(F, 5, 1).toarray()
    np.testing.assert_array_equal(np.flatnonzero(R[1]), [0, 1, 2])

"""Tests for service.methods.pose_space.weighting (bickel2008 §5.3, eq. 3-4)."""

import numpy as np
import pytest

from service.methods.pose_space.feature_graph import FeatureGraph
from service.methods.pose_space.weighting import edge_weights, equal_weights, weighted_sq_distances


def test_edge_weights_by_hand_with_a_global_beta():
    nodes = np.array([[0.0, 0, 0], [10.0, 0, 0], [0.0, 10, 0]])
    g = FeatureGraph(np.array([[0, 1], [0, 2]]), np.array([10.0, 10.0]))
    v = np.array([[5.0, 0, 0], [5.0, 5, 0]])
    A = edge_weights(v, nodes, g, threshold=1e-6, max_edges=16, beta=0.1).toarray()
    # vertex 0 lies on edge 0: L - l = 0 there; for edge 1, L = 5 + sqrt(125)
    e1 = 5 + np.sqrt(125) - 10
    a = np.array([1.0, np.exp(-0.1 * e1)])
    np.testing.assert_allclose(A[0], a / a.sum(), rtol=1e-12)
    # vertex 1 is symmetric to both edges
    np.testing.assert_allclose(A[1], [0.5, 0.5], rtol=1e-12)


def test_edge_weights_keep_at_most_k_edges_and_sum_to_one():
    rng = np.random.default_rng(1)
    nodes = rng.uniform(0, 100, (40, 3))
    edges = np.array([[i, j] for i in range(40) for j in range(i + 1, 40) if rng.random() < 0.1])
    g = FeatureGraph(edges, np.linalg.norm(nodes[edges[:, 0]] - nodes[edges[:, 1]], axis=1))
    V = rng.uniform(0, 100, (500, 3))
    A = edge_weights(V, nodes, g, threshold=0.025, max_edges=16)
    counts = np.diff(A.indptr)
    assert counts.max() == 16 and counts.min() >= 1
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), 1.0, rtol=1e-12)
    # the kept edges are each vertex's 16 smallest excesses L - l
    L = (np.linalg.norm(V[:, None] - nodes[edges[:, 0]], axis=2)
         + np.linalg.norm(V[:, None] - nodes[edges[:, 1]], axis=2) - g.rest_length)
    best = np.sort(np.argsort(L[7])[:16])
    np.testing.assert_array_equal(np.sort(A[7].indices), best)


def test_weighted_distances_match_eq3():
    rng = np.random.default_rng(2)
    A = equal_weights(5, 4)
    A = A.multiply(rng.uniform(0.5, 1, (5, 4))).tocsr()
    f, basis = rng.normal(size=4), rng.normal(size=(3, 4))
    D2 = weighted_sq_distances(A, f, basis)
    dense = A.toarray()
    expect = np.array([[dense[v] @ (f - basis[j]) ** 2 for j in range(3)] for v in range(5)])
    np.testing.assert_allclose(D2, expect, rtol=1e-12)
    D2b = weighted_sq_distances(A, np.stack([f, f]), basis)
    np.testing.assert_allclose(D2b[:, 1], expect, rtol=1e-12)
    # equal α: the global distance / E
    np.testing.assert_allclose(weighted_sq_distances(equal_weights(2, 4), f, basis)[0],
                               np.sum((f - basis) ** 2, axis=1) / 4, rtol=1e-12)

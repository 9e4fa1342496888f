"""Tests for service.methods.pose_space.feature_graph (bickel2008 §5.1)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.methods.inputs import InvalidInput
from service.methods.pose_space.feature_graph import FeatureGraph, automatic_graph, graph_from_pairs


def test_feature_of_one_edge_is_its_relative_stretch():
    g = FeatureGraph(np.array([[0, 1]]), np.array([10.0]))
    # endpoints 12 mm apart: (12 - 10) / 10 = 0.2; 7.5 mm: -0.25
    assert g.features(np.array([[0.0, 0, 0], [12.0, 0, 0]]))[0] == pytest.approx(0.2, abs=1e-15)
    assert g.features(np.array([[1.0, 1, 1], [1.0, 8.5, 1]]))[0] == pytest.approx(-0.25, abs=1e-15)


def test_features_are_invariant_under_rigid_motion():
    rng = np.random.default_rng(4)
    rest = rng.normal(size=(30, 3)) * 20
    uv = rest[:, :2] / 100 + 0.5
    g = automatic_graph(uv, rest, max_edge_ratio=10.0, min_angle_deg=0.0)
    pose = rest + rng.normal(size=rest.shape)                     # a deformed pose
    R = Rotation.from_euler("xyz", [35, -80, 120], degrees=True).as_matrix()
    moved = pose @ R.T + np.array([100.0, -40.0, 7.0])
    f = g.features(pose)
    assert np.abs(f).max() > 0.01
    np.testing.assert_allclose(g.features(moved), f, atol=1e-12)
    np.testing.assert_allclose(g.features(rest), 0.0, atol=1e-15)


def test_automatic_graph_prunes_long_and_sliver_edges():
    # a 5x5 grid of markers (2 mm spacing) plus one far outlier: Delaunay joins the
    # outlier with long edges, which the length test drops; without pruning they stay
    x, y = np.meshgrid(np.arange(5.0), np.arange(5.0))
    uv = np.concatenate([np.stack([x.ravel(), y.ravel()], 1) * 0.02, [[0.5, 0.9]]])
    rest = np.concatenate([uv * 100, np.zeros((26, 1))], axis=1)
    g = automatic_graph(uv, rest, max_edge_ratio=2.5, min_angle_deg=12.0)
    assert not np.any(g.edges == 25)
    assert g.rest_length.max() <= 2.5 * np.median(g.rest_length)
    # every grid edge (40 of them) and one diagonal per cell (16) survive
    assert g.n_edges == 56
    loose = automatic_graph(uv, rest, max_edge_ratio=100.0, min_angle_deg=0.0)
    assert np.any(loose.edges == 25)


def test_graph_from_pairs_checks_names():
    rest = np.eye(3) * 10
    g = graph_from_pairs([("a", "b"), ("c", "a")], ("a", "b", "c"), rest)
    np.testing.assert_array_equal(g.edges, [[0, 1], [0, 2]])
    np.testing.assert_allclose(g.rest_length, np.sqrt(200.0))
    with pytest.raises(InvalidInput, match="no marker named 'd'"):
        graph_from_pairs([("a", "d")], ("a", "b", "c"), rest)
    with pytest.raises(InvalidInput, match="twice"):
        graph_from_pairs([("a", "b"), ("b", "a")], ("a", "b", "c"), rest)

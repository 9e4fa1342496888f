"""Tests for service.methods.shape_space.patches: seed-and-grow patches and the compression of §4.2."""

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components

from service.geometry.laplacian import triangle_areas
from service.geometry.topology import adjacency_matrix
from service.methods.shape_space.patches import (
    PatchAverager, patch_average, seed_and_grow_patches, triangle_patches,
)

from .conftest import grid_mesh


@pytest.fixture(scope="module")
def big_sheet():
    return grid_mesh(nx=60, ny=50, size=120.0, seed=3)


def test_every_vertex_in_exactly_one_connected_patch(big_sheet):
    V, F = big_sheet
    labels = seed_and_grow_patches(V, F, size=100, seed=1)
    assert labels.shape == (len(V),) and labels.min() == 0
    P = labels.max() + 1
    assert np.array_equal(np.unique(labels), np.arange(P))          # no empty patch
    A = adjacency_matrix(F, len(V))
    for p in range(P):
        idx = np.flatnonzero(labels == p)
        assert connected_components(A[idx][:, idx], directed=False)[0] == 1


def test_patch_sizes_are_near_the_target(big_sheet):
    V, F = big_sheet
    labels = seed_and_grow_patches(V, F, size=100, seed=1)
    sizes = np.bincount(labels)
    assert len(sizes) == 30                                          # round(3000 / 100)
    assert sizes.mean() == pytest.approx(100.0)
    assert 50 <= sizes.min() and sizes.max() <= 160       # measured 67 … 129 (plain seeds: 28 … 226)
    plain = np.bincount(seed_and_grow_patches(V, F, size=100, seed=1, relax_iterations=0))
    assert np.std(sizes) < 0.5 * np.std(plain)                       # Lloyd steps even them out


def test_patches_are_reproducible_per_seed(big_sheet):
    V, F = big_sheet
    a = seed_and_grow_patches(V, F, size=80, seed=7)
    b = seed_and_grow_patches(V, F, size=80, seed=7)
    c = seed_and_grow_patches(V, F, size=80, seed=8)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_each_component_gets_its_own_patches():
    V1, F1 = grid_mesh(nx=10, ny=10)
    V = np.concatenate([V1, V1 + [100.0, 0, 0], [[0.0, 0.0, 50.0]]])   # two sheets + a lone vertex
    F = np.concatenate([F1, F1 + 100])
    labels = seed_and_grow_patches(V, F, size=50, seed=0)
    assert len(np.unique(labels)) == 5                               # 2 + 2 + 1
    assert not set(labels[:100]) & set(labels[100:200])
    assert np.sum(labels == labels[-1]) == 1


def test_triangle_patch_is_the_majority_of_its_corners():
    labels = np.array([0, 0, 1, 1, 2])
    F = np.array([[0, 1, 2], [2, 3, 0], [2, 3, 4], [0, 2, 4], [4, 2, 3]])
    assert triangle_patches(F, labels).tolist() == [0, 1, 1, 0, 1]


def test_patch_average_is_the_area_weighted_mean(sheet):
    V, F = sheet
    labels = seed_and_grow_patches(V, F, size=20, seed=0)
    tri = triangle_patches(F, labels)
    A = triangle_areas(V, F)
    X = np.random.default_rng(0).normal(size=(2, len(F), 9))
    P = labels.max() + 1
    got = patch_average(X, tri, A, P)
    for p in range(P):
        sel = tri == p
        np.testing.assert_allclose(got[1, p], (A[sel, None] * X[1, sel]).sum(0) / A[sel].sum(), rtol=1e-12)
    assert PatchAverager(tri, A, P)(X[0]).shape == (P, 9)

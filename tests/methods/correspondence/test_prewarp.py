"""Tests for service.methods.correspondence.prewarp: the Delaunay piecewise-affine pre-warp."""

import numpy as np
import pytest

from service.methods.correspondence.prewarp import affine_fit, piecewise_affine_coords
from service.methods.inputs import InvalidInput

A = np.array([[1.05, 0.08, 3.5], [-0.06, 0.97, -2.25]])     # source = A @ [x, y, 1]


def grid(H, W):
    xs, ys = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    return np.stack([xs, ys], axis=-1)


def test_an_exact_affine_warp_is_recovered_everywhere():
    rng = np.random.default_rng(0)
    tgt = rng.uniform(5, 75, (12, 2))
    src = tgt @ A[:, :2].T + A[:, 2]
    coords = piecewise_affine_coords(src, tgt, (60, 80))
    expect = grid(60, 80) @ A[:, :2].T + A[:, 2]
    np.testing.assert_allclose(coords, expect, atol=1e-9)      # inside the hull and outside
    np.testing.assert_allclose(affine_fit(src, tgt), A, atol=1e-12)


def test_landmarks_are_interpolated_exactly_and_triangles_are_affine():
    rng = np.random.default_rng(1)
    tgt = np.array([[10, 10], [50, 12], [30, 45], [12, 40], [55, 50]], float)
    src = tgt + rng.normal(0, 3, tgt.shape)
    coords = piecewise_affine_coords(src, tgt, (64, 64), extend=False)
    np.testing.assert_allclose(coords[tgt[:, 1].astype(int), tgt[:, 0].astype(int)], src, atol=1e-9)
    assert np.isnan(coords[0, 0]).all() and np.isfinite(coords[30, 30]).all()
    # second differences vanish inside a triangle (affine there)
    inner = coords[20:23, 30:33, 0]
    assert abs(inner[1, 0] - 2 * inner[1, 1] + inner[1, 2]) < 1e-9


def test_bad_landmarks_are_rejected():
    with pytest.raises(InvalidInput, match="at least 3"):
        piecewise_affine_coords(np.zeros((2, 2)), np.ones((2, 2)), (8, 8))
    line = np.column_stack([np.arange(4.0), np.arange(4.0)])
    with pytest.raises(InvalidInput, match="degenerate"):
        piecewise_affine_coords(line, line, (8, 8), extend=False)
    with pytest.raises(InvalidInput, match="repeat"):
        piecewise_affine_coords(np.zeros((3, 2)), np.array([[1, 1], [1, 1], [2, 5.0]]), (8, 8))
    with pytest.raises(InvalidInput, match="finite"):
        piecewise_affine_coords(np.full((3, 2), np.nan), np.eye(3)[:, :2], (8, 8))

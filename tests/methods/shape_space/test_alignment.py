"""Tests for service.methods.shape_space.alignment: head motion removed before encoding."""

import numpy as np
from scipy.spatial.transform import Rotation

from service.methods.shape_space.alignment import align_frames, stability_weights

from .conftest import grid_mesh


def test_stability_weights_favour_still_vertices_and_recover_the_head_pose():
    V, F = grid_mesh(nx=20, ny=20, size=100.0)
    rng = np.random.default_rng(0)
    moving = V[:, 1] < 30                                          # a 'jaw' that opens
    frames, truth = [], []
    for k in range(12):
        X = V.copy()
        X[moving, 2] += rng.uniform(2, 10) * (30 - V[moving, 1]) / 30
        R = Rotation.from_rotvec(rng.normal(scale=0.05, size=3)).as_matrix()
        t = rng.normal(scale=5, size=3)
        frames.append(X @ R.T + t)
        truth.append(X)
    frames, truth = np.array(frames), np.array(truth)
    w = stability_weights(frames, V)
    assert abs(w.mean() - 1) < 1e-12
    assert np.median(w[~moving]) > 5 * np.median(w[V[:, 1] < 10])   # the jaw's far end
    still = ~moving
    err_w = np.abs(align_frames(frames, V, w)[0] - truth)[:, still].max()
    err_u = np.abs(align_frames(frames, V)[0] - truth)[:, still].max()
    assert err_w < 0.05 * err_u and err_w < 0.05


def test_transforms_restore_the_pose():
    V, _ = grid_mesh()
    X = V @ Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix().T + [3.0, -1.0, 2.0]
    aligned, T = align_frames(X[None], V)
    np.testing.assert_allclose(aligned[0], V, atol=1e-10)
    np.testing.assert_allclose(T[0].inverse().apply(aligned[0]), X, atol=1e-10)
    frames = np.stack([X, X[::-1][::-1] + 1.0])
    expected, _ = align_frames(frames, V)
    same, _ = align_frames(frames, V, inplace=True)
    assert same is frames
    np.testing.assert_allclose(same, expected, rtol=0, atol=1e-12)


def test_stability_weights_equal_the_explicit_aligned_offsets():
    """The weights' motion term, contracted over the frames without aligned copies, equals
    the RMS offset of explicitly aligned frames (the definition)."""
    rng = np.random.default_rng(5)
    V, _ = grid_mesh(8, 7)
    V = V + [0.0, 0.0, 700.0]
    frames = np.repeat(V[None], 9, axis=0)
    frames[:, :20, 2] += rng.normal(scale=2.0, size=(9, 1))              # a moving "jaw"
    frames = np.einsum("fde,fne->fnd", Rotation.random(9, random_state=6).as_matrix(), frames)
    frames += rng.normal(scale=0.05, size=frames.shape)
    w = stability_weights(frames, V, refinements=0)                       # one unweighted fit
    aligned, _ = align_frames(frames, V)
    m = np.sqrt(((aligned - V) ** 2).sum(axis=2).mean(axis=0))
    expected = 1.0 / (m ** 2 + np.median(m) ** 2)
    # the expansion cancels |p|² (~5e5 mm² here) against m² (~1e-3 mm²): ~1e-8 relative
    np.testing.assert_allclose(w, expected / expected.mean(), rtol=1e-6)

"""Tests for service.geometry.rigid: weighted Kabsch / Umeyama alignment."""

import numpy as np
import pytest

from service.geometry.rigid import RigidTransform, rigid_align


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@pytest.fixture
def pose():
    rng = np.random.default_rng(7)
    P = rng.standard_normal((150, 3)) * [60.0, 80.0, 40.0]     # markers, mm
    R = random_rotation(rng)
    t = np.array([12.0, -300.0, 45.5])
    return P, R, t


def test_rigid_align_recovers_known_rotation_and_translation(pose):
    P, R, t = pose
    T = rigid_align(P, P @ R.T + t)
    np.testing.assert_allclose(T.R, R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T.t, t, rtol=0, atol=1e-10)
    assert T.s == 1.0
    assert abs(np.linalg.det(T.R) - 1.0) < 1e-12


def test_rigid_align_recovers_scale_umeyama(pose):
    P, R, t = pose
    T = rigid_align(P, 1.07 * P @ R.T + t, scale=True)
    assert abs(T.s - 1.07) < 1e-12
    np.testing.assert_allclose(T.R, R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T.t, t, rtol=0, atol=1e-10)


def test_rigid_align_ignores_nan_rows_occluded_markers(pose):
    P, R, t = pose
    Q = P @ R.T + t
    P, Q = P.copy(), Q.copy()
    P[[3, 50]] = np.nan
    Q[[7, 8, 120]] = [np.nan, 0.0, 0.0]
    T = rigid_align(P, Q, scale=True)
    np.testing.assert_allclose(T.R, R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T.t, t, rtol=0, atol=1e-10)
    assert abs(T.s - 1.0) < 1e-12


def test_rigid_align_weights_zero_out_outliers_and_act_as_multiplicity(pose):
    P, R, t = pose
    Q = P @ R.T + t
    Q[:10] += 25.0                                             # ten bad markers
    w = np.ones(len(P))
    w[:10] = 0.0
    T = rigid_align(P, Q, weights=w)
    np.testing.assert_allclose(T.R, R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T.t, t, rtol=0, atol=1e-10)
    # with noise, weight 2 equals listing the point twice
    rng = np.random.default_rng(3)
    Qn = P @ R.T + t + rng.standard_normal(P.shape)
    w = rng.integers(1, 4, len(P)).astype(float)
    Tw = rigid_align(P, Qn, weights=w, scale=True)
    Tr = rigid_align(np.repeat(P, w.astype(int), axis=0), np.repeat(Qn, w.astype(int), axis=0),
                     scale=True)
    np.testing.assert_allclose(Tw.R, Tr.R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(Tw.t, Tr.t, rtol=0, atol=1e-9)
    assert abs(Tw.s - Tr.s) < 1e-12


def test_rigid_align_never_returns_a_reflection(pose):
    P, _, _ = pose
    Q = P * [-1.0, 1.0, 1.0]                                   # a mirror image
    T = rigid_align(P, Q)
    assert abs(np.linalg.det(T.R) - 1.0) < 1e-12
    # the best proper rotation is worse than the mirror but better than the identity
    res = np.linalg.norm(T.apply(P) - Q)
    assert 0 < res < np.linalg.norm(P - Q)


def test_transform_apply_inverse_matrix_and_batched_frames(pose):
    P, R, t = pose
    T = RigidTransform(R=R, t=t, s=1.3)
    X = np.random.default_rng(4).standard_normal((5, 40, 3))   # (frames, n, 3)
    Y = T.apply(X)
    assert Y.shape == (5, 40, 3)
    np.testing.assert_allclose(Y[2], 1.3 * X[2] @ R.T + t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T.inverse().apply(Y), X, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T.inverse().inverse().t, t, rtol=0, atol=1e-12)
    M = T.matrix()
    np.testing.assert_allclose((np.c_[X[0], np.ones(40)] @ M.T)[:, :3], Y[0], atol=1e-12)
    np.testing.assert_allclose(T(X[0]), Y[0], rtol=0, atol=0)


def test_rigid_align_rejects_bad_input(pose):
    P, R, t = pose
    Q = P @ R.T + t
    with pytest.raises(ValueError, match="at least 3"):
        rigid_align(P[:2], Q[:2])
    Pn = P.copy()
    Pn[2:] = np.nan
    with pytest.raises(ValueError, match=r"got 2 of 150"):
        rigid_align(Pn, Q)
    with pytest.raises(ValueError, match="non-negative"):
        rigid_align(P, Q, weights=-np.ones(len(P)))
    with pytest.raises(ValueError, match=r"\(n,3\)"):
        rigid_align(P, Q[:-1])
    with pytest.raises(ValueError, match="coincide"):
        rigid_align(np.zeros((4, 3)), Q[:4], scale=True)


def test_rigid_align_frames_is_rigid_align_per_frame():
    from scipy.spatial.transform import Rotation

    from service.geometry.rigid import rigid_align_frames

    rng = np.random.default_rng(3)
    Q = rng.normal(scale=50.0, size=(300, 3)) + [0.0, 0.0, 900.0]        # far from the origin
    R0 = Rotation.random(6, random_state=4).as_matrix()
    P = np.einsum("fde,ne->fnd", R0, Q) + rng.normal(scale=10.0, size=(6, 1, 3))
    P += rng.normal(scale=0.3, size=P.shape)
    P[5] = Q @ np.diag([1.0, 1.0, -1.0])                                    # a mirror image
    w = rng.uniform(0.0, 2.0, size=300)
    R, t = rigid_align_frames(P, Q, w)
    for f in range(6):
        T = rigid_align(P[f], Q, w)
        np.testing.assert_allclose(R[f], T.R, rtol=0, atol=1e-12)
        np.testing.assert_allclose(t[f], T.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, rtol=0, atol=1e-12)
    with pytest.raises(ValueError):
        rigid_align_frames(P, Q, np.zeros(300))

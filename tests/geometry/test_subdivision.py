"""Loop/midpoint subdivision as sparse operators carrying UVs."""

import numpy as np

from service.geometry.subdivision import subdivide


def test_midpoint_subdivision_keeps_original_vertices_first(rig):
    sub = subdivide(rig.triangles, rig.n_vertices, rig.triangle_uv, len(rig.uv), scheme="midpoint")
    V1 = sub.S @ rig.neutral
    np.testing.assert_array_equal(V1[: rig.n_vertices], rig.neutral)
    np.testing.assert_array_equal((sub.S_uv @ rig.uv)[: len(rig.uv)], rig.uv)
    assert len(sub.faces) == 4 * len(rig.triangles) == len(sub.uv_faces)


def test_loop_subdivision_sizes_and_partition_of_unity(rig):
    sub = subdivide(rig.triangles, rig.n_vertices, rig.triangle_uv, len(rig.uv), iterations=1)
    assert sub.S.shape == (44786, 11248)
    np.testing.assert_allclose(np.asarray(sub.S.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert (sub.S.data > 0).all() or sub.S.data.min() > -1e-12


def test_uv_corners_follow_position_corners(rig):
    """Each fine triangle's UVs are the midpoint-interpolated UVs of its coarse corners."""
    sub = subdivide(rig.triangles, rig.n_vertices, rig.triangle_uv, len(rig.uv), scheme="midpoint")
    V1, UV1 = sub.S @ rig.neutral, sub.S_uv @ rig.uv
    t = 123                                     # the corner triangle (a, m_ab, m_ca) of face 123
    a, b, c = rig.triangles[t]
    ua, ub, uc = rig.uv[rig.triangle_uv[t]]
    np.testing.assert_allclose(V1[sub.faces[t]], [rig.neutral[a], (rig.neutral[a] + rig.neutral[b]) / 2,
                                                  (rig.neutral[a] + rig.neutral[c]) / 2])
    np.testing.assert_allclose(UV1[sub.uv_faces[t]], [ua, (ua + ub) / 2, (ua + uc) / 2])


def test_loop_subdivision_of_a_flat_patch_stays_flat():
    xs, ys = np.meshgrid(np.arange(5.0), np.arange(5.0))
    V = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(25)])
    idx = np.arange(25).reshape(5, 5)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    sub = subdivide(F, 25, iterations=2)
    np.testing.assert_allclose((sub.S @ V)[:, 2], 0.0, atol=1e-15)

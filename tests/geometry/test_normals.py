"""Tests for service.geometry.normals: unit face and angle-weighted vertex normals."""

from pathlib import Path

import numpy as np
import pytest

from service.geometry.normals import corner_angles, face_normals, vertex_normals
from service.geometry.subdivision import subdivide

RIG = np.load(Path(__file__).resolve().parents[2] / "service/samples/data/ict_face_rig.npz")


def icosphere(levels: int, radius: float = 50.0):
    """Icosahedron subdivided ``levels`` times (midpoint) and projected onto a sphere."""
    p = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
                  [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]], float)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    sub = subdivide(F, len(V), iterations=levels, scheme="midpoint")
    V = sub.S @ V
    return radius * V / np.linalg.norm(V, axis=1, keepdims=True), sub.faces


def test_face_normal_of_a_ccw_triangle_by_hand():
    V = np.array([[0.0, 0, 0], [2, 0, 0], [0, 3, 0], [0, 0, 1]])
    F = np.array([[0, 1, 2], [0, 3, 1], [0, 1, 1]])            # last one degenerate
    N = face_normals(V, F)
    np.testing.assert_allclose(N, [[0, 0, 1], [0, 1, 0], [0, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(corner_angles(V, F[:1]), [[np.pi / 2, np.arctan(1.5), np.arctan(2 / 3)]],
                               atol=1e-15)


def test_vertex_normals_on_a_sphere_match_the_radial_direction():
    def max_angle_deg(V, N):
        radial = V / np.linalg.norm(V, axis=1, keepdims=True)
        return np.degrees(np.arccos(np.clip((N * radial).sum(1), -1, 1))).max()

    V, F = icosphere(3)                                        # 642 vertices, 7.5 mm edges
    N = vertex_normals(V, F)
    np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, rtol=0, atol=1e-14)
    assert max_angle_deg(V, N) < 0.3                           # measured 0.26°
    assert max_angle_deg(V, vertex_normals(V, F, weighting="area")) < 0.55  # 0.50°
    V4, F4 = icosphere(4)                                      # halved edges: error / 4
    assert max_angle_deg(V, N) / max_angle_deg(V4, vertex_normals(V4, F4)) > 3.5
    assert (face_normals(V, F) * V[F].mean(axis=1)).sum(1).min() > 0   # outward


def test_angle_weighting_is_independent_of_the_triangulation():
    # Unit cube with its six quads split along alternating diagonals: the angle-weighted
    # corner normal is exactly (±1,±1,±1)/√3; area weighting depends on the splits.
    V = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6],
                      [0, 2, 6, 4], [1, 5, 7, 3]])
    F = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    F = F[:, ::-1] if (face_normals(V, F)[0] @ (V[F[0]].mean(0) - 0.5)) < 0 else F
    expected = (V - 0.5) / np.linalg.norm(V - 0.5, axis=1, keepdims=True)
    np.testing.assert_allclose(vertex_normals(V, F), expected, rtol=0, atol=1e-15)
    assert np.abs(vertex_normals(V, F, weighting="area") - expected).max() > 0.05


def test_vertex_normals_unit_on_the_face_rig_and_batched_equals_per_frame():
    V = RIG["neutral"].astype(np.float64)
    F = RIG["triangles"].astype(np.int64)
    N = vertex_normals(V, F)
    assert N.shape == V.shape and N.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, rtol=0, atol=1e-14)
    frames = V + RIG["expression_deltas"][:3].astype(np.float64)    # (3,n,3)
    Nb = vertex_normals(frames, F)
    assert Nb.shape == (3, len(V), 3)
    np.testing.assert_allclose(Nb[1], vertex_normals(frames[1], F), rtol=0, atol=1e-14)
    Fn = face_normals(frames, F)
    np.testing.assert_allclose(Fn[2], face_normals(frames[2], F), rtol=0, atol=0)
    # the face looks along +z (README: +z out of the face); the nose tip certainly does
    assert N[RIG["landmarks68"][30], 2] > 0.9


def test_unreferenced_vertex_gets_zero_normal_and_bad_input_is_rejected():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]])
    N = vertex_normals(V, np.array([[0, 1, 2]]))
    np.testing.assert_array_equal(N[3], 0.0)
    np.testing.assert_allclose(N[:3], [[0, 0, 1]] * 3, atol=1e-15)
    with pytest.raises(ValueError, match="weighting"):
        vertex_normals(V, np.array([[0, 1, 2]]), weighting="uniform")
    with pytest.raises(ValueError, match=r"\(n,3\)"):
        vertex_normals(V[:, :2], np.array([[0, 1, 2]]))


def test_compiled_angle_normals_are_the_numpy_passes_bit_for_bit():
    """issue 23: vertex_normals' compiled angle-weighted path equals the NumPy passes it
    replaced (corner contributions summed in corner order by bincount, normalized) bit for
    bit, on the ICT-like random mesh below, a batch of frames, a degenerate triangle and an
    unreferenced vertex."""
    from service.geometry.normals import _angle_weighted_normals, _normalize

    rng = np.random.default_rng(11)
    n = 400
    V = rng.normal(size=(3, n, 3)) * [30.0, 40.0, 20.0] + [0.0, 0.0, 100.0]
    F = np.array([rng.choice(n - 1, 3, replace=False) for _ in range(900)], np.int64)
    F[5] = [7, 7, 9]                                   # degenerate: zero area, zero normal
    V[1, 3] = V[1, 4]                                  # a zero-length edge in one frame
    got = vertex_normals(V, F)
    want = np.empty_like(got)
    for f in range(len(V)):
        contrib = _angle_weighted_normals(V[f:f + 1], F).reshape(3 * len(F), 3)
        acc = np.stack([np.bincount(F.ravel(), contrib[:, d], minlength=n) for d in range(3)], axis=1)
        want[f] = _normalize(acc)
    np.testing.assert_array_equal(got, want)
    assert not got[:, n - 1].any()                     # unreferenced vertex: zero normal
    np.testing.assert_array_equal(vertex_normals(V[2], F), got[2])


def test_a_numpy_whose_einsum_sums_otherwise_keeps_the_numpy_passes(monkeypatch):
    import service.geometry.normals as normals

    rng = np.random.default_rng(4)
    V = rng.normal(size=(60, 3)) * 20.0
    F = np.array([rng.choice(60, 3, replace=False) for _ in range(100)], np.int64)
    compiled = normals.vertex_normals(V, F)
    monkeypatch.setattr(normals, "_EINSUM_ORDER", [False])
    monkeypatch.setattr(normals, "_compiled_angle_normals", None)       # not called
    np.testing.assert_array_equal(normals.vertex_normals(V, F), compiled)

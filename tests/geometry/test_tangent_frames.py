"""Tests for service.geometry.tangent_frames: UV-aligned orthonormal per-vertex frames."""

from pathlib import Path

import numpy as np
import pytest

from service.geometry.tangent_frames import tangent_frames, uv_handedness

RIG = np.load(Path(__file__).resolve().parents[2] / "service/samples/data/ict_face_rig.npz")


def grid(k: int = 25, size: float = 96.0):
    """Planar k×k grid in z = 0 (mm), CCW triangles (normal +z), both diagonal directions."""
    x, y = np.meshgrid(np.linspace(0, size, k), np.linspace(0, size, k))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(k * k)]
    i, j = np.meshgrid(np.arange(k - 1), np.arange(k - 1))
    a = (j * k + i).ravel()
    b, c, d = a + 1, a + k + 1, a + k
    flip = ((i + 2 * j) % 3 == 0).ravel()
    F = np.concatenate([np.where(flip[:, None], np.c_[a, b, d], np.c_[a, b, c]),
                        np.where(flip[:, None], np.c_[b, c, d], np.c_[a, c, d])])
    return V, F


def assert_orthonormal_right_handed(frames, tol=1e-10):
    I = np.einsum("...ij,...kj->...ik", frames, frames)
    assert np.abs(I - np.eye(3)).max() < tol
    assert np.abs(np.linalg.det(frames) - 1.0).max() < tol


def test_planar_grid_with_uv_equal_to_xy_gives_the_identity_frame():
    V, F = grid()
    frames = tangent_frames(V, F, V[:, :2] / 96.0, F)
    assert frames.shape == (len(V), 3, 3)
    np.testing.assert_allclose(frames, np.broadcast_to(np.eye(3), frames.shape), rtol=0, atol=1e-12)


def test_tangent_follows_increasing_u_of_a_rotated_and_sheared_uv_map():
    V, F = grid()
    th = np.deg2rad(30.0)
    uv = V[:, :2] @ np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]).T
    fr = tangent_frames(V, F, uv, F)
    np.testing.assert_allclose(fr[:, 0], np.tile([np.cos(th), -np.sin(th), 0], (len(V), 1)), atol=1e-12)
    # uv = J p with J = [[2, 0], [0.3, 0.5]]: dP/du = first column of J⁻¹ = (0.5, −0.3)
    uv = V[:, :2] @ np.array([[2.0, 0.0], [0.3, 0.5]]).T
    fr = tangent_frames(V, F, uv, F)
    t = np.array([0.5, -0.3, 0.0]) / np.hypot(0.5, 0.3)
    np.testing.assert_allclose(fr[:, 0], np.tile(t, (len(V), 1)), atol=1e-12)
    np.testing.assert_allclose(fr[:, 1], np.tile(np.cross([0, 0, 1], t), (len(V), 1)), atol=1e-12)
    assert_orthonormal_right_handed(fr)


def test_mirrored_chart_keeps_a_right_handed_frame_and_reports_handedness():
    V, F = grid()
    uv = np.c_[-V[:, 0], V[:, 1]] / 96.0                        # mirrored in u
    fr = tangent_frames(V, F, uv, F)
    np.testing.assert_allclose(fr[:, 0], np.tile([-1.0, 0, 0], (len(V), 1)), atol=1e-12)  # +u
    np.testing.assert_allclose(fr[:, 2], np.tile([0, 0, 1.0], (len(V), 1)), atol=1e-12)   # N
    np.testing.assert_allclose(fr[:, 1], np.tile([0, -1.0, 0], (len(V), 1)), atol=1e-12)  # N×T
    assert_orthonormal_right_handed(fr)
    sign = uv_handedness(F, uv, F, len(V))
    np.testing.assert_array_equal(sign, -1.0)
    np.testing.assert_allclose(sign[:, None] * fr[:, 1], np.tile([0, 1.0, 0], (len(V), 1)),
                               atol=1e-12)                     # handedness·B = +v


def test_mirror_seam_does_not_cancel_the_tangent():
    # u = |x − 48| / 96: the left half is a mirrored copy sharing the seam column x = 48
    V, F = grid()
    uv = np.c_[np.abs(V[:, 0] - 48.0), V[:, 1]] / 96.0
    fr = tangent_frames(V, F, uv, F)
    assert_orthonormal_right_handed(fr)
    sign = uv_handedness(F, uv, F, len(V))
    left, right = V[:, 0] < 47, V[:, 0] > 49
    np.testing.assert_array_equal(sign[left], -1.0)
    np.testing.assert_array_equal(sign[right], 1.0)
    # everywhere, seam included (which chart wins there is a majority vote), T is +u of
    # the chart of the vertex's handedness: (−1,0,0) for the mirrored, (1,0,0) otherwise
    np.testing.assert_allclose(fr[:, 0], sign[:, None] * [1.0, 0, 0], rtol=0, atol=1e-12)


def test_uv_seam_between_two_charts_averages_their_tangents():
    # right half is its own UV island, rotated by 90° (u runs along −y there): seam
    # vertices see both charts with equal angle sums (π each side) → the bisector
    V, F = grid()
    right_face = V[F].mean(axis=1)[:, 0] > 48.0
    uv_left = V[:, :2] / 96.0
    uv_right = np.c_[-V[:, 1], V[:, 0]] / 96.0 + [2.0, 0.0]    # u = −y, v = x (det +1)
    uv = np.r_[uv_left, uv_right]
    uv_faces = np.where(right_face[:, None], F + len(V), F)
    fr = tangent_frames(V, F, uv, uv_faces)
    assert_orthonormal_right_handed(fr)
    interior_seam = (np.abs(V[:, 0] - 48.0) < 1e-9) & (V[:, 1] > 1) & (V[:, 1] < 95)
    expected = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    np.testing.assert_allclose(fr[interior_seam, 0], np.tile(expected, (interior_seam.sum(), 1)),
                               atol=1e-12)
    right = V[:, 0] > 49
    np.testing.assert_allclose(fr[right, 0], np.tile([0, -1.0, 0], (right.sum(), 1)), atol=1e-12)


def test_degenerate_uv_triangles_are_skipped():
    V, F = grid()
    uv = V[:, :2] / 96.0
    uv_faces = F.copy()
    uv = np.r_[uv, [[0.5, 0.5]]]
    uv_faces[[10, 200, 201]] = len(uv) - 1                      # collapsed to one UV point
    uv_faces[300] = [F[300, 0], F[300, 0], F[300, 1]]           # zero-length UV edge
    fr = tangent_frames(V, F, uv, uv_faces)
    np.testing.assert_allclose(fr, np.broadcast_to(np.eye(3), fr.shape), rtol=0, atol=1e-12)
    # a lone triangle with no usable UV still gets a finite orthonormal frame about N
    V1 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    fr1 = tangent_frames(V1, np.array([[0, 1, 2]]), np.zeros((1, 2)), np.array([[0, 0, 0]]))
    assert_orthonormal_right_handed(fr1)
    np.testing.assert_allclose(fr1[:, 2], np.tile([0, 0, 1.0], (3, 1)), atol=1e-15)


def test_face_rig_frames_are_orthonormal_and_follow_u():
    V = RIG["neutral"].astype(np.float64)
    F = RIG["triangles"].astype(np.int64)
    uv, uv_faces = RIG["uv"].astype(np.float64), RIG["triangle_uv"].astype(np.int64)
    fr = tangent_frames(V, F, uv, uv_faces)
    assert fr.shape == (len(V), 3, 3)
    assert_orthonormal_right_handed(fr)
    np.testing.assert_array_equal(uv_handedness(F, uv, uv_faces, len(V)), 1.0)  # no mirroring
    # per triangle dP/du (a direction of +u) against the T of each of its corners
    U = uv[uv_faces]
    d1, d2 = U[:, 1] - U[:, 0], U[:, 2] - U[:, 0]
    e1, e2 = V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    dpdu /= np.linalg.norm(dpdu, axis=1, keepdims=True)
    cos = np.einsum("fkd,fd->fk", fr[F, 0], dpdu)
    # per-vertex T averages its triangles; only tiny, strongly sheared UV triangles
    # (eyelids, lips; < 1 mm²) and UV seams between charts deviate much from it
    assert np.median(cos) > 0.995                              # measured 0.9986
    assert np.percentile(cos, 5) > 0.93                        # 0.954
    assert (cos < 0).mean() < 1e-3                             # 23 of 66864 corners
    # batched over frames equals per frame
    frames = V + RIG["expression_deltas"][[5, 20]].astype(np.float64)
    fb = tangent_frames(frames, F, uv, uv_faces)
    assert fb.shape == (2, len(V), 3, 3)
    np.testing.assert_allclose(fb[1], tangent_frames(frames[1], F, uv, uv_faces), rtol=0, atol=1e-13)


def test_tangent_frames_rejects_mismatched_uv_faces():
    V, F = grid(4)
    with pytest.raises(ValueError, match=r"\(m,3\)"):
        tangent_frames(V, F, V[:, :2], F[:-1])
    with pytest.raises(ValueError, match="out of range"):
        tangent_frames(V, F, V[:3, :2], F)


def _face_rig_field():
    """The face rig's FrameField and two expression poses far from the origin (float32 must
    not lose the edges to the offset)."""
    from service.geometry.tangent_frames import FrameField

    V = RIG["neutral"].astype(np.float64)
    F = RIG["triangles"].astype(np.int64)
    uv, uv_faces = RIG["uv"].astype(np.float64), RIG["triangle_uv"].astype(np.int64)
    ff = FrameField.build(V, F, uv, uv_faces)
    return ff, V + RIG["expression_deltas"][[5, 20]].astype(np.float64) + [300.0, -200.0, 150.0]


def test_frame_field_float32_agrees_with_float64_on_the_face_rig():
    ff, poses = _face_rig_field()
    f64, f32 = ff.frames(poses), ff.frames(poses, np.float32)
    assert f32.dtype == np.float32 and f64.dtype == np.float64
    assert np.abs(f32 - f64).max() < 2e-5                        # measured 4e-6
    C = np.random.default_rng(0).normal(scale=2.0, size=poses.shape)     # mm
    w64, w32 = ff.to_world(poses, C), ff.to_world(poses, C, np.float32)
    assert w32.dtype == np.float32 and np.abs(w32 - w64).max() < 1e-4  # mm
    np.testing.assert_array_equal(w64, np.einsum("...nji,...nj->...ni", f64, C))
    with pytest.raises(ValueError, match="float64 or float32"):
        ff.frames(poses, np.float16)


def _pose_major_rows32(ff, V):
    """The (n,3) pose-major float32 frames FrameField._rows32 replaced: T, B, N (b,n,3),
    has_n (b,n) of poses V (b,n,3), each sparse product one column at a time."""
    from service.geometry.tangent_frames import CANCEL_RTOL, _cross, _normalize

    def by_columns(A, X):
        Xt = np.ascontiguousarray(X.T)
        out = np.empty((A.shape[0], X.shape[1]), np.result_type(A.dtype, X.dtype))
        for i, column in enumerate(Xt):
            out[:, i] = A @ column
        return out

    nb, n = V.shape[:2]
    m = len(ff.faces)
    incidence, du_edges = ff._float32
    e = (ff.edges @ V.transpose(1, 0, 2).reshape(n, 3 * nb)).astype(np.float32)
    T = by_columns(du_edges, e).reshape(n, nb, 3)
    e = e.reshape(2, m, nb, 3)
    fn = _cross(e[0], e[1])
    N = _normalize(by_columns(incidence, fn.reshape(m, 3 * nb)).reshape(n, nb, 3))
    T -= np.einsum("nbd,nbd->nb", T, N)[..., None] * N
    has_n = np.einsum("nbd,nbd->nb", N, N) > 0.25
    tn = np.sqrt(np.einsum("nbd,nbd->nb", T, T))
    weak = has_n & ~(tn > CANCEL_RTOL * np.maximum(np.abs(T).max(), 1e-300))
    if weak.any():
        Nw = N[weak]
        axis = np.eye(3)[np.argmin(np.abs(Nw), axis=1)]
        T[weak] = axis - np.einsum("kd,kd->k", axis, Nw)[:, None] * Nw
    T = _normalize(T)
    B = _cross(N, T)
    return T.transpose(1, 0, 2), B.transpose(1, 0, 2), N.transpose(1, 0, 2), has_n.T


def test_frame_field_float32_component_major_is_the_pose_major_path_bit_for_bit():
    """frames / to_world in float32 run component-major (FrameField._rows32); the (n,3)
    pose-major float32 arithmetic they replaced (_rows) gives the same bits, one pose or two."""
    ff, poses = _face_rig_field()
    C = np.random.default_rng(0).normal(scale=2.0, size=poses.shape).astype(np.float32)
    T, B, N, has_n = _pose_major_rows32(ff, poses)
    old_frames = np.stack([T, B, N], axis=-2)
    old_frames[~has_n] = np.eye(3)
    old_world = C[..., 0:1] * T
    old_world += C[..., 1:2] * B
    old_world += C[..., 2:3] * N
    old_world[~has_n] = C[~has_n]
    np.testing.assert_array_equal(ff.frames(poses, np.float32), old_frames)
    np.testing.assert_array_equal(ff.to_world(poses, C, np.float32), old_world)
    np.testing.assert_array_equal(ff.frames(poses[1], np.float32), old_frames[1])
    np.testing.assert_array_equal(ff.to_world(poses[1], C[1], np.float32), old_world[1])


def test_frame_field_float32_rows_are_the_same_on_any_kernel_threads(monkeypatch):
    """The compiled float32 frames (service.geometry.frame_rows) over vertex and triangle
    ranges on two threads: the same bits as on one (and as the NumPy passes, test above)."""
    ff, poses = _face_rig_field()
    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    one = ff._rows32(poses[0], edges=True)
    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    two = ff._rows32(poses[0], edges=True)
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a, b)
    assert one[3].all() and one[4].shape == (3, 2 * len(ff.faces))


def test_frame_field_to_frame_inverts_to_world_and_shares_the_rows():
    """to_frame (world → frame coordinates, the PDM's shell fallback) is the einsum of the
    float32 frames it replaced bit for bit, and the poses' rows (rows32) computed once serve both
    it and to_world bit for bit."""
    ff, poses = _face_rig_field()
    W = np.random.default_rng(1).normal(scale=2.0, size=poses.shape).astype(np.float32)
    rows = ff.rows32(poses)
    local = ff.to_frame(poses, W, rows)
    old = np.einsum("fnij,fnj->fni", ff.frames(poses, np.float32), W)
    assert local.dtype == np.float32 and local.shape == W.shape
    np.testing.assert_array_equal(local, old)          # the same float32 sums, x, y, z in order
    np.testing.assert_array_equal(ff.to_frame(poses, W), local)
    np.testing.assert_array_equal(ff.to_world(poses, W, np.float32, rows), ff.to_world(poses, W, np.float32))
    np.testing.assert_allclose(ff.to_world(poses, local, np.float32), W, rtol=0, atol=1e-5)   # orthonormal frames
    np.testing.assert_array_equal(ff.to_frame(poses[1], W[1]), local[1])


def test_frame_field_from_its_operators_is_the_same_field_and_wrong_ones_are_refused():
    """FrameField.from_operators of :meth:`operators` (e.g. mapped from a model's cache) uses
    the matrices as given and gives the built field's frames bit for bit; a missing matrix,
    a wrong shape or a non-CSR one gives None (then build it)."""
    import scipy.sparse as sp

    from service.geometry.tangent_frames import OPERATORS, FrameField

    ff, poses = _face_rig_field()
    ops = ff.operators()
    assert tuple(ops) == OPERATORS
    again = FrameField.from_operators(ff.faces.astype(np.int32), ops)
    assert all(getattr(again, k) is ops[k] for k in OPERATORS)
    np.testing.assert_array_equal(again.frames(poses), ff.frames(poses))
    np.testing.assert_array_equal(again.frames(poses, np.float32), ff.frames(poses, np.float32))
    n = ops["du"].shape[0]
    assert FrameField.from_operators(ff.faces, {k: v for k, v in ops.items() if k != "edges"}) is None
    assert FrameField.from_operators(ff.faces[:-1], ops) is None                  # other triangles
    assert FrameField.from_operators(ff.faces, {**ops, "du": sp.csr_matrix((n + 1, n + 1))}) is None
    assert FrameField.from_operators(ff.faces, {**ops, "du_edges": ops["du_edges"].tocsc()}) is None


def test_edges_from_the_corners_are_the_edge_operators_rows_bit_for_bit():
    """frame_rows.triangle_edges (the corners differenced, issue 23) against the CSR rows of
    the edge operator it stands for, in either stored column order, on vertices with +0 and
    −0 coordinates and corners sharing coordinates (the signs of zero included); FrameField
    uses it for the operator build makes, not for another one."""
    import scipy.sparse as sp

    from service.geometry.frame_rows import triangle_edges, triangle_rows
    from service.geometry.tangent_frames import FrameField

    ff, poses = _face_rig_field()
    assert ff._edge_faces is not None
    rng = np.random.default_rng(9)
    V = poses[0].copy()
    V[rng.choice(len(V), 300, replace=False), rng.integers(0, 3, 300)] = 0.0
    V[rng.choice(len(V), 300, replace=False), rng.integers(0, 3, 300)] = -0.0
    F = ff.faces
    V[F[:50, 1]] = V[F[:50, 0]]                                     # e1 = 0 exactly
    m = len(F)
    E = ff.edges.tocsr()
    flipped = E.copy()                                              # the other column order per row
    flipped.indices = flipped.indices.reshape(-1, 2)[:, ::-1].copy().ravel()
    flipped.data = flipped.data.reshape(-1, 2)[:, ::-1].copy().ravel()
    got = (np.empty((3, 2 * m), np.float32), np.empty((3, m), np.float32))
    triangle_edges(0, m, ff._edge_faces, V, m, *got)
    for op in (E, flipped):
        want = (np.empty((3, 2 * m), np.float32), np.empty((3, m), np.float32))
        triangle_rows(0, m, op.indptr.astype(np.uint64), op.indices.astype(np.uint32), op.data, V, m, *want)
        for a, b in zip(got, want):
            assert np.array_equal(a.view(np.uint32), b.view(np.uint32))
    assert (got[0] == 0).sum() > 150 and np.signbit(got[0][got[0] == 0]).sum() == 0
    other = FrameField(ff.faces, ff.incidence, ff.du, sp.csr_matrix(2 * E), ff.du_edges)
    assert other._edge_faces is None
    assert FrameField(ff.faces, ff.incidence, ff.du, flipped, ff.du_edges)._edge_faces is not None

"""Tests for service.methods.pose_space.shell_frames and the float32 per-frame mesh path."""

import numpy as np

from service.geometry.tangent_frames import FrameField
from service.methods.pose_space.shell_frames import ShellFrames, locality_order


def _sphere_patch(k: int = 14):
    """A bumpy height field (k², 3) mm over a UV grid, its triangles and UVs (with a mirrored
    column of triangles so both handedness branches run)."""
    u, v = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    uv = np.column_stack([u.ravel(), v.ravel()])
    V = np.column_stack([40 * uv, 3 * np.sin(6 * uv[:, 0]) * np.cos(5 * uv[:, 1])]) + [80.0, 90.0, 100.0]
    idx = np.arange(k * k).reshape(k, k)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    return V, F, uv


def test_locality_order_is_a_permutation_of_small_bandwidth():
    V, F, _ = _sphere_patch(20)
    rng = np.random.default_rng(3)
    shuffle = rng.permutation(len(V))                  # a scrambled numbering of the same mesh
    rank = np.empty(len(V), np.int64)
    rank[shuffle] = np.arange(len(V))
    Fs = rank[F]
    order = locality_order(Fs, len(V))
    np.testing.assert_array_equal(np.sort(order), np.arange(len(V)))
    inv = np.empty(len(V), np.int64)
    inv[order] = np.arange(len(V))
    band = lambda G: np.abs(G[:, None, :] - G[:, :, None]).max()
    assert band(inv[Fs]) <= 2 * 20 + 2 < band(Fs)     # a grid row apart at most


def test_frames_match_the_float64_frame_field_and_rotate_like_it():
    V, F, uv = _sphere_patch()
    rng = np.random.default_rng(0)
    u = np.stack([2.0 * np.sin(V[:, 0] / 9), 1.5 * np.cos(V[:, 1] / 7), 2.5 * np.sin(V[:, 0] / 11 + V[:, 1] / 13)], 1)
    sf = ShellFrames.build(V, F, uv, F)
    T, B, N = sf.rows(sf.to_internal(u.astype(np.float32)))
    assert T.dtype == np.float32 and (np.abs(N).sum(axis=0) > 0).all()
    ref = FrameField.build(V, F, uv, F).frames(V + u)                            # (n,3,3) float64
    got = np.stack([sf.to_vertices(R) for R in (T, B, N)], axis=1)               # (n,3,3)
    err = np.abs(got - ref).max()
    assert err < 1e-5, err
    C = rng.normal(size=(len(V), 3)).astype(np.float32)
    zero = np.zeros((3, len(V)), np.float32)
    W = sf.to_vertices(sf.shell(sf.to_internal(u), zero, sf.to_internal(C), aligned=True))
    np.testing.assert_allclose(W, u + np.einsum("nji,nj->ni", ref, C), atol=1e-5)


def test_internal_order_round_trip_is_exact():
    V, F, uv = _sphere_patch()
    sf = ShellFrames.build(V, F, uv, F)
    X = np.random.default_rng(1).normal(size=(len(V), 3)).astype(np.float32)
    np.testing.assert_array_equal(sf.to_vertices(sf.to_internal(X)), X)
    np.testing.assert_array_equal(sf.to_internal(X)[:, sf.rank], X.T)


def test_float32_distances_and_corrections_match_float64(wpsd_exact, ps_data):
    """The compiled sum (distances summed per vertex in float32, polynomial, fade) against
    the float64 distances of eq. 3 and the corrections from them."""
    ev = wpsd_exact.evaluator
    sf, cs = ev.shell_frames, ev.correction_sum
    _, u = ev.deformation(ps_data[1][1].markers[[2, 9]])
    f = ev.features(u)
    ref = ev.sq_distances(f)                                                   # (n,2,P) float64
    for k in range(2):
        C, D = cs(f[k], 0.75, keep_distances=True)
        assert D.dtype == np.float32 and C.dtype == np.float32
        assert np.abs(D[sf.rank] - ref[:, k]).max() <= 1e-6 * ref.max()
        c64 = ev.corrections(ref[:, k:k + 1], f[k:k + 1])[0]
        np.testing.assert_allclose(sf.to_vertices(C), 0.75 * c64, atol=1e-5)
        np.testing.assert_array_equal(cs(f[k], 0.75, D2=D), C)              # distances given = summed


def test_mesh_path_within_1e_4_mm_of_float64_apply_corrections(wpsd_exact, ps_data):
    """The per-frame float32 shell + rotated corrections against the float64 operators."""
    from service.methods.pose_space.corrections import apply_corrections

    ev = wpsd_exact.evaluator
    pose, u = ev.deformation(ps_data[1][1].markers[[5]])
    f = ev.features(u)
    c = ev.corrections(ev.sq_distances(f), f)
    ref = pose.restore(apply_corrections(ev.base, ev.base.deform(u), c))[0]
    got = np.empty_like(ref, dtype=np.float32)
    ev.shell_detail(u[0], ev.shell_frames.to_internal(c[0]), pose.R[0], pose.t[0], world=got)
    two = np.empty_like(got)
    ev.shell_frames.shell(*_shell_args(ev, u[0], c[0]), pose.R[0], pose.t[0], world=two, threads=2)
    np.testing.assert_array_equal(two, got)           # vertex ranges on two threads: the same sums
    assert got.dtype == np.float32
    err = np.abs(got - ref).max()
    assert err < 1e-4, err
    assert np.abs(c).max() > 0.5                      # corrections that the frames had to rotate


def _shell_args(ev, u, c):
    sf = ev.shell_frames
    return sf.displacement(ev.basis_internal, u), ev.smooth_internal, sf.to_internal(c)


def test_displacement_is_the_basis_product_in_the_internal_order(wpsd_exact, ps_data):
    from service.geometry.thin_shell import apply_basis

    ev = wpsd_exact.evaluator
    sf = ev.shell_frames
    _, u = ev.deformation(ps_data[1][1].markers[[4]])
    ref = apply_basis(ev.base.basis.astype(np.float64), u[0])                 # (n,3) float64
    for threads in (1, 2):
        U = sf.displacement(ev.basis_internal, u[0], threads=threads)
        assert U.dtype == np.float32 and U.shape == (3, len(ref))
        assert np.abs(sf.to_vertices(U) - ref).max() <= 1e-5 * max(np.abs(ref).max(), 1.0)
        assert np.abs(ref).max() > 1.0                                        # a real deformation

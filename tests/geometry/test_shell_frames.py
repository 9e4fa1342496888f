"""Tests for service.geometry.shell_frames: the compiled float32 tangent frames of a thin
shell, the shell composed in them, and the per-point frame coordinates."""

import numpy as np

from service.geometry import ranges
from service.geometry.shell_frames import ShellFrames, displacement_pair, locality_order
from service.geometry.tangent_frames import FrameField


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


def test_kernel_indices_are_unsigned():
    """Every index array a kernel gathers or scatters by is unsigned (Numba then emits no
    negative-index wraparound check per access)."""
    V, F, uv = _sphere_patch()
    sf = ShellFrames.build(V, F, uv, F)
    at, dest = sf.points(np.array([5, 0, 5, 17]))
    for a in (sf.order, sf.rank, sf.faces, sf.ptr, sf.tri, at, dest):
        assert a.dtype.kind == "u", a.dtype
    np.testing.assert_array_equal(at, np.sort(sf.rank[[5, 0, 5, 17]]))
    np.testing.assert_array_equal(sf.rank[[5, 0, 5, 17]][dest], at)


def test_displacement_pair_is_each_product_alone_bit_for_bit():
    """One pass over two bases gives each basis' :meth:`ShellFrames.displacement` exactly
    (the same per-row sum), on any threads; both within float32 rounding of float64."""
    V, F, uv = _sphere_patch()
    sf = ShellFrames.build(V, F, uv, F)
    rng = np.random.default_rng(7)
    n, h = len(V), 37                                     # h not a multiple of the vector width
    B, Bc = (sf.internal_basis(rng.normal(size=(n, h)) * s) for s in (1.0, 0.01))
    u_H = rng.normal(size=(h, 3)) * 4.0
    u = np.ascontiguousarray(u_H.T, np.float32)
    for threads in (1, 2):
        U, Uc = np.empty((3, n), np.float32), np.empty((3, n), np.float32)
        ranges.run(displacement_pair, n, B, Bc, u, U, Uc, threads=threads)
        np.testing.assert_array_equal(U, sf.displacement(B, u_H, threads=1))
        np.testing.assert_array_equal(Uc, sf.displacement(Bc, u_H, threads=1))
    want = (Bc.astype(np.float64) @ u.T.astype(np.float64)).T
    assert np.abs(Uc - want).max() < 1e-5 * np.abs(want).max()


def _shell_case(k: int = 14):
    """The patch, its ShellFrames, a displacement u (n,3) and the float64 frames of V + u."""
    V, F, uv = _sphere_patch(k)
    u = np.stack([2.0 * np.sin(V[:, 0] / 9), 1.5 * np.cos(V[:, 1] / 7), 2.5 * np.sin(V[:, 0] / 11 + V[:, 1] / 13)], 1)
    sf = ShellFrames.build(V, F, uv, F)
    return V, u, sf, FrameField.build(V, F, uv, F).frames(V + u)


def test_coordinates_are_to_frame_at_the_points_on_any_threads():
    """The world vectors base + W in the shell's frames less sub, at points listed in any
    order with repeats (UV points on seam vertices), against the float64 frames."""
    V, u, sf, ref = _shell_case()
    rng = np.random.default_rng(5)
    n = len(V)
    W, base, sub = (rng.normal(size=(n, 3)) for _ in range(3))
    vertices = np.concatenate([rng.permutation(n), rng.integers(0, n, 40)])       # repeats
    frames = sf.rows(sf.to_internal(u))
    pts = sf.points(vertices)
    got = sf.coordinates(frames, sf.to_internal(W), sf.to_internal(base), sf.to_internal(sub), pts)
    want = (np.einsum("nij,nj->ni", ref, W + base) - sub)[vertices]
    assert got.dtype == np.float32 and got.shape == (len(vertices), 3)
    err = np.abs(got - want).max()
    assert err < 1e-5 * np.abs(want).max(), err                                  # float32 frames
    two = sf.coordinates(frames, sf.to_internal(W), sf.to_internal(base), sf.to_internal(sub), pts, threads=2)
    np.testing.assert_array_equal(two, got)


def test_place_is_the_shell_in_given_frames_with_an_exact_rest_pose():
    """X = rest + U + Frameᵀ C with the frames of :meth:`rows` given: float64 ``rest`` keeps
    the rest pose exact (the float32 terms added to it), the world output is Rᵀ (X − t) in
    float32, and vertex ranges on two threads give the same values."""
    V, u, sf, ref = _shell_case()
    rng = np.random.default_rng(6)
    C = rng.normal(size=(len(V), 3)).astype(np.float32)
    U = sf.to_internal(u)
    frames = sf.rows(U)
    rest = np.ascontiguousarray(V[sf.order].T)                                   # (3,n) float64
    Ci = np.ascontiguousarray(C[sf.order])                                       # (n,3) internal
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    t = np.array([12.0, -30.0, 250.0])
    world = np.empty((len(V), 3), np.float32)
    X = sf.place(frames, U, rest, Ci, R, t, aligned=True, world=world)
    want = V + u.astype(np.float32) + np.einsum("nji,nj->ni", ref, C)
    assert X.dtype == np.float64
    err = np.abs(X - want).max()
    assert err < 1e-5, err                                                       # mm; float32 frames and C
    werr = np.abs(world - (want - t) @ R).max()
    assert werr < 1e-5 + 2 ** -20 * np.linalg.norm(want - t, axis=1).max(), werr
    into = np.empty_like(X)
    two = np.empty_like(world)
    sf.place(frames, U, rest, Ci, R, t, aligned=into, world=two, threads=2)
    np.testing.assert_array_equal(into, X)
    np.testing.assert_array_equal(two, world)
    # the float32 shell of the same inputs (frames computed in the kernel): the same X to float32
    Xs = sf.to_vertices(sf.shell(U, sf.to_internal(V), sf.to_internal(C), aligned=True))
    assert np.abs(Xs - X).max() < 1e-4


def test_arrays_round_trip_and_wrong_shapes_are_built_again():
    """ShellFrames.arrays → from_arrays gives the same frames (a model's cache stores them);
    a missing field, a wrong shape or dtype gives None (the caller builds them)."""
    import dataclasses

    from tests.geometry.test_normal_map import cylinder

    st, V, F = cylinder()
    sf = ShellFrames.build(V, F, st, F)
    arrays = sf.arrays()
    back = ShellFrames.from_arrays(arrays, len(V), len(F))
    for f in dataclasses.fields(sf):
        assert np.array_equal(getattr(back, f.name), getattr(sf, f.name)) and getattr(back, f.name).dtype == getattr(sf, f.name).dtype
    assert ShellFrames.from_arrays(arrays, len(V) + 1, len(F)) is None
    assert ShellFrames.from_arrays({k: v for k, v in arrays.items() if k != "angle"}, len(V), len(F)) is None
    assert ShellFrames.from_arrays({**arrays, "rest": arrays["rest"].astype(np.float64)}, len(V), len(F)) is None

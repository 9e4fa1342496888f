"""The pose-space per-frame mesh path on :mod:`service.geometry.shell_frames` (the kernels' own
tests are in tests/geometry/test_shell_frames.py)."""

import numpy as np


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

"""Tests for service.geometry.normal_map: displacement map → tangent-space normal map."""

from pathlib import Path

import numpy as np
import pytest

from service.geometry.normal_map import NormalMapper, tangent_space_normal_map, uv_chart_labels
from service.geometry.tangent_frames import tangent_frames
from service.geometry.uv_raster import rasterize_uv, texel_centers_uv

RIG = Path(__file__).resolve().parents[2] / "service/samples/data/ict_face_rig.npz"


def grid(nx: int, ny: int):
    """Parameters st (k,2) of an (nx+1)×(ny+1) grid on [0,1]², CCW triangles (m,3)."""
    s, t = np.meshgrid(np.linspace(0, 1, nx + 1), np.linspace(0, 1, ny + 1))
    st = np.c_[s.ravel(), t.ravel()]
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    a = (j * (nx + 1) + i).ravel()
    b, c, d = a + 1, a + nx + 2, a + nx + 1
    return st, np.concatenate([np.c_[a, b, c], np.c_[a, c, d]])


def normal_map(h, V, F, uv, H, W):
    """Normal map of h on (V, F) with per-vertex uv, frames from tangent_frames."""
    raster = rasterize_uv(uv, F, H, W)
    return tangent_space_normal_map(h, raster, V, F, uv, F, tangent_frames(V, F, uv, F)), raster


def unit(x, y, z):
    """Stack and normalize along the last axis (float64)."""
    n = np.stack(np.broadcast_arrays(x, y, z), axis=-1).astype(np.float64)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def plane(size_x=10.0, size_y=10.0, k=8):
    """Flat k×k grid in z = 0, size_x × size_y mm, normal +z; returns (st, V, F)."""
    st, F = grid(k, k)
    V = np.c_[st[:, 0] * size_x, st[:, 1] * size_y, np.zeros(len(st))]
    return st, V, F


# flat plane, h = A sin(2π x / λ): texel spacing Δ = 10/128 mm, κ = 2π/λ
A, LAM, SIZE, RES = 0.2, 5.0, 10.0, 128
KAPPA, DELTA = 2 * np.pi / LAM, SIZE / RES


def sine_map(x_of_texel):
    return A * np.sin(KAPPA * x_of_texel)


def test_flat_plane_sine_matches_the_analytic_normal_within_the_difference_error():
    st, V, F = plane()
    x = SIZE * texel_centers_uv(RES, RES)[..., 0]                       # world x of texels
    n, raster = normal_map(sine_map(x), V, F, st, RES, RES)
    assert raster.mask.all() and n.dtype == np.float32 and n.shape == (RES, RES, 3)
    inner = np.s_[:, 1:-1]
    # central differences of a sampled sine are exact up to the factor sin(κΔ)/(κΔ) ...
    slope_fd = A * np.sin(KAPPA * DELTA) / DELTA * np.cos(KAPPA * x)
    np.testing.assert_allclose(n[inner], unit(-slope_fd, 0, 1)[inner], rtol=0, atol=2e-6)
    # ... so against the analytic normal the error is ≤ A κ (κΔ)²/6 = 4.0e-4 (Δ = 0.078 mm)
    exact = unit(-A * KAPPA * np.cos(KAPPA * x), 0, 1)
    bound = A * KAPPA * (KAPPA * DELTA) ** 2 / 6
    err = np.abs(n - exact).max(axis=-1)
    assert bound == pytest.approx(4.04e-4, rel=1e-2)
    assert err[inner].max() <= bound + 2e-6
    # one-sided at the first and last columns: ≤ A κ² Δ / 2 = 1.24e-2
    assert err[:, [0, -1]].max() <= A * KAPPA ** 2 * DELTA / 2
    assert np.abs(n[..., 1]).max() < 1e-6                             # h does not vary along v


def test_metric_plane_stretched_twice_along_x_halves_the_slope():
    st, V, F = plane()
    h = sine_map(SIZE * texel_centers_uv(RES, RES)[..., 0])
    n1, _ = normal_map(h, V, F, st, RES, RES)
    n2, _ = normal_map(h, V * [2.0, 1.0, 1.0], F, st, RES, RES)   # same uv, twice as wide
    np.testing.assert_allclose(n2[..., 0] / n2[..., 2], 0.5 * n1[..., 0] / n1[..., 2],
                               rtol=1e-5, atol=1e-7)
    assert np.abs(n1[..., 0]).max() > 0.2


def cylinder(R=20.0, theta=np.pi / 2, L=30.0, ks=48, kz=6):
    """Patch of a cylinder of radius R (mm) around z, angle theta, height L; uv = (θ/theta, z/L)."""
    st, F = grid(ks, kz)
    a = theta * st[:, 0]
    return st, np.c_[R * np.cos(a), R * np.sin(a), L * st[:, 1]], F   # outward normals


def test_constant_h_gives_exactly_the_unperturbed_normal():
    st, V, F = cylinder()
    raster = rasterize_uv(0.1 + 0.8 * st, F, 64, 96)
    h = np.where(raster.mask, 3.7, np.nan)
    uv = 0.1 + 0.8 * st
    n = tangent_space_normal_map(h, raster, V, F, uv, F, tangent_frames(V, F, uv, F))
    assert (~raster.mask).any()
    np.testing.assert_array_equal(n, np.broadcast_to(np.float32([0, 0, 1]), n.shape))


def test_mirrored_chart_x_follows_the_tangent_along_increasing_u():
    st, V, F = plane()
    uv_mirror = np.c_[1.0 - st[:, 0], st[:, 1]]                      # u grows towards −x
    fr = tangent_frames(V, F, uv_mirror, F)
    np.testing.assert_allclose(fr[:, 0], np.tile([-1.0, 0, 0], (len(V), 1)), atol=1e-12)
    np.testing.assert_allclose(fr[:, 1], np.tile([0, -1.0, 0], (len(V), 1)), atol=1e-12)

    def h_of(u, v):                                                 # a function of world (x, y)
        x, y = SIZE * u, SIZE * v
        return sine_map(x) + 0.5 * A * np.sin(2 * KAPPA * y)

    c = texel_centers_uv(RES, RES)
    sx = A * np.sin(KAPPA * DELTA) / DELTA                            # central-difference slopes
    sy = 0.5 * A * np.sin(2 * KAPPA * DELTA) / DELTA
    inner = np.s_[1:-1, 1:-1]

    n_plain, _ = normal_map(h_of(c[..., 0], c[..., 1]), V, F, st, RES, RES)
    x, y = SIZE * c[..., 0], SIZE * c[..., 1]
    dx, dy = sx * np.cos(KAPPA * x), sy * np.cos(2 * KAPPA * y)        # ∂h/∂x, ∂h/∂y
    np.testing.assert_allclose(n_plain[inner], unit(-dx, -dy, 1)[inner], atol=2e-6)

    n_mirror, raster = normal_map(h_of(1.0 - c[..., 0], c[..., 1]), V, F, uv_mirror, RES, RES)
    assert raster.mask.all()
    x = SIZE * (1.0 - c[..., 0])
    dx = sx * np.cos(KAPPA * x)
    # T = +u = −x and B = N × T = −y: (−T·∇h, −B·∇h) = (+∂h/∂x, +∂h/∂y)
    np.testing.assert_allclose(n_mirror[inner], unit(dx, dy, 1)[inner], atol=2e-6)
    # the same world bump seen from both charts: x flips with T, y flips with B
    np.testing.assert_allclose(n_mirror[:, ::-1][inner] * [-1, -1, 1], n_plain[inner], atol=2e-6)


def test_cylinder_ramp_in_u_has_the_arclength_slope():
    R, theta, L = 20.0, np.pi / 2, 30.0
    st, V, F = cylinder(R, theta, L)
    H, W = 64, 128
    c = texel_centers_uv(H, W)
    a, b = 10.0, 6.0                                                  # mm per unit u, v
    n, raster = normal_map(a * c[..., 0] + b * c[..., 1], V, F, st, H, W)
    assert raster.mask.all()
    # dh/ds along the arc = a / (R θ) = 0.318, along z = b / L = 0.2; the chords differ from
    # the arc by (φ/sin φ) and the interpolated tangent from the chord by ≤ φ, φ = θ/(2·48):
    # relative error ≤ φ² (1/6 + 1/2) = 1.8e-4
    slope_u, slope_v = -n[..., 0] / n[..., 2], -n[..., 1] / n[..., 2]
    np.testing.assert_allclose(slope_u, a / (R * theta), rtol=5e-4)
    np.testing.assert_allclose(slope_v, b / L, rtol=2e-5)
    assert np.abs(slope_u - a / (R * theta)).max() > 1e-6               # faceting is visible


def test_coarse_cylinder_matches_a_direct_float64_evaluation_of_the_definition():
    # 4 segments over 90°: vertex frames 22.5° apart, so the interpolated T, N are far from
    # unit and orthogonal and the Gram-Schmidt step matters (|N| drops to cos 11.25° = 0.98)
    st, V, F = cylinder(ks=4, kz=2)
    uv = st @ np.array([[1.0, 0.0], [0.3, 1.0]]).T * [0.7, 0.9] + [0.0, 0.05]   # sheared
    H, W = 40, 56
    c = texel_centers_uv(H, W)
    a, b = 15.0, -10.0
    fr = tangent_frames(V, F, uv, F)
    n, raster = normal_map(a * c[..., 0] + b * c[..., 1], V, F, uv, H, W)
    m = raster.mask
    pad = np.pad(m, 1)
    ok = m & (pad[1:-1, :-2] | pad[1:-1, 2:]) & (pad[:-2, 1:-1] | pad[2:, 1:-1])
    assert ok.sum() > 0.95 * m.sum() > 1000
    # the definition, texel by texel: g = J (JᵀJ)⁻¹ ∇h with J = E D⁻¹, frame interpolated
    # and re-orthonormalized (N first), normal ∝ (−T̂·g, −B̂·g, 1)
    t = raster.triangle[ok]
    E = np.stack([V[F[t, 1]] - V[F[t, 0]], V[F[t, 2]] - V[F[t, 0]]], axis=-1)      # (k,3,2)
    D = np.stack([uv[F[t, 1]] - uv[F[t, 0]], uv[F[t, 2]] - uv[F[t, 0]]], axis=-1)  # (k,2,2)
    J = E @ np.linalg.inv(D)
    g = (J @ np.linalg.solve(np.swapaxes(J, 1, 2) @ J, np.broadcast_to([a, b], (len(t), 2))
                             [..., None]))[..., 0]
    N = raster.interpolate(fr[:, 2], F)[ok]
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    T = raster.interpolate(fr[:, 0], F)[ok]
    T -= np.sum(T * N, axis=1, keepdims=True) * N
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    B = np.cross(N, T)
    expected = unit(-np.sum(T * g, axis=1), -np.sum(B * g, axis=1), 1.0)
    np.testing.assert_allclose(n[ok], expected, rtol=0, atol=3e-6)
    assert np.abs(n[ok, 0]).max() > 0.2 and np.abs(n[ok, 1]).max() > 0.2


def test_tilted_plane_with_sheared_uv_matches_the_metric_formula():
    rng = np.random.default_rng(7)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))                                    # rotation
    st, F = grid(6, 6)
    P2 = 12.0 * st                                                    # plane coords, mm
    V = P2 @ Q[:, :2].T + [3.0, -1.0, 2.0]
    A2 = np.array([[0.05, 0.02], [-0.015, 0.045]])                    # uv = A2 p + c, det > 0
    uv = P2 @ A2.T + [0.2, 0.25]
    H, W = 96, 80
    c = texel_centers_uv(H, W)
    alpha, beta = 0.8, -1.3                                           # h = α u + β v, mm
    n, raster = normal_map(alpha * c[..., 0] + beta * c[..., 1], V, F, uv, H, W)
    J = Q[:, :2] @ np.linalg.inv(A2)                                  # ∂P/∂(u,v), mm per uv
    g = J @ np.linalg.solve(J.T @ J, [alpha, beta])                   # surface gradient
    T = J[:, 0] / np.linalg.norm(J[:, 0])
    N = Q[:, 2] if np.dot(np.cross(J[:, 0], J[:, 1]), Q[:, 2]) > 0 else -Q[:, 2]
    expected = unit(-T @ g, -np.cross(N, T) @ g, 1.0)
    # texels with a covered neighbour along both axes (exact differences of a linear map)
    m = raster.mask
    pad = np.pad(m, 1)
    ok = m & (pad[1:-1, :-2] | pad[1:-1, 2:]) & (pad[:-2, 1:-1] | pad[2:, 1:-1])
    assert ok.sum() > 0.95 * m.sum() > 1000
    np.testing.assert_allclose(n[ok], np.broadcast_to(expected, n[ok].shape), atol=3e-6)


def test_uncovered_texels_and_chart_borders():
    # two charts packed side by side in uv (touching at u = 0.5), the right one half as tall;
    # h is a ramp of slope 0.1 along x in both, with a 5 mm jump between the charts and
    # NaN / inf outside them
    st, F = grid(4, 4)
    k = len(st)
    V = np.r_[np.c_[10 * st, np.zeros(k)], np.c_[12 + 10 * st, np.zeros(k)]]
    uv = np.r_[np.c_[0.5 * st[:, 0], st[:, 1]], np.c_[0.5 + 0.5 * st[:, 0], 0.5 * st[:, 1]]]
    FF = np.r_[F, F + k]
    np.testing.assert_array_equal(uv_chart_labels(FF, 2 * k), np.repeat([0, 1], len(F)))
    H, W = 32, 64
    raster = rasterize_uv(uv, FF, H, W)
    c = texel_centers_uv(H, W)
    right = c[..., 0] > 0.5
    x = np.where(right, 12 + 20 * (c[..., 0] - 0.5), 20 * c[..., 0])
    h = np.where(right, 5.0, 0.0) + 0.1 * x
    h[~raster.mask] = np.nan
    h[0, -1] = np.inf
    assert not raster.mask[0, -1] and (~raster.mask).sum() == H * W // 4
    n = tangent_space_normal_map(h, raster, V, FF, uv, FF, tangent_frames(V, FF, uv, FF))
    assert np.isfinite(n).all()
    np.testing.assert_array_equal(n[~raster.mask], np.broadcast_to([0, 0, 1], (H * W // 4, 3)))
    slope = np.broadcast_to(unit(-0.1, 0, 1), (3 * H * W // 4, 3))     # no jump, no NaN
    np.testing.assert_allclose(n[raster.mask], slope, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)


def test_opposite_vertex_tangents_inside_a_triangle_stay_finite_and_unit():
    # frames given directly: the right column of vertices has T and B flipped (still
    # right-handed), so the interpolated T passes through 0 inside the middle triangles
    st, V, F = plane(k=2)
    fr = np.broadcast_to(np.eye(3), (len(V), 3, 3)).copy()
    fr[st[:, 0] > 0.75, :2] *= -1
    raster = rasterize_uv(st, F, 32, 32)
    h = 0.5 * np.random.default_rng(11).normal(size=(32, 32))
    n = NormalMapper(raster, F, st, F, len(V)).normal_map(h, V, fr)
    assert np.isfinite(n).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)
    c = texel_centers_uv(32, 32)[..., 0]
    left, right = c < 0.45, c > 0.8                                   # T = +x, T = −x
    assert (np.abs(n[..., :2]).max(axis=-1)[left | right] > 0).mean() > 0.9


def test_function_and_mapper_agree_bit_exactly_and_calls_are_independent():
    st, V, F = cylinder()
    H, W = 48, 64
    raster = rasterize_uv(st, F, H, W)
    fr = tangent_frames(V, F, st, F)
    rng = np.random.default_rng(3)
    h1, h2 = 0.3 * rng.normal(size=(2, H, W))
    mapper = NormalMapper(raster, F, st, F, len(V))
    a = mapper.normal_map(h1, V, fr)
    mapper.normal_map(h2, V + 1.0, fr)
    np.testing.assert_array_equal(mapper.normal_map(h1, V, fr), a)
    b = tangent_space_normal_map(h1, raster, V, F, st, F, fr)
    assert a.dtype == b.dtype == np.float32
    assert np.array_equal(a, b)
    # a float32 map (the API dtype) gives the same normals up to its rounding
    np.testing.assert_allclose(mapper.normal_map(h1.astype(np.float32), V, fr), a, atol=1e-5)


def _dot(a, b):
    """Column-wise dot product of (3,N) arrays (the mapper's NumPy passes, frozen)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    """Column-wise cross product ``a × b`` of (3,N) arrays (the mapper's NumPy passes, frozen)."""
    c = np.empty_like(a)
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        np.multiply(a[j], b[k], out=c[i])
        c[i] -= a[k] * b[j]
    return c


def _numpy_gradient_operators(mapper, V):
    """NormalMapper.gradient_operators as NumPy passes over (3,mu) rows (frozen copy before its
    compiled kernel, issue 23)."""
    from service.geometry.normal_map import TRIANGLE_DEGENERATE_SIN

    Vt = np.ascontiguousarray(np.asarray(V, dtype=np.float64).T)
    p0 = np.take(Vt, mapper._faces_t[0], axis=1)
    e1 = (np.take(Vt, mapper._faces_t[1], axis=1) - p0).astype(np.float32)
    e2 = (np.take(Vt, mapper._faces_t[2], axis=1) - p0).astype(np.float32)
    nrm = _cross(e1, e2)
    det = _dot(nrm, nrm)
    ok = det > np.float32(TRIANGLE_DEGENERATE_SIN ** 2) * _dot(e1, e1) * _dot(e2, e2)
    inv = np.divide(np.float32(1.0), det, out=np.zeros_like(det), where=ok)
    a1 = _cross(e2, nrm)
    a1 *= inv
    a2 = _cross(nrm, e1)
    a2 *= inv
    du1, dv1, du2, dv2 = mapper._uv_edges
    K = np.empty((6, len(det)), dtype=np.float32)
    K[:3] = a1 * du1 + a2 * du2
    K[3:] = a1 * dv1 + a2 * dv2
    return K


def _numpy_derivatives(mapper, hf):
    """(∂h/∂u, ∂h/∂v) (N,) float32 at the covered texels as NumPy passes over the map (frozen
    copy of the mapper's stencils before the compiled pass took them in, issue 23): central
    differences from one dense difference image, the non-central texels patched."""
    from service.geometry.normal_texels import U_BWD, U_FWD, V_BWD, V_FWD

    texel = mapper._texel.astype(np.int64)
    W = mapper.shape[1]
    out = []
    for row, (step, fwd, bwd) in enumerate(((1, U_FWD, U_BWD), (W, V_FWD, V_BWD))):
        f, b = (mapper._code & fwd) > 0, (mapper._code & bwd) > 0
        odd = np.flatnonzero(~(f & b))
        diff = np.zeros(len(hf), dtype=hf.dtype)
        with np.errstate(invalid="ignore", over="ignore"):
            np.subtract(hf[2 * step:], hf[:len(hf) - 2 * step], out=diff[step:len(hf) - step])
        d = np.take(diff, texel)
        d[odd] = hf[np.where(f, texel + step, texel)[odd]] - hf[np.where(b, texel - step, texel)[odd]]
        d = d.astype(np.float32, copy=False)
        d *= mapper._scales[row][f.astype(int) + b]
        out.append(d)
    return out


def _numpy_normal_map(mapper, h, V, frames):
    """The per-texel pass as NumPy blocks of sparse products and elementwise passes
    (frozen copy of NormalMapper.normal_map before its compiled kernel, issue 23)."""
    import scipy.sparse as sp

    from service.geometry.normal_map import _EPS

    H, W = mapper.shape
    hf = np.asarray(h).reshape(-1)
    du, dv = _numpy_derivatives(mapper, hf)
    K = _numpy_gradient_operators(mapper, V)
    TN = np.empty((6, mapper.n), dtype=np.float32)
    TN[:3] = frames[:, 0].T
    TN[3:] = frames[:, 2].T
    N = len(mapper._texel)
    interp = sp.csr_matrix((mapper._lam.ravel(), mapper._corners.astype(np.int64).ravel(),
                            np.arange(0, 3 * N + 1, 3)), shape=(N, mapper.n))
    out = np.zeros((H * W, 3), np.float32)
    out[:, 2] = 1.0
    for s in range(0, N, 1 << 17):
        e = min(s + (1 << 17), N)
        Kb = np.take(K, mapper._triangle[s:e], axis=1)
        g = Kb[:3] * du[s:e]
        g += Kb[3:] * dv[s:e]
        Y = np.empty((6, e - s), dtype=np.float32)
        for i, row in enumerate(TN):
            Y[i] = interp[s:e] @ row
        T, Nn = Y[:3], Y[3:]
        X = _cross(T, Nn)
        Z = _cross(X, Nn)
        x = _dot(Z, g)
        x /= np.sqrt(np.maximum(_dot(Z, Z), _EPS))
        y = _dot(X, g)
        y /= np.sqrt(np.maximum(_dot(X, X), _EPS))
        r = x * x
        r += y * y
        r += 1.0
        np.sqrt(r, out=r)
        np.divide(1.0, r, out=r)
        out[mapper._texel[s:e]] = np.stack([x * r, y * r, r], axis=1)
    return out.reshape(H, W, 3)


def test_the_compiled_texel_pass_is_the_numpy_one_bit_for_bit_on_any_threads():
    """Issue 23: the per-texel kernel against the NumPy blocks it replaced, on the cylinder
    (a seam) and the deformed ICT rig (two UDIM tiles, mirrored charts, NaN outside)."""
    st, V, F = cylinder()
    raster = rasterize_uv(st, F, 48, 64)
    fr = tangent_frames(V, F, st, F).astype(np.float32)
    h = 0.2 * np.random.default_rng(5).normal(size=(48, 64))
    mapper = NormalMapper(raster, F, st, F, len(V))
    one = mapper.normal_map(h, V, fr, threads=1)
    np.testing.assert_array_equal(one, _numpy_normal_map(mapper, h, V, fr))
    np.testing.assert_array_equal(mapper.normal_map(h, V, fr, threads=2), one)
    rig = np.load(RIG)
    V = rig["neutral"].astype(np.float64) + rig["expression_deltas"][0].astype(np.float64)
    F = rig["triangles"].astype(np.int64)
    UF = rig["triangle_uv"].astype(np.int64)
    uv = rig["uv"].astype(np.float64) * [0.5, 1.0]
    raster = rasterize_uv(uv, UF, 192, 192)
    mapper = NormalMapper(raster, F, uv, UF, len(V))
    fr = tangent_frames(V, F, uv, UF).astype(np.float32)
    c = texel_centers_uv(192, 192)
    h = np.where(raster.mask, 0.4 * np.sin(40 * c[..., 0]) * np.cos(33 * c[..., 1]), np.nan)
    np.testing.assert_array_equal(mapper.normal_map(h, V, fr, threads=2), _numpy_normal_map(mapper, h, V, fr))


def test_ict_rig_deformed_pose_is_finite_unit_and_flat_for_constant_h():
    rig = np.load(RIG)
    V = rig["neutral"].astype(np.float64) + rig["expression_deltas"][0].astype(np.float64)
    F = rig["triangles"].astype(np.int64)
    UF = rig["triangle_uv"].astype(np.int64)
    uv = rig["uv"].astype(np.float64) * [0.5, 1.0]                    # both UDIM tiles in [0,1]²
    H = W = 192
    raster = rasterize_uv(uv, UF, H, W)
    mapper = NormalMapper(raster, F, uv, UF, len(V))
    fr = tangent_frames(V, F, uv, UF)
    c = texel_centers_uv(H, W)
    h = 0.4 * np.sin(40 * c[..., 0]) * np.cos(33 * c[..., 1])
    n = mapper.normal_map(np.where(raster.mask, h, np.nan), V, fr)
    assert np.isfinite(n).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)
    assert (n[raster.mask, 2] > 0.2).all() and np.abs(n[raster.mask, :2]).max() > 0.1
    outside = n[~raster.mask]
    np.testing.assert_array_equal(outside, np.broadcast_to([0, 0, 1], outside.shape))
    flat = mapper.normal_map(np.full((H, W), -2.5), V, fr)
    np.testing.assert_array_equal(flat, np.broadcast_to(np.float32([0, 0, 1]), flat.shape))


def test_shapes_are_checked():
    st, V, F = plane(k=2)
    raster = rasterize_uv(st, F, 8, 8)
    mapper = NormalMapper(raster, F, st, F, len(V))
    fr = tangent_frames(V, F, st, F)
    with pytest.raises(ValueError, match="h must be"):
        mapper.normal_map(np.zeros((8, 9)), V, fr)
    with pytest.raises(ValueError, match="frames must be"):
        mapper.normal_map(np.zeros((8, 8)), V, fr[:, :2])
    with pytest.raises(ValueError, match="V must be"):
        mapper.normal_map(np.zeros((8, 8)), V[:-1], fr)
    with pytest.raises(ValueError, match="raster refers"):
        NormalMapper(raster, F[:1], st, F[:1], len(V))


def test_out_is_written_in_place():
    st, V, F = cylinder()
    H, W = 48, 64
    raster = rasterize_uv(st, F, H, W)
    fr = tangent_frames(V, F, st, F).astype(np.float32)
    h = 0.3 * np.random.default_rng(4).normal(size=(H, W)).astype(np.float32)
    mapper = NormalMapper(raster, F, st, F, len(V))
    ref = mapper.normal_map(h, V, fr)
    out = np.full((2, H, W, 3), np.nan, np.float32)                   # dirty: every texel is written
    got = mapper.normal_map(h, V, fr, out=out[1])
    assert got is out[1] or np.shares_memory(got, out)
    np.testing.assert_array_equal(out[1], ref)
    assert np.isnan(out[0]).all()
    with pytest.raises(ValueError, match="out must be"):
        mapper.normal_map(h, V, fr, out=np.zeros((H, W, 3)))


def test_a_float16_out_is_the_float32_map_rounded_by_numpy_bit_for_bit():
    """Issue 23: the texel pass and the uncovered runs write float16 themselves; the map is
    ``astype(np.float16)`` of the float32 one, on one thread and on two, NaN texels too."""
    st, V, F = cylinder()
    H, W = 48, 64
    raster = rasterize_uv(st, F, H, W)
    fr = tangent_frames(V, F, st, F).astype(np.float32)
    fr[:5, 0] = np.nan                                               # NaN normals near those vertices
    h = 0.3 * np.random.default_rng(8).normal(size=(H, W)).astype(np.float32)
    mapper = NormalMapper(raster, F, st, F, len(V))
    ref = mapper.normal_map(h, V, fr)
    assert np.isnan(ref).any() and (ref[~raster.mask] == [0, 0, 1]).all()
    for threads in (1, 2):
        out = np.full((H, W, 3), np.nan, np.float16)                  # dirty: every texel is written
        got = mapper.normal_map(h, V, fr, out=out, threads=threads)
        assert got is out
        np.testing.assert_array_equal(out.view(np.uint16), ref.astype(np.float16).view(np.uint16))


def test_rows_of_the_frame_field_give_the_frames_normal_map_bit_for_bit():
    """normal_map(rows=FrameField.normal_rows(V)) (T, N rows and the frames' float32 edges,
    no (n,3,3) frames formed, no edges gathered again) is normal_map(frames=frames(V, float32))."""
    from service.geometry.tangent_frames import FrameField

    st, V, F = cylinder()
    H, W = 48, 64
    raster = rasterize_uv(st, F, H, W)
    ff = FrameField.build(V, F, st, F)
    pose = V + 0.05 * np.random.default_rng(6).normal(size=V.shape) + [200.0, -100.0, 50.0]
    h = 0.3 * np.random.default_rng(7).normal(size=(H, W)).astype(np.float32)
    mapper = NormalMapper(raster, F, st, F, len(V))
    frames = ff.frames(pose, np.float32)
    TN, edges = ff.normal_rows(pose)
    np.testing.assert_array_equal(TN[:3], frames[:, 0].T)
    np.testing.assert_array_equal(TN[3:], frames[:, 2].T)
    np.testing.assert_array_equal(mapper.gradient_operators(pose, edges), mapper.gradient_operators(pose))
    np.testing.assert_array_equal(mapper.normal_map(h, pose, None, rows=(TN, edges)),
                                  mapper.normal_map(h, pose, frames))
    with pytest.raises(ValueError, match="rows"):
        mapper.normal_map(h, pose, None, rows=(TN[:3], edges))
    with pytest.raises(ValueError, match="edges must be"):
        mapper.gradient_operators(pose, edges[:, :-1])


def test_compiled_gradient_operators_are_the_numpy_passes_bit_for_bit():
    """Issue 23: the per-triangle kernel against the NumPy passes it replaced, on a deformed
    cylinder far from the origin with collapsed triangles (degenerate: zero) and a NaN vertex,
    from V and from the frames' edges."""
    from service.geometry.tangent_frames import FrameField

    st, V, F = cylinder()
    raster = rasterize_uv(st, F, 48, 64)
    mapper = NormalMapper(raster, F, st, F, len(V))
    pose = V + 0.05 * np.random.default_rng(8).normal(size=V.shape) + [200.0, -100.0, 50.0]
    pose[F[:5, 1]] = pose[F[:5, 0]]                              # five triangles collapsed
    ref = _numpy_gradient_operators(mapper, pose)
    got = mapper.gradient_operators(pose)
    assert (ref == 0).all(axis=0).sum() >= 1 and np.abs(ref).max() > 0
    assert np.array_equal(got.view(np.uint32), ref.view(np.uint32))
    _, edges = FrameField.build(V, F, st, F).normal_rows(pose)
    assert np.array_equal(mapper.gradient_operators(pose, edges).view(np.uint32), ref.view(np.uint32))
    pose[F[7, 2]] = np.nan
    ref, got = _numpy_gradient_operators(mapper, pose), mapper.gradient_operators(pose)
    assert np.isnan(ref).any()
    assert np.array_equal(got.view(np.uint32), ref.view(np.uint32))


def test_a_mapper_from_its_arrays_maps_bit_for_bit_and_bad_arrays_are_refused():
    """issue 23 (cold start): NormalMapper.arrays() → from_arrays() (a model's cache) gives
    the same maps bit for bit; missing, mistyped, misshaped or out-of-range arrays give None."""
    st, V, F = cylinder()
    raster = rasterize_uv(st, F, 48, 40)
    mapper = NormalMapper(raster, F, st, F, len(V))
    arrays = mapper.arrays()
    again = NormalMapper.from_arrays(arrays, len(V), len(F))
    rng = np.random.default_rng(7)
    h = rng.normal(0, 0.05, mapper.shape)
    Vd = V + rng.normal(0, 0.01, V.shape)
    fr = tangent_frames(Vd, F, st, F)
    assert again is not None and again.shape == mapper.shape
    np.testing.assert_array_equal(again.normal_map(h, Vd, fr), mapper.normal_map(h, Vd, fr))
    assert NormalMapper.from_arrays(arrays, len(V) + 1, len(F)) is None
    assert NormalMapper.from_arrays({k: v for k, v in arrays.items() if k != "lam"}, len(V), len(F)) is None
    assert NormalMapper.from_arrays({**arrays, "lam": arrays["lam"].astype(np.float64)}, len(V), len(F)) is None
    assert NormalMapper.from_arrays({**arrays, "texel": arrays["texel"][:-1]}, len(V), len(F)) is None
    bad = arrays["corners"].copy()
    bad[0, 0] = len(V)
    assert NormalMapper.from_arrays({**arrays, "corners": bad}, len(V), len(F)) is None

"""ma2008 §4.1: coarse marker mesh, 5D deformation vectors, axes, d1/d2."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import scan_convert
from service.methods.pdm import deformation as dm


def _grid(n=7, spacing=10.0, seed=0):
    """Markers on a jittered n×n grid in the plane z=0; uv = xy / 100; axes = x, y."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    P = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    P[:, :2] += rng.uniform(-1.5, 1.5, size=(n * n, 2))
    axes = np.tile(np.eye(3)[:2], (n * n, 1, 1))
    return dm.marker_mesh(P[:, :2] / 100.0, P, axes), P


def test_two_ring_and_rest_sigma():
    mesh, P = _grid()
    assert mesh.faces.shape[1] == 3 and len(mesh.faces) >= 2 * 36 - 4
    N2 = mesh.two_ring.toarray()
    assert N2.diagonal().all() and (N2 == N2.T).all()
    # the two-ring of an interior marker of a triangulated grid holds 13-19 markers
    centre = 24
    assert 13 <= N2[centre].sum() <= 25
    sig = dm.neighbourhood_sigma(mesh, P[None])[0]
    j = np.flatnonzero(N2[centre])
    np.testing.assert_allclose(sig[centre], P[j, :2].std(axis=0), rtol=1e-12)
    np.testing.assert_allclose(mesh.rest_sigma, sig)


def test_a_mesh_given_its_own_triangles_equals_the_triangulated_one():
    """A stored model's marker mesh (``faces=``, no Delaunay at load) is the trained one."""
    mesh, P = _grid()
    again = dm.marker_mesh(mesh.uv, P, mesh.axes, faces=mesh.faces)
    for name in ("uv", "faces", "rest", "axes", "rest_sigma"):
        np.testing.assert_array_equal(getattr(again, name), getattr(mesh, name))
    assert (again.two_ring != mesh.two_ring).nnz == 0


def test_strain_of_a_uniformly_scaled_patch_is_analytic():
    """Scaling the patch by s about any point changes σ by (s−1)σ_ref exactly; O = (s−1)P."""
    mesh, P = _grid()
    s = 1.15
    S = dm.deformation_vectors(mesh, (s * P)[None])[0]
    np.testing.assert_allclose(S[:, 3:], (s - 1) * mesh.rest_sigma, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(S[:, :3], (s - 1) * P, atol=1e-12)
    # anisotropic: stretch along u only
    S = dm.deformation_vectors(mesh, (P * [1.2, 1.0, 1.0])[None])[0]
    np.testing.assert_allclose(S[:, 3], 0.2 * mesh.rest_sigma[:, 0], rtol=1e-12)
    np.testing.assert_allclose(S[:, 4], 0.0, atol=1e-12)


def test_neutral_gives_zero_and_occluded_markers_drop_out():
    mesh, P = _grid()
    np.testing.assert_allclose(dm.deformation_vectors(mesh, P[None]), 0.0, atol=1e-12)
    Q = P.copy()
    Q[10] = np.nan
    S = dm.deformation_vectors(mesh, Q[None])[0]
    assert np.isnan(S[10, :3]).all() and np.isfinite(S[:, 3:]).all()
    # at the neutral, a missing marker leaves every strain exactly zero (it drops out of
    # the rest σ too), and the offsets can be supplied (e.g. completed by the thin shell)
    np.testing.assert_allclose(S[:, 3:], 0.0, atol=1e-12)
    S2 = dm.deformation_vectors(mesh, Q[None], offsets=np.zeros((1,) + P.shape))[0]
    assert np.isfinite(S2).all()
    # stretched by 1.5 along u: a neighbour's strain is measured over the visible markers only
    i = 11
    j = np.setdiff1d(np.flatnonzero(mesh.two_ring.toarray()[i]), [10])
    Q[:, 0] *= 1.5
    S = dm.deformation_vectors(mesh, Q[None])[0]
    np.testing.assert_allclose(S[i, 3], 0.5 * P[j, 0].std(), rtol=1e-12)


def test_pca_axes_recover_a_planted_two_dimensional_deformation():
    mesh, P = _grid()
    rng = np.random.default_rng(1)
    M = len(P)
    a, b = np.zeros(5), np.zeros(5)
    a[1], a[3] = 0.8, 0.6                     # "raise + stretch along u"
    b[0], b[2] = 0.6, -0.8
    t1, t2 = rng.normal(0, 3, 40), rng.normal(0, 1, 40)
    t2 -= (t2 @ t1) / (t1 @ t1) * t1          # uncorrelated samples: the axes are exactly a, b
    scale = dm.strain_scale(mesh)
    X = t1[:, None, None] * a + t2[:, None, None] * b + rng.normal(0, 1e-3, (40, M, 5))
    S = X / scale                              # so that scale·S = X
    axes = dm.deformation_axes(mesh, S)
    assert np.all(np.abs(np.abs(axes.q @ a) - 1) < 1e-3)
    assert np.all(np.abs(np.abs(axes.r @ b) - 1) < 1e-3)
    # consistently oriented over the mesh
    assert abs(np.sign(axes.q @ a).sum()) == M and abs(np.sign(axes.r @ b).sum()) == M
    assert np.all(axes.energy[:, 1] > 0.999)
    d1, d2 = dm.pdm_parameters(axes, S, dm.barycentric_operator(mesh, mesh.uv))
    sign1, sign2 = np.sign(axes.q[0] @ a), np.sign(axes.r[0] @ b)
    np.testing.assert_allclose(d1, sign1 * t1[:, None] * np.ones(M), atol=0.02)
    np.testing.assert_allclose(d2, sign2 * t2[:, None] * np.ones(M), atol=0.02)


def test_smoothing_replaces_the_outlier_and_keeps_pairs_orthonormal():
    mesh, _ = _grid()
    M = len(mesh.uv)
    Q = np.tile(np.eye(5)[0], (M, 1))
    R = np.tile(np.eye(5)[1], (M, 1))
    Q[24] = np.eye(5)[2]                       # one outlier axis
    R[24] = np.eye(5)[1]
    q, r, replaced, worst = dm.smooth_axes(Q, R, mesh.adjacency, threshold_deg=10.0)
    assert replaced >= 1 and worst <= 10.0
    np.testing.assert_allclose(q[24], np.eye(5)[0], atol=1e-12)
    np.testing.assert_allclose(np.einsum("md,md->m", q, r), 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1, atol=1e-12)


def test_orientation_flips_disagreeing_neighbours():
    mesh, _ = _grid()
    V = np.tile([1.0, 0, 0, 0, 0], (len(mesh.uv), 1))
    V[::3] *= -1
    out = dm.orient_consistently(V, mesh.adjacency)
    assert np.all(out[:, 0] == out[0, 0])


def test_barycentric_operator_interpolates_inside_and_clamps_outside():
    mesh, P = _grid()
    rng = np.random.default_rng(2)
    uv = rng.uniform(0.05, 0.55, size=(200, 2))
    W = dm.barycentric_operator(mesh, uv)
    np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert W.min() >= -1e-12
    # linear functions of uv are reproduced inside the hull
    inside = (uv > 0.02).all(axis=1) & (uv < 0.58).all(axis=1)
    f = mesh.uv @ [2.0, -3.0] + 1
    np.testing.assert_allclose((W @ f)[inside], (uv @ [2.0, -3.0] + 1)[inside], atol=1e-9)
    # far outside: the value of the nearest hull point (constant extension)
    far = dm.barycentric_operator(mesh, np.array([[0.3, 5.0]]))
    top = (W @ f).max()
    assert (far @ f)[0] <= f.max() + 1e-9
    assert np.isfinite(top)


def test_barycentric_operator_outside_is_the_nearest_point_of_the_coarse_mesh():
    mesh, P = _grid()
    rng = np.random.default_rng(3)
    uv = rng.uniform(-0.5, 1.1, size=(400, 2))
    W = dm.barycentric_operator(mesh, uv, bridge_holes=False)
    pos = W @ mesh.uv
    # brute force: nearest point over every coarse triangle's three edges and interior
    T = mesh.uv[mesh.faces]
    best = np.full(len(uv), np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        A, AB = T[:, a], T[:, b] - T[:, a]
        t = np.clip(np.einsum("pkd,kd->pk", uv[:, None] - A, AB) / np.einsum("kd,kd->k", AB, AB), 0, 1)
        best = np.minimum(best, np.linalg.norm(A + t[..., None] * AB - uv[:, None], axis=2).min(axis=1))
    lam = np.stack([scan_convert.barycentric_2d(T, np.full(len(T), x), np.full(len(T), y)) for x, y in uv])
    best[(lam >= -1e-12).all(axis=2).any(axis=1)] = 0.0
    np.testing.assert_allclose(np.linalg.norm(pos - uv, axis=1), best, atol=1e-12)


def test_sample_actor_deformation_is_mostly_two_dimensional(actor0):
    """On the sample actor's training clips the first two axes carry > 85 % of the energy
    (ma2008 Table 1: 92.5 %), and the smoothing pass converges at its default threshold."""
    from service.geometry.rigid import rigid_align
    from service.geometry.tangent_frames import tangent_frames
    from service.samples import performances
    from service.samples.actor import render_performance

    skin, layout = actor0.skin, actor0.markers
    clips = performances.training_clips(actor0.rig.expression_names, 3)
    P = np.concatenate([render_performance(actor0, c, np.arange(0))["markers"] for c in clips])
    rest = layout.positions(skin.neutral, skin.faces)
    P = np.stack([rigid_align(p, rest).apply(p) for p in P])
    frames = tangent_frames(skin.neutral, skin.faces, skin.uv, skin.uv_faces)
    axes = np.einsum("mk,mkad->mad", layout.barycentric, frames[skin.faces[layout.triangle]][:, :, :2])
    axes /= np.linalg.norm(axes, axis=2, keepdims=True)
    uv = np.einsum("mk,mkd->md", layout.barycentric, skin.uv[skin.uv_faces[layout.triangle]])
    mesh = dm.marker_mesh(uv, rest, axes)
    result = dm.deformation_axes(mesh, dm.deformation_vectors(mesh, P))
    energy = result.energy.mean(axis=0)
    assert energy[1] > 0.85 and energy[0] < energy[1] < energy[2] <= 1.0 + 1e-12
    assert result.worst_angle_deg <= 30.0
    np.testing.assert_allclose(np.einsum("md,md->m", result.q, result.r), 0, atol=1e-9)


def test_parameter_field_is_interpolate_then_dot_in_either_point_order():
    mesh, P = _grid()
    rng = np.random.default_rng(5)
    M = len(P)
    q = rng.normal(size=(M, 5))
    r = rng.normal(size=(M, 5))
    scale = rng.uniform(0.5, 2.0, size=(M, 5))
    axes = dm.DeformationAxes(q, r, scale, np.ones((M, 5)), 0, 0.0)
    uv = rng.uniform(-0.1, 0.7, size=(300, 2))               # inside and outside the hull
    W = dm.barycentric_operator(mesh, uv)
    S = rng.normal(size=(4, M, 5))
    Sp = np.einsum("pm,tmd->tpd", W.toarray(), S * scale)
    d1_ref = np.einsum("tpd,pd->tp", Sp, W @ q)
    d2_ref = np.einsum("tpd,pd->tp", Sp, W @ r)
    d1, d2 = dm.ParameterField.build(axes, W)(S)             # gather path
    np.testing.assert_allclose(d1, d1_ref, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(d2, d2_ref, rtol=1e-5, atol=1e-4)
    order = dm.ParameterField.element_order(W)
    field = dm.ParameterField.build(axes, W[order])
    assert field.runs is not None                           # grouped: the run-length path
    e1, e2 = field(S)
    np.testing.assert_allclose(e1, d1_ref[:, order], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(e2, d2_ref[:, order], rtol=1e-5, atol=1e-4)


def test_holes_are_bridged_for_the_parameters_only():
    # a ring of markers around a wide hole: the hole's Delaunay triangles have long edges,
    # so the coarse mesh drops them (no strain across the hole) ...
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring = np.concatenate([np.column_stack([np.cos(t), np.sin(t)]) * r for r in (1.0, 1.25, 1.5)])
    P = np.column_stack([ring * 20.0, np.zeros(len(ring))])
    mesh = dm.marker_mesh(ring * 0.2 + 0.5, P, np.tile(np.eye(3)[:2], (len(P), 1, 1)))
    centre = np.array([[0.5, 0.5], [0.52, 0.47]])
    f = mesh.uv @ [2.0, -3.0] + 1.0
    bridged = dm.barycentric_operator(mesh, centre)
    edge = dm.barycentric_operator(mesh, centre, bridge_holes=False)
    # ... but the parameters inside it interpolate across (linear functions reproduced)
    np.testing.assert_allclose(bridged @ f, centre @ [2.0, -3.0] + 1.0, atol=1e-9)
    assert np.diff(edge.indptr).max() == 2                   # the hole's edge: 2 markers
    assert np.abs(edge @ f - (centre @ [2.0, -3.0] + 1.0)).max() > 0.1
    assert np.diff(bridged.indptr).max() == 3


def test_parameter_field_blocks_cover_the_runs_and_combine_bit_for_bit():
    mesh, P = _grid()
    rng = np.random.default_rng(6)
    M = len(P)
    axes = dm.DeformationAxes(rng.normal(size=(M, 5)), rng.normal(size=(M, 5)),
                              np.ones((M, 5)), np.ones((M, 5)), 0, 0.0)
    W = dm.barycentric_operator(mesh, rng.uniform(-0.1, 0.7, size=(400, 2)))
    field = dm.ParameterField.build(axes, W[dm.ParameterField.element_order(W)])
    S = rng.normal(size=(3, M, 5))
    d1, d2 = field(S)
    blocks = field.blocks(37)
    starts = field.run_starts
    # consecutive whole runs, every element once; a block passes 37 points only when one run does
    assert blocks[0][0] == 0 and blocks[-1][1] == len(field.markers)
    assert all(a < b and b == c for (a, b), (c, _) in zip(blocks, blocks[1:] + [(blocks[-1][1], 0)]))
    assert all(starts[b] - starts[a] <= 37 or b == a + 1 for a, b in blocks)
    g = field.element_terms(S)
    parts = [field.combine(g, a, b) for a, b in blocks]
    assert np.array_equal(np.concatenate([p[0] for p in parts], axis=1), d1)
    assert np.array_equal(np.concatenate([p[1] for p in parts], axis=1), d2)


def test_sorted_field_combine_by_matrix_products_is_the_elementwise_sum_within_float32():
    """ParameterField.combine (one (2,6)·(6,run) product per element) against the elementwise
    sum over the points (_combine of the repeated terms): within 3e-7 of the largest |d|;
    any split of the elements gives the same bits."""
    from service.methods.pdm.deformation import ParameterField

    rng = np.random.default_rng(7)
    M, E, P, T = 12, 9, 4000, 3
    markers = np.sort(rng.integers(0, M, (E, 3)), axis=1)
    element = np.sort(rng.integers(0, E, P))
    w = rng.dirichlet(np.ones(3), P)
    mono = np.stack([w[:, 0] ** 2, w[:, 1] ** 2, w[:, 2] ** 2, w[:, 0] * w[:, 1], w[:, 0] * w[:, 2],
                     w[:, 1] * w[:, 2]]).astype(np.float32)
    q, r = rng.normal(size=(2, M, 5))
    field = ParameterField(element, markers, mono, q, r, np.ones((M, 5)), np.bincount(element, minlength=E))
    S = rng.normal(scale=3.0, size=(T, M, 5))
    g = field.element_terms(S)
    d1, d2 = field.combine(g, 0, E)
    e1, e2 = ParameterField._combine(g[:, :, element], mono)
    for got, ref in ((d1, e1), (d2, e2)):
        assert got.dtype == np.float32 and got.shape == (T, P)
        assert np.abs(got - ref).max() <= 3e-7 * np.abs(ref).max()
    starts = field.run_starts
    parts = [field.combine(g, a, b) for a, b in ((0, 4), (4, 5), (5, E))]
    np.testing.assert_array_equal(np.concatenate([p[0] for p in parts], axis=1), d1)
    np.testing.assert_array_equal(np.concatenate([p[1] for p in parts], axis=1), d2)
    assert starts[-1] == P


def test_an_unsorted_field_combines_by_element_and_puts_the_points_back():
    """ParameterField.build of points not grouped by element (the vertex band's UV points)
    sorts them once (``sorting``); a call combines by element (the matrix products) and
    returns the points in their own order: within 3e-7 of the elementwise sum."""
    import scipy.sparse as sp

    from service.methods.pdm.deformation import DeformationAxes, ParameterField

    rng = np.random.default_rng(8)
    M, E, P, T = 12, 9, 3000, 2
    tri = np.array([rng.choice(M, 3, replace=False) for _ in range(E)])
    element = rng.integers(0, E, P)                                  # unsorted
    w = rng.dirichlet(np.ones(3), P)
    W = sp.csr_matrix((w.ravel(), (np.repeat(np.arange(P), 3), tri[element].ravel())), shape=(P, M))
    q, r = rng.normal(size=(2, M, 5))
    axes = DeformationAxes(q, r, np.ones((M, 5)), np.ones((M, 5)), 0, 0.0)
    field = ParameterField.build(axes, W)
    assert field.runs is None and field.sorting is not None
    S = rng.normal(scale=3.0, size=(T, M, 5))
    d1, d2 = field(S)
    g = field.element_terms(S)
    e1, e2 = ParameterField._combine(g[:, :, field.element], field.mono)
    for got, ref in ((d1, e1), (d2, e2)):
        assert got.dtype == np.float32 and got.shape == (T, P)
        assert np.abs(got - ref).max() <= 3e-7 * np.abs(ref).max()


def _matmul_products(g, mono, starts, a, b):
    """The per-element BLAS products ParameterField._products made before it was compiled:
    one (T,2,6)·(6,run) ``np.matmul`` per element."""
    T, s0 = g.shape[0], starts[a]
    G = g[:, :, a:b].reshape(T, 2, 6, b - a)
    out = np.empty((T, 2, starts[b] - s0), np.float32)
    for e in range(a, b):
        s, t = starts[e] - s0, starts[e + 1] - s0
        if t > s:
            np.matmul(G[..., e - a], mono[:, s + s0:t + s0], out=out[:, :, s:t])
    return out[:, 0], out[:, 1]


def _assert_same_products(got, want):
    """Within 4 float32 ulp of the products' scale (six terms, each |g m| ≤ scale)."""
    scale = np.abs(want).max()
    assert np.abs(got.astype(np.float64) - want).max() <= 4 * np.finfo(np.float32).eps * scale


@pytest.mark.parametrize("T", [1, 3])
def test_compiled_element_products_are_the_per_element_matmul(T, monkeypatch):
    """The compiled pass (one fused multiply-add per term after the first product) gives the
    per-element np.matmul's values, for a block of elements and scattered back through an
    order, on one and two kernel threads: bit for bit where OpenBLAS's float32 GEMM kernel
    uses FMA in term order (this machine kind's), so the assertion is a bound of a few float32
    ulp of the row's scale, which another BLAS kernel's summation order also meets."""
    from service.methods.pdm.deformation import ParameterField

    rng = np.random.default_rng(11)
    E, P = 23, 5000
    counts = np.bincount(rng.integers(0, E, P), minlength=E)
    counts[5] = 0                                                     # an element without points
    P = int(counts.sum())
    starts = np.concatenate([[0], np.cumsum(counts)])
    g = rng.normal(scale=4.0, size=(T, 12, E)).astype(np.float32)
    w = rng.dirichlet(np.ones(3), P)
    mono = np.stack([w[:, 0] ** 2, w[:, 1] ** 2, w[:, 2] ** 2, w[:, 0] * w[:, 1], w[:, 0] * w[:, 2],
                     w[:, 1] * w[:, 2]]).astype(np.float32)
    for a, b in ((0, E), (3, 17)):
        want = _matmul_products(g, mono, starts, a, b)
        for threads in ("1", "2"):
            monkeypatch.setenv("NUMBA_NUM_THREADS", threads)
            got = ParameterField._products(g, mono, starts, a, b)
            for x, y in zip(got, want):
                assert x.flags.c_contiguous and x.shape == (T, starts[b] - starts[a])
                _assert_same_products(x, y)
    order = rng.permutation(P)
    got = ParameterField._products(g, mono, starts, 0, E, order)
    for x, y in zip(got, _matmul_products(g, mono, starts, 0, E)):
        want = np.empty_like(y)
        want[:, order] = y
        _assert_same_products(x, want)

"""Exact closest points on triangle meshes, and marker layouts resolved to surface points."""

import re

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from service.geometry.closest_point import closest_points, resolve_marker_layout
from service.io.markers import MarkerLayout


def brute_force_distance(V, F, P):
    """Distance (q,) from each point to the mesh, over all (point, triangle) pairs.

    A different method from the module's: the plane projection when it falls inside a
    non-degenerate triangle, else the nearest of the three edges (clamped segments).
    """
    T = V[F][None]                                               # (1,m,3,3)
    p = P[:, None, :]                                            # (q,1,3)
    A, B, C = T[..., 0, :], T[..., 1, :], T[..., 2, :]
    n = np.cross(B - A, C - A)
    nn = np.einsum("...d,...d->...", n, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        height = np.einsum("...d,...d->...", p - A, n) / nn
        foot = p - height[..., None] * n
        sides = [np.einsum("...d,...d->...", np.cross(Y - X, foot - X), n)
                 for X, Y in ((A, B), (B, C), (C, A))]
    inside = (nn > 0) & (np.stack(sides) >= 0).all(axis=0)
    best = np.where(inside, np.abs(height) * np.sqrt(nn), np.inf)
    for X, Y in ((A, B), (B, C), (C, A)):
        e = Y - X
        ee = np.einsum("...d,...d->...", e, e)
        t = np.einsum("...d,...d->...", p - X, e) / np.where(ee > 0, ee, 1.0)
        t = np.clip(np.where(ee > 0, t, 0.0), 0, 1)
        best = np.minimum(best, np.linalg.norm(p - X - t[..., None] * e, axis=-1))
    return best.min(axis=1)


def assert_consistent(result, V, F, P):
    """Barycentrics are a convex combination reproducing the point at the distance."""
    assert result.triangle.dtype == np.int64
    assert np.isfinite(result.barycentric).all()
    assert (result.barycentric >= 0).all()
    np.testing.assert_allclose(result.barycentric.sum(axis=1), 1, atol=1e-14)
    point = np.einsum("qk,qkd->qd", result.barycentric, V[F[result.triangle]])
    np.testing.assert_allclose(result.point, point, atol=1e-14)
    np.testing.assert_allclose(result.distance, np.linalg.norm(P - point, axis=1), atol=1e-14)


@pytest.fixture(scope="module")
def sphere():
    """An icosphere (162 vertices, 320 triangles) with radially jittered vertices."""
    s = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(7)
    V = np.asarray(s.vertices) * rng.uniform(0.85, 1.15, size=(len(s.vertices), 1))
    return V, np.asarray(s.faces, dtype=np.int64)


def test_closest_points_single_triangle_voronoi_regions():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    F = np.array([[0, 1, 2]])
    P = np.array([
        [-1, -1, 0],       # corner A
        [2, -1, 0],        # corner B
        [0.5, -1, 0],      # edge AB
        [-1, 2, 0],        # corner C
        [-1, 0.25, 0],     # edge AC
        [1, 1, 0],         # edge BC
        [0.25, 0.25, 3],   # face
    ])
    result = closest_points(V, F, P)
    expected = np.array([
        [1, 0, 0], [0, 1, 0], [0.5, 0.5, 0], [0, 0, 1], [0.75, 0, 0.25], [0, 0.5, 0.5],
        [0.5, 0.25, 0.25],
    ])
    np.testing.assert_array_equal(result.triangle, 0)
    np.testing.assert_allclose(result.barycentric, expected, atol=1e-15)
    np.testing.assert_allclose(result.distance, [2**0.5, 2**0.5, 1, 2**0.5, 1, 0.5**0.5, 3],
                               atol=1e-15)
    assert_consistent(result, V, F, P)


@pytest.mark.parametrize("k", [1, 4, 16])
def test_closest_points_matches_brute_force_on_icosphere(sphere, k):
    V, F = sphere
    rng = np.random.default_rng(11)
    direction = rng.normal(size=(600, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    # near the surface (both sides), inside, and far away
    radius = np.r_[rng.uniform(0.8, 1.2, 300), rng.uniform(0, 0.5, 100), rng.uniform(2, 20, 200)]
    P = direction * radius[:, None]
    result = closest_points(V, F, P, k=k)
    np.testing.assert_allclose(result.distance, brute_force_distance(V, F, P), rtol=0, atol=1e-12)
    assert_consistent(result, V, F, P)


def test_closest_points_on_vertices_edges_and_faces_have_zero_distance(sphere):
    V, F = sphere
    rng = np.random.default_rng(5)

    on_vertex = closest_points(V, F, V)
    np.testing.assert_allclose(on_vertex.distance, 0, atol=1e-15)
    corner = F[on_vertex.triangle] == np.arange(len(V))[:, None]      # (n,3) where v sits
    assert corner.sum(axis=1).tolist() == [1] * len(V)
    np.testing.assert_allclose(on_vertex.barycentric, corner, atol=1e-12)

    edge = F[rng.choice(len(F), 50, replace=False)][:, :2]             # (50,2) edges
    on_edge = closest_points(V, F, V[edge].mean(axis=1))
    np.testing.assert_allclose(on_edge.distance, 0, atol=1e-15)
    tri = F[on_edge.triangle]
    is_end = (tri[:, :, None] == edge[:, None, :]).any(axis=2)        # (50,3) corner on edge
    assert is_end.sum(axis=1).tolist() == [2] * 50
    np.testing.assert_allclose(on_edge.barycentric, 0.5 * is_end, atol=1e-12)

    face = rng.choice(len(F), 50, replace=False)
    bary = rng.dirichlet([3, 3, 3], 50)
    bary = (bary + 0.05) / 1.15                                        # every λ ≥ 0.04
    on_face = closest_points(V, F, np.einsum("qk,qkd->qd", bary, V[F[face]]))
    np.testing.assert_allclose(on_face.distance, 0, atol=1e-15)
    np.testing.assert_array_equal(on_face.triangle, face)
    np.testing.assert_allclose(on_face.barycentric, bary, atol=1e-12)


def test_closest_points_widens_past_the_nearest_centroid():
    # triangle 0 is long and thin (centroid far along it), triangle 1 small and nearby
    V = np.array([[0.0, 0, 0], [100, 0, 0], [0, 1, 0], [-0.5, 5, 0], [0.5, 5, 0], [0, 6, 0]])
    F = np.array([[0, 1, 2], [3, 4, 5]])
    P = np.array([[1.0, 0.5, 1.0]])
    assert cKDTree(V[F].mean(axis=1)).query(P, k=1)[1].tolist() == [1]
    result = closest_points(V, F, P, k=1)
    assert result.triangle.tolist() == [0]
    np.testing.assert_allclose(result.distance, [1.0], atol=1e-15)
    np.testing.assert_allclose(result.barycentric, [[0.49, 0.01, 0.5]], atol=1e-15)


def test_closest_points_widens_over_several_doublings():
    # a row of 40 small triangles along y = 3 and one long sliver along the x axis
    x = np.arange(40.0)
    small = np.stack([np.c_[x, 3 + 0 * x, 0 * x], np.c_[x + 0.5, 3 + 0 * x, 0 * x],
                      np.c_[x + 0.25, 3.5 + 0 * x, 0 * x]], axis=1).reshape(-1, 3)
    V = np.r_[small, [[0.0, 0, 0], [40, 0, 0], [40, 0.2, 0]]]
    F = np.r_[np.arange(120).reshape(40, 3), [[120, 121, 122]]]
    rng = np.random.default_rng(3)
    P = np.c_[rng.uniform(-2, 42, 200), rng.uniform(-1, 2, 200), rng.uniform(-1, 1, 200)]
    nearest_centroid = cKDTree(V[F].mean(axis=1)).query(P, k=1)[1]
    result = closest_points(V, F, P, k=1)
    assert (result.triangle == 40).sum() > 150 and (nearest_centroid == 40).sum() < 30
    np.testing.assert_allclose(result.distance, brute_force_distance(V, F, P), rtol=0, atol=1e-12)
    assert_consistent(result, V, F, P)


def test_closest_points_degenerate_triangles_give_no_nan():
    V = np.array([
        [0.0, 0, 0], [1, 0, 0], [0, 1, 0],       # a proper triangle
        [2, 0, 0], [3, 0, 0], [4, 0, 0],         # collinear
        [0, 0, 2], [0, 0, 2], [1, 1, 2],         # two corners coincide
        [5, 5, 5],                               # a single point
    ])
    F = np.array([[0, 1, 2], [3, 4, 5], [4, 5, 3], [6, 7, 8], [9, 9, 9]])
    rng = np.random.default_rng(9)
    P = rng.uniform(-1, 6, size=(300, 3))
    P[:3] = [[3.5, 0, 0], [0.5, 0.5, 2], [5, 5, 5]]                   # on each degenerate one
    with np.errstate(all="raise"):
        result = closest_points(V, F, P, k=2)
    assert_consistent(result, V, F, P)
    np.testing.assert_allclose(result.distance, brute_force_distance(V, F, P), rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.distance[:3], 0, atol=1e-15)
    assert result.triangle[0] in (1, 2) and result.triangle[1] == 3 and result.triangle[2] == 4


@pytest.mark.parametrize(
    "V, F, P, k, message",
    [
        (np.zeros((3, 2)), [[0, 1, 2]], np.zeros((1, 3)), 16, "vertices must have shape"),
        (np.eye(3), np.zeros((0, 3), int), np.zeros((1, 3)), 16, "m >= 1"),
        (np.eye(3), [[0, 1, 3]], np.zeros((1, 3)), 16, r"in \[0, 3\), got \[0, 3\]"),
        (np.eye(3), [[0, 1, 2]], np.zeros(3), 16, r"shape \(q,3\)"),
        (np.eye(3), [[0, 1, 2]], [[0, 0, 0], [0, np.nan, 0]], 16, "query point 1"),
        (np.eye(3), [[0, 1, 2]], np.zeros((1, 3)), 0, "k must be an integer >= 1"),
    ],
)
def test_closest_points_rejects_bad_input(V, F, P, k, message):
    with pytest.raises(ValueError, match=message):
        closest_points(V, F, P, k=k)


def test_closest_points_with_no_queries():
    result = closest_points(np.eye(3), [[0, 1, 2]], np.zeros((0, 3)))
    assert result.triangle.shape == (0,) and result.barycentric.shape == (0, 3)


# ---------------------------------------------------------------------------- marker layouts


def layout(*markers):
    """A MarkerLayout from (name, kind, value) tuples; value is the vertex, (triangle,
    barycentric) or the position."""
    M = len(markers)
    vertex, triangle = np.full(M, -1, np.int64), np.full(M, -1, np.int64)
    barycentric, position = np.full((M, 3), np.nan), np.full((M, 3), np.nan)
    for m, (_, kind, value) in enumerate(markers):
        if kind == "vertex":
            vertex[m] = value
        elif kind == "triangle":
            triangle[m], barycentric[m] = value
        else:
            position[m] = value
    return MarkerLayout(tuple(m[0] for m in markers), tuple(m[1] for m in markers),
                        vertex, triangle, barycentric, position)


def test_resolve_marker_layout_all_three_kinds(sphere):
    V, F = sphere
    on_surface = np.array([0.2, 0.3, 0.5]) @ V[F[17]]
    off_surface = 1.5 * V[40]
    markers = layout(
        ("FH1", "vertex", 40),
        ("FH2", "triangle", (99, [0.2, 0.3, 0.5])),
        ("FH3", "position", on_surface),
        ("FH4", "position", off_surface),
        ("FH5", "triangle", (3, [0.0, 0.0, 1.0 + 5e-5])),     # within the tolerance
    )
    triangle, barycentric = resolve_marker_layout(markers, V, F)
    assert triangle.dtype == np.int64 and barycentric.dtype == np.float64
    first = np.flatnonzero((F == 40).any(axis=1))[0]
    assert triangle[:3].tolist() == [first, 99, 17] and triangle[4] == 3
    np.testing.assert_array_equal(barycentric[0], F[first] == 40)
    np.testing.assert_array_equal(barycentric[1], [0.2, 0.3, 0.5])          # kept as given
    np.testing.assert_allclose(barycentric[2], [0.2, 0.3, 0.5], atol=1e-12)
    snapped = closest_points(V, F, off_surface[None])
    assert triangle[3] == snapped.triangle[0]
    np.testing.assert_array_equal(barycentric[3], snapped.barycentric[0])
    np.testing.assert_array_equal(barycentric[4], [0.0, 0.0, 1.0])   # renormalized (issue 16)


def test_resolve_marker_layout_snaps_positions_back_onto_the_rig(rig_mesh):
    # markers given in triangles of the real neutral, then as their positions: the snap
    # finds the same surface points (on a mesh whose largest triangle is 6x the median)
    V, F = rig_mesh
    rng = np.random.default_rng(2)
    M = 40
    triangle = rng.choice(len(F), M, replace=False)
    barycentric = rng.dirichlet([2, 2, 2], M)
    names = tuple(f"M{m}" for m in range(M))
    in_triangles = MarkerLayout(names, ("triangle",) * M, np.full(M, -1), triangle,
                                barycentric, np.full((M, 3), np.nan))
    resolved = resolve_marker_layout(in_triangles, V, F)
    np.testing.assert_array_equal(resolved[0], triangle)
    np.testing.assert_array_equal(resolved[1], barycentric)
    position = np.einsum("mk,mkd->md", barycentric, V[F[triangle]])
    as_positions = MarkerLayout(names, ("position",) * M, np.full(M, -1), np.full(M, -1),
                                np.full((M, 3), np.nan), position)
    snapped_triangle, snapped_barycentric = resolve_marker_layout(as_positions, V, F)
    snapped = np.einsum("mk,mkd->md", snapped_barycentric, V[F[snapped_triangle]])
    np.testing.assert_allclose(snapped, position, rtol=0, atol=1e-9)        # mm
    lifted = position + rng.normal(scale=3.0, size=(M, 3))
    np.testing.assert_allclose(closest_points(V, F, lifted).distance,
                               brute_force_distance(V, F, lifted), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "marker, message",
    [
        (("FH2", "triangle", (99999, [0.2, 0.3, 0.5])),
         "marker 'FH2': triangle 99999 out of range [0, 320)"),
        (("FH2", "triangle", (-1, [0.2, 0.3, 0.5])),
         "marker 'FH2': triangle -1 out of range [0, 320)"),
        (("BR1", "triangle", (5, [-0.1, 0.6, 0.5])),
         "marker 'BR1': barycentric [-0.1, 0.6, 0.5] (sum 1.0); expected 3 non-negative "
         "numbers summing to 1 within 0.0001"),
        (("BR1", "triangle", (5, [0.2, 0.3, 0.6])),
         "marker 'BR1': barycentric [0.2, 0.3, 0.6] (sum 1.1); expected"),
        (("BR1", "triangle", (5, [np.nan, 0.5, 0.5])), "marker 'BR1': barycentric [nan"),
        (("CH1", "vertex", 163), "marker 'CH1': vertex 163 out of range [0, 163)"),
        (("CH1", "vertex", -1), "marker 'CH1': vertex -1 out of range [0, 163)"),
        (("CH1", "vertex", 162),
         "marker 'CH1': vertex 162 is used by no triangle, expected a vertex of the surface"),
        (("NS1", "position", [0.0, np.inf, 0.0]),
         "marker 'NS1': position [0.0, inf, 0.0], expected 3 finite numbers"),
        (("NS1", "landmark", 3), "marker 'NS1': kind 'landmark', expected 'vertex', "
                                 "'triangle' or 'position'"),
    ],
)
def test_resolve_marker_layout_names_the_bad_marker(sphere, marker, message):
    V, F = sphere
    V = np.r_[V, [[9.0, 9.0, 9.0]]]               # vertex 162: used by no triangle
    markers = layout(("OK1", "vertex", 0), marker, ("OK2", "position", [0.0, 0.0, 2.0]))
    with pytest.raises(ValueError, match=re.escape(message)):
        resolve_marker_layout(markers, V, F)


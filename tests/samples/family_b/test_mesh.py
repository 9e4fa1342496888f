"""Family b's mesh operators: diagonal flip, red-green refinement, butterfly, reordering."""

import numpy as np
import pytest

from service.geometry.topology import edge_face_counts
from service.samples.family_b import mesh as M


def _grid(k=6):
    """A flat k×k quad grid in the xy-plane, quads stored as (a,b,c), (a,c,d) pairs."""
    x, y = np.meshgrid(np.arange(k + 1.0), np.arange(k + 1.0))
    V = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i = (np.arange(k)[:, None] * (k + 1) + np.arange(k)[None]).ravel()
    a, b, c, d = i, i + 1, i + k + 2, i + k + 1
    T = np.empty((2 * len(i), 3), np.int64)
    T[0::2], T[1::2] = np.stack([a, b, c], 1), np.stack([a, c, d], 1)
    return V, T


def test_flip_quad_diagonals_uses_the_other_diagonal():
    V, T = _grid(2)
    Fl = M.flip_quad_diagonals(T)
    quad = T[0::2][:, [0, 1, 2]].tolist()[0] + [T[1, 2]]          # a, b, c, d of quad 0
    assert sorted(Fl[0]) == sorted([quad[0], quad[1], quad[3]])
    assert sorted(Fl[1]) == sorted([quad[1], quad[2], quad[3]])
    n = lambda F: np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])[:, 2]
    assert np.all(np.sign(n(Fl)) == np.sign(n(T)))                   # orientation kept
    with pytest.raises(ValueError, match="quads"):
        M.flip_quad_diagonals(T[1:3])


def test_red_green_refinement_is_conforming_and_exact_on_affine_surfaces():
    V, T = _grid(6)
    F = M.flip_quad_diagonals(T)
    red = np.zeros(len(F), bool)
    red[[10, 11, 30]] = True
    region = np.zeros(len(V), np.int64)
    m = M.refine(F, len(V), F, len(V), region, red)
    E, count = edge_face_counts(m.faces)
    assert count.max() == 2                                          # no T-junctions: conforming
    Vf = m.S @ V
    area = 0.5 * np.cross(Vf[m.faces[:, 1]] - Vf[m.faces[:, 0]], Vf[m.faces[:, 2]] - Vf[m.faces[:, 0]])[:, 2]
    assert np.all(area > 0) and np.isclose(area.sum(), 36.0)         # same surface, same orientation
    # the boundary is 24 unit edges; it is split only where refined triangles touch it
    assert np.isclose(np.linalg.norm(Vf[E[count == 1, 0]] - Vf[E[count == 1, 1]], axis=1).sum(), 24.0)
    # butterfly rows sum to 1 (affine invariance) and keep the coarse vertices (interpolating)
    np.testing.assert_allclose(np.asarray(m.S.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    np.testing.assert_allclose(m.S[: len(V)].toarray(), np.eye(len(V)))
    bent = V.copy()
    bent[:, 2] = 0.3 * V[:, 0] - 0.2 * V[:, 1] + 1.0                # an affine height field
    np.testing.assert_allclose((m.S @ bent)[:, 2], 0.3 * Vf[:, 0] - 0.2 * Vf[:, 1] + 1.0, atol=1e-12)
    # a red triangle becomes 4, a green one (one split edge) 2
    closed, split, _, corner_edge = M.red_closure(F, red)
    green = (split[corner_edge].sum(axis=1) == 1) & ~closed
    assert closed.sum() >= 3 and green.sum() > 0
    assert len(m.faces) == len(F) + 3 * closed.sum() + green.sum()


def test_butterfly_reproduces_a_quadratic_inside_better_than_midpoints():
    V, T = _grid(8)
    F = M.flip_quad_diagonals(T)
    curved = V.copy()
    curved[:, 2] = 0.05 * (V[:, 0] - 4) ** 2
    m = M.refine(F, len(V), F, len(V), np.zeros(len(V), np.int64), np.ones(len(F), bool))
    P = m.S @ curved
    new = np.arange(len(V), len(P))
    inner = new[(P[new, 0] > 2) & (P[new, 0] < 6) & (P[new, 1] > 2) & (P[new, 1] < 6)]
    exact = 0.05 * (P[inner, 0] - 4) ** 2
    # the midpoint of an edge with Δx = 1 lies 0.05/4 = 0.0125 above the parabola
    assert np.abs(P[inner, 2] - exact).max() < 0.5 * 0.0125


def test_spatial_order_renumbers_everything_consistently():
    V, T = _grid(4)
    m = M.refine(T, len(V), T, len(V), np.arange(len(V)) % 3, np.ones(len(T), bool))
    Vf = m.S @ V
    order = M.spatial_order(Vf, cell=1.0)
    r = M.reorder(m, order)
    assert sorted(order) == list(range(len(Vf)))
    np.testing.assert_allclose(r.S @ V, Vf[order])
    np.testing.assert_array_equal(r.region, m.region[order])
    # the same triangles (as point sets), in a new numbering
    tri = lambda X, F: {tuple(sorted(map(tuple, X[f].round(9)))) for f in F}
    assert tri(r.S @ V, r.faces) == tri(Vf, m.faces)
    assert not np.array_equal(order[: len(V)], np.arange(len(V)))      # rig vertices are not first

"""Marker placement on the sample actor: count, spacing, clearances, surface points."""

from __future__ import annotations

import io

import numpy as np
from scipy.spatial import cKDTree

from service.io.markers import read_marker_layout, write_marker_layout
from service.samples.markers import (EYELID_CLEARANCE_MM, INNER_LIP_CLEARANCE_MM, hole_loops,
                                     place_markers)


def test_markers_are_evenly_spread_surface_points_clear_of_eyes_and_lips(actor0):
    skin, layout = actor0.skin, actor0.markers
    V, F = skin.neutral, skin.faces
    assert len(layout.names) == 150 and len(set(layout.names)) == 150
    np.testing.assert_allclose(layout.barycentric.sum(axis=1), 1.0, atol=1e-12)
    assert layout.barycentric.min() >= 0
    # each marker's handle vertex is a corner of its triangle
    assert np.all((F[layout.triangle] == layout.vertex[:, None]).any(axis=1))
    P = layout.positions(V, F)
    # even spacing: nearest-neighbour distances within a factor ~2 of each other
    d, _ = cKDTree(P).query(P, k=2)
    nn = d[:, 1]
    assert nn.min() > 0.45 * np.median(nn) and nn.max() < 2.0 * np.median(nn)
    assert 8.0 < np.median(nn) < 16.0                     # mm, a typical face layout
    # clearances from the openings, measured to the opening's boundary loop (less the
    # half-triangle a marker may sit away from its vertex)
    lm = skin.rig_neutral[actor0.rig.landmarks68]
    loops = hole_loops(V, F)
    trees = [cKDTree(V[loop]) for loop in loops]
    slack = 1.5
    for points, clearance in ((lm[36:48], EYELID_CLEARANCE_MM), (lm[60:68], INNER_LIP_CLEARANCE_MM)):
        for p in points:
            tree = trees[int(np.argmin([t.query(p)[0] for t in trees]))]
            assert tree.query(P)[0].min() > clearance - slack


def test_marker_placement_is_seeded(actor0):
    skin = actor0.skin
    lm = skin.rig_neutral[actor0.rig.landmarks68]
    args = (skin.neutral, skin.faces, skin.region == 0, lm[36:48], lm[60:68], 40)
    a, b, c = place_markers(*args, seed=1), place_markers(*args, seed=1), place_markers(*args, seed=2)
    np.testing.assert_array_equal(a.triangle, b.triangle)
    np.testing.assert_array_equal(a.barycentric, b.barycentric)
    assert not np.array_equal(a.triangle, c.triangle)


def test_marker_layout_round_trips_through_the_api_json(actor0):
    layout = actor0.markers
    buf = io.BytesIO()
    write_marker_layout(buf, layout.to_layout())
    back = read_marker_layout(buf.getvalue(), triangle_count=len(actor0.skin.faces))
    assert back.names == layout.names and set(back.kinds) == {"triangle"}
    np.testing.assert_array_equal(back.triangle, layout.triangle)
    np.testing.assert_array_equal(back.barycentric, layout.barycentric)

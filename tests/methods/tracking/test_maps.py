"""Blended per-frame maps (fyffe §7.3) from per-vertex scan weights."""

from __future__ import annotations

import numpy as np

from service.methods.tracking.maps import blend_maps


def test_blend_maps_mixes_the_scans_maps_by_the_vertex_weights():
    # one quad covering the UV square, two scans with constant maps 1 and 3
    F = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    maps = np.stack([np.full((8, 8), 1.0), np.full((8, 8), 3.0)])
    W = np.zeros((2, 4, 2))
    W[0, :, 0] = 1.0                       # frame 0: all scan 0
    W[1, :] = [0.25, 0.75]                 # frame 1: 1/4 · 1 + 3/4 · 3 = 2.5
    out = blend_maps(W, F, uv, F, maps)
    assert out.shape == (2, 8, 8)
    np.testing.assert_allclose(out[0], 1.0, atol=1e-6)
    np.testing.assert_allclose(out[1], 2.5, atol=1e-6)
    # weights varying over the mesh blend per texel: left edge scan 0, right edge scan 1
    W2 = np.array([[[1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [1.0, 0.0]]])
    row = blend_maps(W2, F, uv, F, maps)[0, 4]
    assert row[0] < 1.3 and row[-1] > 2.7 and np.all(np.diff(row) > 0)

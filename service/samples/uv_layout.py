"""Repacking the rig's two UDIM tiles into the single [0,1]² tile of API.md's maps.

The ICT rig's UVs put the face in u∈[0,1) and the head & neck in u∈[1,2). Maps in
facesynth live in one [0,1]² tile, so the charts are moved by per-chart affine maps
(uniform scale + offset: texel aspect and chart shape are kept):

    face tile (narrow face + rest of face)   scale 0.80 → [0.00, 0.80] × [0.20, 1.00]
    neck chart (bottom strip of tile 2)       → fitted into [0.00, 1.00] × [0.00, 0.20]
    head chart and both ears                  → fitted into [0.80, 1.00] × [0.20, 1.00]

so the face gets about 60 % of all texels (it gets ~4 texels for every one the back of
the head gets, per mm²), which is where detail lives.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components

from service.geometry.topology import adjacency_matrix

GUTTER = 0.008  # uv units kept free around each packed group (≈ 8 texels at 1024²)


def _fit(uv: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """Uniformly scale and translate points (k,2) into box (u0, v0, u1, v1), centred."""
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    u0, v0, u1, v1 = box[0] + GUTTER, box[1] + GUTTER, box[2] - GUTTER, box[3] - GUTTER
    s = min((u1 - u0) / (hi[0] - lo[0]), (v1 - v0) / (hi[1] - lo[1]))
    centre_box = np.array([(u0 + u1) / 2, (v0 + v1) / 2])
    return (uv - (lo + hi) / 2) * s + centre_box


def repack_ict_uv(uv: np.ndarray, uv_faces: np.ndarray) -> np.ndarray:
    """Move the rig's UDIM charts into [0,1]² (see module docstring).

    Parameters
    ----------
    uv : (K,2) float        UV coordinates spanning u∈[0,2)
    uv_faces : (m,3) int    per-corner indices into uv

    Returns
    -------
    uv01 : (K,2) float      the same UV vertices, repacked into [0,1]², topology unchanged
    """
    uv = np.asarray(uv, dtype=np.float64)
    _, chart = connected_components(adjacency_matrix(uv_faces, len(uv)), directed=False)
    in_face_tile = uv[:, 0] < 1.0
    out = np.empty_like(uv)
    out[in_face_tile] = uv[in_face_tile] * 0.80 + np.array([0.0, 0.20])
    head = ~in_face_tile
    # the neck is the chart of tile 2 that reaches the bottom of the tile
    tile2_charts = np.unique(chart[head])
    lowest = {c: uv[chart == c, 1].min() for c in tile2_charts}
    neck_chart = min(lowest, key=lowest.get)
    neck = head & (chart == neck_chart)
    rest = head & ~neck
    out[neck] = _fit(uv[neck], (0.0, 0.0, 1.0, 0.20))
    out[rest] = _fit(uv[rest], (0.80, 0.20, 1.0, 1.0))
    return out

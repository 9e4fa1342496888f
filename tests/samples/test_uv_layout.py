"""The rig's two UDIM tiles repacked into [0,1]²: inside, no overlaps, shapes kept."""

from __future__ import annotations

import numpy as np

from service.geometry.uv_raster import rasterize_uv
from service.samples.uv_layout import repack_ict_uv


def _signed_areas(uv, UF):
    e1, e2 = uv[UF[:, 1]] - uv[UF[:, 0]], uv[UF[:, 2]] - uv[UF[:, 0]]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def test_repack_fits_the_unit_tile_without_overlap(rig):
    uv = repack_ict_uv(rig.uv, rig.triangle_uv)
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    UF = rig.triangle_uv
    area = _signed_areas(uv, UF)
    # charts keep their orientation (a uniform scale + offset never flips a triangle)
    np.testing.assert_array_equal(np.sign(area), np.sign(_signed_areas(rig.uv, UF)))
    # no overlap: rasterized coverage equals the summed triangle areas (to border texels)
    R = 512
    covered = rasterize_uv(uv, UF, R, R).mask.sum() / R ** 2
    np.testing.assert_allclose(covered, np.abs(area).sum(), rtol=0.01)


def test_repack_is_a_per_chart_similarity_and_favours_the_face(rig):
    uv0, UF = rig.uv, rig.triangle_uv
    uv = repack_ict_uv(uv0, UF)
    face = uv0[:, 0] < 1.0
    # the face tile is scaled by exactly 0.8 and lifted by 0.2
    np.testing.assert_allclose(uv[face], uv0[face] * 0.8 + [0.0, 0.2], atol=1e-12)
    # every triangle keeps its shape: area ratio uniform within a chart group
    ratio = np.abs(_signed_areas(uv, UF)) / np.maximum(np.abs(_signed_areas(uv0, UF)), 1e-15)
    tri_face = face[UF].all(axis=1)
    np.testing.assert_allclose(ratio[tri_face], 0.64, rtol=1e-9)
    # the face tile gets most of the texels
    area = np.abs(_signed_areas(uv, UF))
    assert area[tri_face].sum() / area.sum() > 0.55

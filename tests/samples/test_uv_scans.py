"""Tests for service.samples.uv_scans: scans as UV maps with their known correspondence."""

import numpy as np
import pytest

from service.geometry import optical_flow as of
from service.geometry.uv_raster import uv_to_texel
from service.samples.uv_scans import build_uv_scans, mm_per_texel


@pytest.fixture(scope="module")
def scans(pdm_actor_dir):
    return build_uv_scans(pdm_actor_dir, resolution=256, expressions=["train_smile"], seed=0)


def interior_vertices(S, scan, valid):
    """Face vertices whose texel in the target is valid (visible in both scans)."""
    face = np.flatnonzero(np.isfinite(scan.layout).all(axis=1))
    xy = uv_to_texel(S.target.layout[face], S.resolution, S.resolution)
    r, c = np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)
    return face[valid[r, c]], xy[valid[r, c]]


def test_every_scan_has_its_own_layout_in_the_unit_tile(scans):
    S = scans
    src, tgt = S.sources[0], S.target
    face = np.isfinite(tgt.layout).all(axis=1)
    assert np.array_equal(face, np.isfinite(src.layout).all(axis=1))
    assert 0 < tgt.layout[face].min() and tgt.layout[face].max() < 1
    moved = np.linalg.norm(src.layout[face] - tgt.layout[face], axis=1) * S.resolution
    assert np.median(moved) > 0.5 and moved.max() > 5                # texels
    assert src.maps["albedo"].shape == (256, 256, 3) and src.maps["position"].dtype == np.float32
    assert 0.3 < tgt.mask.mean() < 0.8 and np.all(src.maps["albedo"][~src.mask] == 0)


def test_truth_carries_each_vertex_to_its_place_in_the_source(scans):
    S = scans
    truth, valid = S.truth(0)
    assert valid.mean() > 0.3 and np.isnan(truth[~S.target.mask]).all()
    v, xy = interior_vertices(S, S.sources[0], valid)
    found = of.sample(np.nan_to_num(truth), xy)                       # bilinear in the target grid
    expect = uv_to_texel(S.sources[0].layout[v], S.resolution, S.resolution)
    err = np.linalg.norm(found - expect, axis=1)
    assert np.median(err) < 0.02 and np.percentile(err, 90) < 0.1
    # the position maps hold the scans' head-frame vertices
    pos = of.sample(S.target.maps["position"], xy)
    # (bilinear lookup between texel centres of a curved surface at 1.1 mm texels: 0.024 mm median)
    off = np.linalg.norm(pos - S.target.vertices[v], axis=1)
    assert np.median(off) < 0.05 and np.percentile(off, 90) < 0.3


def test_clicks_are_off_by_the_click_noise(scans):
    S = scans
    xy = uv_to_texel(S.target_landmarks[0], S.resolution, S.resolution)
    clicked = of.sample(S.target.maps["position"], xy)
    off = np.linalg.norm(clicked - S.target.vertices[S.landmark_vertices], axis=1)
    assert 0.15 < np.median(off) < 0.7                 # σ = 0.3 mm per axis: median 0.35 mm
    assert 0.9 < mm_per_texel(S.target) < 1.4          # 256² over a ~250 mm wide face
    assert len(np.unique(S.landmark_vertices)) == len(S.landmark_vertices) == 32


def test_scans_are_seeded(pdm_actor_dir):
    a = build_uv_scans(pdm_actor_dir, resolution=64, expressions=["train_pucker"], landmarks=8, seed=4)
    b = build_uv_scans(pdm_actor_dir, resolution=64, expressions=["train_pucker"], landmarks=8, seed=4)
    c = build_uv_scans(pdm_actor_dir, resolution=64, expressions=["train_pucker"], landmarks=8, seed=5)
    np.testing.assert_array_equal(a.sources[0].maps["albedo"], b.sources[0].maps["albedo"])
    np.testing.assert_array_equal(a.source_landmarks[0], b.source_landmarks[0])
    assert not np.allclose(a.target.layout[a.landmark_vertices], c.target.layout[a.landmark_vertices])
    with pytest.raises(ValueError, match="no expression"):
        build_uv_scans(pdm_actor_dir, resolution=64, expressions=[])

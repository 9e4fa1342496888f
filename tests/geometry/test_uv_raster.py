"""Tests for service.geometry.uv_raster: UV rasterization and vertex <-> map transfer."""

from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from service.geometry import scan_convert, uv_raster
from service.geometry.topology import edge_face_counts
from service.geometry.uv_raster import (
    dilate,
    interpolate,
    interpolation_matrix,
    map_to_vertices,
    rasterize_uv,
    sample_map,
    splat,
    texel_centers_uv,
)

RIG = Path(__file__).resolve().parents[2] / "service" / "samples" / "data" / "ict_face_rig.npz"

# the unit square as two triangles sharing the diagonal (0,0)-(1,1)
SQUARE_UV = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


@pytest.fixture(scope="module")
def rig_layout():
    """The ICT rig's UVs with both UDIM tiles squeezed into the unit tile (u/2)."""
    d = np.load(RIG)
    uv = d["uv"].astype(np.float64) * [0.5, 1.0]
    return uv, d["triangle_uv"].astype(np.int64), d["triangles"].astype(np.int64), len(d["neutral"])


def test_rasterize_single_triangle_covers_lower_left_half_with_diagonal():
    # uv (0,0),(1,0),(0,1): texel (r,c) centre is inside iff u + v <= 1  <=>  c <= r
    r = rasterize_uv(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), np.array([[0, 1, 2]]), 4, 4)
    rows, cols = np.indices((4, 4))
    np.testing.assert_array_equal(r.mask, cols <= rows)
    assert r.mask.sum() == 10
    np.testing.assert_array_equal(r.triangle[r.mask], 0)
    np.testing.assert_array_equal(r.triangle[~r.mask], -1)
    # texel (3,0): uv = (1/8, 1/8) -> barycentrics (3/4, 1/8, 1/8)
    np.testing.assert_allclose(r.barycentric[3, 0], [0.75, 0.125, 0.125], rtol=0, atol=1e-15)


def test_rasterize_shared_edge_texels_go_to_exactly_one_triangle():
    H = W = 8                                  # the diagonal passes through 8 texel centres
    r = rasterize_uv(SQUARE_UV, SQUARE_F, H, W)
    assert r.mask.all()
    counts = np.bincount(r.triangle.ravel(), minlength=2)
    assert counts.sum() == H * W              # each texel exactly once
    # 28 texels strictly on each side, the 8 diagonal ones split between the two
    assert counts.min() >= (H * W - H) // 2
    # off-diagonal texels go to the triangle that contains them
    rows, cols = np.indices((H, W))
    u = (cols + 0.5) / W
    v = 1 - (rows + 0.5) / H
    np.testing.assert_array_equal(r.triangle[u > v + 1e-9], 0)
    np.testing.assert_array_equal(r.triangle[v > u + 1e-9], 1)
    # deterministic: same answer again, and independent of the chunking
    again = rasterize_uv(SQUARE_UV, SQUARE_F, H, W)
    np.testing.assert_array_equal(again.triangle, r.triangle)


def test_rasterize_rig_barycentrics_reproduce_texel_centres(rig_layout):
    uv, UF, _, _ = rig_layout
    H, W = 256, 384                            # non-square on purpose
    r = rasterize_uv(uv, UF, H, W)
    lam = r.barycentric[r.mask]
    np.testing.assert_allclose(lam.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert lam.min() >= -uv_raster.BARY_TOL
    np.testing.assert_array_equal(r.barycentric[~r.mask], 0.0)
    # interpolating the UVs themselves (per-corner values, through uv_faces) gives the centres
    rec = interpolate(r, uv, UF)
    np.testing.assert_allclose(rec[r.mask], texel_centers_uv(H, W)[r.mask], rtol=0, atol=1e-12)


def test_rasterize_rig_coverage_matches_uv_area_and_is_chunk_independent(rig_layout, monkeypatch):
    uv, UF, _, _ = rig_layout
    R = 256
    r = rasterize_uv(uv, UF, R, R)
    P = uv[UF] * R
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()   # texels
    E, count = edge_face_counts(UF)
    Eb = E[count == 1]
    perimeter = np.linalg.norm((uv[Eb[:, 0]] - uv[Eb[:, 1]]) * R, axis=1).sum()
    # the rig's charts do not overlap, so the texel-centre count is the area up to the texels
    # straddling chart borders; a quarter texel per texel of border is a loose bound
    # (measured: |count - area| = 0.03 * perimeter at 256², 0.007 at 512²)
    assert abs(r.mask.sum() - area) < 0.25 * perimeter
    assert abs(r.mask.sum() / area - 1) < 0.01
    # tiny chunks: ties are resolved across chunk boundaries the same way
    monkeypatch.setattr(scan_convert, "CHUNK_PIXELS", 997)
    small = rasterize_uv(uv, UF, R, R)
    np.testing.assert_array_equal(small.triangle, r.triangle)
    np.testing.assert_array_equal(small.barycentric, r.barycentric)


def test_rasterize_clips_uvs_outside_the_unit_tile():
    uv = SQUARE_UV + [1.0, 0.0]                # the second UDIM tile: nothing in [0,1]²
    r = rasterize_uv(uv, SQUARE_F, 16, 16)
    assert not r.mask.any()
    half = rasterize_uv(SQUARE_UV + [0.5, 0.0], SQUARE_F, 16, 16)
    assert half.mask.sum() == 16 * 8          # the left half of the square is in the tile


def test_interpolate_uses_position_faces_across_a_seam():
    # two triangles of one quad, the second with its own copies of the UVs (a seam):
    # per-vertex values travel through the position faces, not the UV indices
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    UF = np.array([[0, 1, 2], [3, 4, 5]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    vals = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0], [4.0, 40.0]])
    r = rasterize_uv(uv, UF, 32, 32)
    m = interpolate(r, vals, F)
    assert m.shape == (32, 32, 2)
    # triangle 0: values 1, 2, 3 at uv (0,0), (1,0), (1,1), so channel 0 is 1 + u + v
    u, v = texel_centers_uv(32, 32)[20, 25]
    assert u > v
    np.testing.assert_allclose(m[20, 25, 0], 1 + u + v, rtol=0, atol=1e-12)
    # triangle 1: channel 1 is 10, 30, 40 at uv (0,0), (1,1), (0,1), so 10 (1 - u + 3v)
    u, v = texel_centers_uv(32, 32)[25, 3]
    assert v > u
    np.testing.assert_allclose(m[25, 3, 1], 10 * (1 + 3 * v - u), rtol=0, atol=1e-11)
    np.testing.assert_array_equal(interpolate(r, vals[:, 0], F), m[..., 0])


def test_sample_map_of_linear_ramp_is_exact():
    H, W = 37, 53
    uvc = texel_centers_uv(H, W)
    ramp = np.stack([3.0 * uvc[..., 0] - 2.0 * uvc[..., 1] + 0.5, uvc[..., 1]], axis=-1)
    rng = np.random.default_rng(3)
    q = np.c_[rng.uniform(0.5 / W, 1 - 0.5 / W, 500), rng.uniform(0.5 / H, 1 - 0.5 / H, 500)]
    out = sample_map(ramp, q)
    np.testing.assert_allclose(out[:, 0], 3.0 * q[:, 0] - 2.0 * q[:, 1] + 0.5, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], q[:, 1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sample_map(ramp[..., 0], q), out[:, 0], rtol=0, atol=0)
    # texel centres sample their own texel; the top-left texel is row 0, v near 1
    np.testing.assert_allclose(sample_map(ramp, uvc.reshape(-1, 2)), ramp.reshape(-1, 2),
                               rtol=0, atol=1e-12)
    img = np.zeros((H, W))
    img[0, 0] = 1.0
    assert sample_map(img, np.array([[0.5 / W, 1 - 0.5 / H]]))[0] == 1.0
    # clamped at the edges: beyond the outermost centres the edge value holds
    edge = sample_map(ramp, np.array([[0.0, 0.5], [1.0, 0.5], [-3.0, 7.0]]))
    np.testing.assert_allclose(edge, sample_map(ramp, np.array(
        [[0.5 / W, 0.5], [1 - 0.5 / W, 0.5], [0.5 / W, 1 - 0.5 / H]])), rtol=0, atol=1e-14)


def test_map_to_vertices_averages_uv_corners_across_a_seam():
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.9, 0.9], [0.2, 0.3], [0.8, 0.7], [0.1, 0.9]])
    UF = np.array([[0, 1, 2], [3, 4, 5]])
    F = np.array([[0, 1, 2], [0, 2, 3]])       # vertices 0 and 2 are on the seam
    H = W = 64
    uvc = texel_centers_uv(H, W)
    img = np.stack([uvc[..., 0], 5.0 * uvc[..., 1]], axis=-1)
    x = map_to_vertices(img, uv, UF, F, 5)
    expect = np.array([
        (uv[0] + uv[3]) / 2, uv[1], (uv[2] + uv[4]) / 2, uv[5],
    ]) * [1.0, 5.0]
    np.testing.assert_allclose(x[:4], expect, rtol=0, atol=1e-12)
    assert np.isnan(x[4]).all()                # vertex 4 is used by no triangle
    np.testing.assert_allclose(map_to_vertices(img[..., 0], uv, UF, F, 5)[:4], expect[:, 0],
                               rtol=0, atol=1e-12)


def test_splat_is_the_normalized_adjoint_of_interpolate(rig_layout):
    uv, UF, F, n = rig_layout
    r = rasterize_uv(uv, UF, 256, 256)
    # a constant map splats to the constant on every vertex touched by a texel
    x = splat(r, np.full((256, 256, 2), 4.25), F, n)
    touched = ~np.isnan(x[:, 0])
    assert touched.mean() > 0.9
    np.testing.assert_allclose(x[touched], 4.25, rtol=0, atol=1e-12)
    # identity with the sparse operator: x = Pᵀ y / Pᵀ 1
    rng = np.random.default_rng(0)
    y = rng.standard_normal((256, 256))
    P = interpolation_matrix(r, F, n)
    num = P.T @ y.ravel()
    den = P.T @ np.ones(256 * 256)
    np.testing.assert_allclose(splat(r, y, F, n)[touched], num[touched] / den[touched], rtol=1e-12,
                               atol=1e-12)
    # and P is interpolate as a matrix
    vals = rng.standard_normal(n)
    np.testing.assert_allclose((P @ vals).reshape(256, 256), interpolate(r, vals, F),
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(r.splat(y, F, n, fill=-1.0)[~touched], -1.0)


def test_dilate_grows_like_binary_dilation_and_keeps_covered_values():
    H, W = 40, 50
    rows, cols = np.indices((H, W))
    mask = (rows - 20) ** 2 + (cols - 22) ** 2 < 81
    img = np.where(mask, 2.0 * rows + cols, 0.0)
    out, grown = dilate(img, mask, 3, return_mask=True)
    np.testing.assert_array_equal(grown, binary_dilation(mask, np.ones((3, 3)), iterations=3))
    np.testing.assert_array_equal(out[mask], img[mask])
    np.testing.assert_array_equal(out[~grown], 0.0)
    # a constant chart stays constant when padded, for vector maps too
    const, grown2 = dilate(np.where(mask[..., None], [1.5, -2.0], 0.0), mask, 2,
                           return_mask=True)
    np.testing.assert_allclose(const[grown2], np.broadcast_to([1.5, -2.0], (grown2.sum(), 2)),
                               rtol=0, atol=1e-15)
    # a ring texel takes the mean of its covered neighbours
    i, j = 20, 31                              # right of the disc, touches (19..21, 30)
    assert not mask[i, j] and mask[i - 1:i + 2, j - 1].all() and not mask[i - 1:i + 2, j].any()
    np.testing.assert_allclose(out[i, j], np.mean(img[i - 1:i + 2, j - 1]), rtol=0, atol=1e-12)


def test_sampling_matrix_equals_map_to_vertices_inside_and_reads_only_covered_texels():
    # two charts side by side, the right one mirrored: a seam vertex samples both
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    uv = np.array([[0.05, 0.05], [0.45, 0.05], [0.45, 0.95], [0.05, 0.95],
                   [0.55, 0.05], [0.95, 0.05], [0.95, 0.95], [0.55, 0.95]])
    UF = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    H, W = 16, 16
    raster = uv_raster.rasterize_uv(uv, UF, H, W)
    S = uv_raster.sampling_matrix(uv, UF, F, len(V), raster.mask)
    np.testing.assert_allclose(np.asarray(S.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert raster.mask.ravel()[S.indices].all()               # never reads an empty texel
    # an affine map is reproduced at vertices whose footprint is covered; the seam vertex 1
    # averages its two UVs exactly like map_to_vertices on the dilated map
    img = 3.0 + uv_raster.texel_centers_uv(H, W) @ np.array([2.0, -1.0])
    dil = uv_raster.dilate(img, raster.mask, 2)
    ref = uv_raster.map_to_vertices(dil, uv, UF, F, len(V))
    got = S @ np.where(raster.mask, img, 0.0).ravel()
    np.testing.assert_allclose(got, ref, atol=0.35)   # dilation extrapolates, S renormalizes
    expect = 3.0 + uv @ np.array([2.0, -1.0])
    np.testing.assert_allclose(got[0], expect[0], atol=0.2)
    np.testing.assert_allclose(got[1], 0.5 * (expect[1] + expect[4]), atol=0.2)

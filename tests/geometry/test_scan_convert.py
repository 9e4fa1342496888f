"""2D scan conversion: exact pixel-centre coverage with barycentrics."""

from __future__ import annotations

import numpy as np

from service.geometry import scan_convert as sc
from service.geometry.scan_convert import barycentric_2d, scan_convert


def _brute_force(P, H, W):
    ys, xs = np.mgrid[0:H, 0:W]
    pix = []
    for t, tri in enumerate(P):
        with np.errstate(divide="ignore", invalid="ignore"):      # the degenerate triangle
            lam = barycentric_2d(np.repeat(tri[None], H * W, 0), xs.ravel().astype(float),
                                 ys.ravel().astype(float))
        inside = lam.min(axis=1) >= -sc.BARY_TOL
        pix += [(p, t) for p in np.flatnonzero(inside)]
    return sorted(pix)


def test_scan_convert_matches_a_brute_force_test_of_every_pixel():
    rng = np.random.default_rng(7)
    H, W = 23, 31
    P = rng.uniform([-3, -3], [W + 2, H + 2], size=(40, 3, 2))
    P[:5] = rng.uniform(0, 6, size=(5, 3, 2))         # small ones too
    P[5] = [[1, 1], [4, 4], [7, 7]]                    # degenerate: covers nothing
    cover = scan_convert(P, H, W)
    assert sorted(zip(cover.pixel.tolist(), cover.triangle.tolist())) == _brute_force(P, H, W)
    np.testing.assert_allclose(cover.barycentric.sum(axis=1), 1.0, atol=1e-12)
    # the barycentrics reproduce the pixel centres
    xy = np.einsum("pk,pkd->pd", cover.barycentric, P[cover.triangle])
    np.testing.assert_allclose(xy, np.column_stack([cover.pixel % W, cover.pixel // W]), atol=1e-9)


def test_scan_convert_is_independent_of_chunking(monkeypatch):
    rng = np.random.default_rng(3)
    P = rng.uniform(0, 50, size=(60, 3, 2))
    whole = scan_convert(P, 50, 50)
    monkeypatch.setattr(sc, "CHUNK_PIXELS", 37)
    parts = scan_convert(P, 50, 50)
    np.testing.assert_array_equal(parts.pixel, whole.pixel)
    np.testing.assert_array_equal(parts.triangle, whole.triangle)
    np.testing.assert_array_equal(parts.barycentric, whole.barycentric)


def test_a_shared_edge_leaves_no_crack():
    # a square split along its diagonal covers every pixel centre in it at least once
    P = np.array([[[0.2, 0.2], [9.7, 0.2], [9.7, 9.7]], [[0.2, 0.2], [9.7, 9.7], [0.2, 9.7]]])
    cover = scan_convert(P, 12, 12)
    assert set(cover.pixel.tolist()) == {y * 12 + x for y in range(1, 10) for x in range(1, 10)}

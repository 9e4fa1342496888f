"""Scan conversion of 2D triangles: every pixel centre each triangle covers, vectorized.

Shared by the UV rasterizer (:mod:`service.geometry.uv_raster`, which resolves overlaps by
how far inside a texel centre lies) and the z-buffer renderer (:mod:`service.samples.render`,
which resolves them by depth). Pixel centres sit on integer coordinates ``(x, y)`` =
(column, row); callers shift their own convention onto that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A pixel centre belongs to a triangle when its smallest barycentric coordinate is
#: ``>= -BARY_TOL``: the slack closes cracks that floating-point rounding would open along
#: shared edges; callers then resolve overlaps so that every pixel goes to one triangle.
BARY_TOL = 1e-10

#: Candidate pixels processed per vectorized chunk (bounds the temporaries).
CHUNK_PIXELS = 1 << 22


@dataclass(frozen=True)
class Coverage:
    """All (pixel, triangle) pairs with the pixel centre inside the triangle.

    pixel : (N,) int64          flat index ``y W + x``
    triangle : (N,) int64       triangle index
    barycentric : (N,3) float64 coordinates of the pixel centre, summing to 1, ≥ -BARY_TOL
    """

    pixel: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray

    @property
    def score(self) -> np.ndarray:
        """(N,) smallest barycentric coordinate: how far inside its triangle a centre is."""
        return self.barycentric.min(axis=1)


def barycentric_2d(P: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N,3) of points (px, py) in triangles P (N,3,2), Cramer's rule.

    ``λ1, λ2`` from the 2×2 system on the edges from corner 0, ``λ0 = 1 - λ1 - λ2`` so the
    three sum to one up to rounding; works for either orientation (signed area).
    """
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    dx = px - P[:, 0, 0]
    dy = py - P[:, 0, 1]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    l1 = (dx * e2[:, 1] - dy * e2[:, 0]) / det
    l2 = (e1[:, 0] * dy - e1[:, 1] * dx) / det
    return np.stack([1.0 - l1 - l2, l1, l2], axis=1)


def scan_convert(P: np.ndarray, H: int, W: int) -> Coverage:
    """Every pixel centre of an H×W grid inside each triangle P (m,3,2), in triangle order.

    Each triangle's bounding box is split into pixel rows; a row's column span inside the
    triangle is solved for from the (affine) barycentric coordinates, the spans are
    expanded into candidate pixels (in chunks of about ``CHUNK_PIXELS``) and tested exactly.
    No Python loop over triangles or pixels. Degenerate and non-finite triangles cover
    nothing; both orientations are accepted.

    Parameters
    ----------
    P : (m,3,2) float   corner coordinates (x = column, y = row; pixel centres on integers)
    H, W : int          grid height and width

    Returns
    -------
    Coverage
    """
    P = np.asarray(P, dtype=np.float64)
    lo = np.maximum(np.ceil(P.min(axis=1)), 0)                # first pixel centre in bbox
    hi = np.minimum(np.floor(P.max(axis=1)), [W - 1, H - 1])
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    with np.errstate(invalid="ignore"):
        live = (hi >= lo).all(axis=1) & (det != 0) & np.isfinite(det)
    tri_ids = np.flatnonzero(live)
    lo, hi = lo[tri_ids].astype(np.int64), hi[tri_ids].astype(np.int64)
    P, e1, e2, det = P[tri_ids], e1[tri_ids], e2[tri_ids], det[tri_ids]
    bw, bh = (hi - lo + 1).T
    # barycentrics are affine: λ(x,y) = λ(lo) + (x-lo_x) gx + (y-lo_y) gy
    lam0 = barycentric_2d(P, lo[:, 0].astype(np.float64), lo[:, 1].astype(np.float64))
    g1 = np.stack([e2[:, 1], -e2[:, 0]], axis=1) / det[:, None]        # ∇λ1
    g2 = np.stack([-e1[:, 1], e1[:, 0]], axis=1) / det[:, None]        # ∇λ2
    g0 = -g1 - g2
    gx = np.stack([g0[:, 0], g1[:, 0], g2[:, 0]], axis=1)             # (m,3) ∂λ/∂x
    gy = np.stack([g0[:, 1], g1[:, 1], g2[:, 1]], axis=1)             # (m,3) ∂λ/∂y

    # scan lines: one per (triangle, pixel row of its bbox), with the column span where all
    # λ >= -span_tol (looser than BARY_TOL, so rounding never drops a pixel the exact test
    # below would accept)
    row_tri = np.repeat(np.arange(len(tri_ids)), bh)
    row_j = np.arange(len(row_tri)) - np.repeat(np.cumsum(bh) - bh, bh)
    base = lam0[row_tri] + row_j[:, None] * gy[row_tri]               # λ at x = lo_x
    rgx = gx[row_tri]
    span_tol = 10 * BARY_TOL
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = (-span_tol - base) / rgx                               # λ_k = -tol at offset
    s_lo = np.max(np.where(rgx > 0, bound, -np.inf), axis=1)
    s_hi = np.min(np.where(rgx < 0, bound, np.inf), axis=1)
    empty = np.any((rgx == 0) & (base < -span_tol), axis=1)
    width = bw[row_tri]
    s_lo = np.maximum(np.ceil(np.maximum(s_lo, -1.0)), 0).astype(np.int64)
    s_hi = np.minimum(np.floor(np.minimum(s_hi, width)), width - 1).astype(np.int64)
    cnt_all = np.where(empty, 0, np.maximum(s_hi - s_lo + 1, 0))
    rows = np.flatnonzero(cnt_all)
    counts = cnt_all[rows]

    pixel, triangle, bary = [], [], []
    csum = np.cumsum(counts)
    cuts = np.searchsorted(csum, np.arange(CHUNK_PIXELS, csum[-1] if len(csum) else 0,
                                           CHUNK_PIXELS), side="right")
    bounds = np.unique(np.r_[0, cuts, len(rows)])
    for a, b in zip(bounds[:-1], bounds[1:]):
        cnt = counts[a:b]
        rid = np.repeat(rows[a:b], cnt)
        s = s_lo[rid] + (np.arange(len(rid)) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        lam = base[rid] + s[:, None] * rgx[rid]
        inside = lam.min(axis=1) >= -BARY_TOL
        rid, s = rid[inside], s[inside]
        tt = row_tri[rid]
        pixel.append((lo[tt, 1] + row_j[rid]) * W + lo[tt, 0] + s)
        triangle.append(tri_ids[tt])
        bary.append(lam[inside])
    if not pixel:
        return Coverage(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    return Coverage(np.concatenate(pixel), np.concatenate(triangle), np.concatenate(bary))

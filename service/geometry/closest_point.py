"""Closest points on a triangle mesh, and marker layouts resolved to surface points.

:func:`closest_points` finds, for query points, the nearest point of a triangle mesh as a
(triangle, barycentric) pair. Each (query, candidate triangle) pair is solved exactly by the
Voronoi-region case analysis of Ericson, *Real-Time Collision Detection* (2005), §5.1.5,
vectorized over all pairs; the candidates come from a k-d tree over the triangle centroids,
and a query is widened until no unchecked triangle can be closer, so the answer equals a
brute-force search over every triangle.

:func:`surface_points` evaluates (triangle, barycentric) pairs; :func:`resolve_marker_layout` turns an API.md marker layout (markers on vertices, in
triangles, or at free positions) into one (triangle, barycentric) form for every marker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.marker_layout import BARYCENTRIC_TOLERANCE, MarkerLayout

#: A triangle whose height is below ``SLIVER_RTOL`` times its longest edge (zero-area ones
#: included) also has its three edges searched: the face-region formula loses accuracy as
#: the height shrinks and is undefined at zero area, while the edges alone hold every point
#: of a collinear triangle.
SLIVER_RTOL = 1e-6

#: barycentrics of a layout whose sum is off by more than this (or that have a negative
#: coordinate) are renormalized; closer ones, rounding in the last bits, are kept as given
RENORMALIZE_ABOVE = 1e-12

#: (query, candidate) pairs solved per vectorized chunk (bounds the temporaries, ~1 kB a pair).
CHUNK_PAIRS = 1 << 16


@dataclass(frozen=True)
class ClosestPoints:
    """The nearest surface point of a mesh for each of q query points.

    Attributes
    ----------
    triangle : (q,) int64          triangle holding the nearest point (the first found on ties)
    barycentric : (q,3) float64    its coordinates in that triangle, non-negative, summing to 1
    point : (q,3) float64          the nearest point, ``barycentric @ V[F[triangle]]``, units of V
    distance : (q,) float64        ``‖query − point‖``, units of V
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    point: np.ndarray
    distance: np.ndarray


def surface_points(V: np.ndarray, F: np.ndarray, triangle: np.ndarray,
                   barycentric: np.ndarray) -> np.ndarray:
    """Points (…,M,d) at (triangle (M,), barycentric (M,3)) on a mesh with vertices V (…,n,d).

    V may carry leading frame axes, and may be UVs (with per-corner ``uv_faces`` as F).
    """
    corners = np.asarray(V)[..., np.asarray(F)[triangle], :]                 # (…,M,3,d)
    return np.einsum("...mkd,mk->...md", corners, barycentric)


def closest_points(V: np.ndarray, F: np.ndarray, P: np.ndarray, k: int = 16) -> ClosestPoints:
    """Nearest point of the triangle mesh (V, F) to each query point, exactly.

    Candidates are the ``k`` triangles whose centroids are nearest to the query (a
    :class:`scipy.spatial.cKDTree`). Every triangle lies within ``R`` of its centroid (``R``
    the largest centroid-to-corner distance of the mesh), so an unchecked triangle is at
    least ``c_k − R`` away, ``c_k`` the distance to the k-th nearest centroid; a query whose
    best distance exceeds that bound is also searched over the centroids ranked k+1 to 2k,
    the candidate count doubling until the bound holds or every triangle is checked. The
    result equals a brute-force search over all triangles (up to rounding, and up to which
    of several equally near triangles is reported).

    Parameters
    ----------
    V : (n,3) float     vertices, any unit (mm for an actor)
    F : (m,3) int       triangles, m ≥ 1; degenerate (zero-area) ones are allowed
    P : (q,3) float     finite query points, units of V
    k : int             initial candidate count per query (clamped to m)

    Returns
    -------
    ClosestPoints

    Raises
    ------
    ValueError
        For arrays of the wrong shape, triangle indices out of range, non-finite vertices
        or query points, or ``k < 1``.

    Notes
    -----
    ``R`` is the centroid-to-corner radius, not the circumradius: the circumcircle is
    centred on the circumcentre, and for a tall isosceles triangle the apex lies farther
    from the centroid (2h/3) than the circumradius (≈ h/2). One large triangle raises ``R``
    for every query (on the ICT neutral R = 14 mm against a median of 2.3 mm, so a query
    near the surface ends up checking a few hundred triangles, ~0.4 ms each); queries far
    from the surface widen further, up to all m triangles — exact, but slower.
    """
    V, F = _check_mesh(V, F)
    P = np.asarray(P, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"query points must have shape (q,3), got {P.shape}")
    if not np.isfinite(P).all():
        raise ValueError(f"query point {np.flatnonzero(~np.isfinite(P).all(axis=1))[0]} "
                         "has a non-finite coordinate")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")

    T = V[F]                                                      # (m,3,3) corners
    m, q = len(F), len(P)
    centroid = T.mean(axis=1)
    radius = np.linalg.norm(T - centroid[:, None, :], axis=2).max()
    sliver = _is_sliver(T)
    from scipy.spatial import cKDTree  # here: serve's start never needs scipy.spatial

    tree = cKDTree(centroid)

    triangle = np.full(q, -1, np.int64)
    barycentric = np.zeros((q, 3))
    distance = np.full(q, np.inf)
    todo = np.arange(q)
    lo, hi = 0, min(int(k), m)
    while len(todo):
        # the hi nearest centroids; those before lo were searched in an earlier round
        centroid_dist, cand = tree.query(P[todo], k=hi)
        centroid_dist = centroid_dist.reshape(len(todo), hi)
        cand = cand.reshape(len(todo), hi)
        tri, bary, dist = _nearest_candidate(P[todo], cand[:, lo:], T, sliver)
        better = dist < distance[todo]
        triangle[todo[better]] = tri[better]
        barycentric[todo[better]] = bary[better]
        distance[todo[better]] = dist[better]
        if hi == m:
            break
        todo = todo[distance[todo] > centroid_dist[:, -1] - radius]
        lo, hi = hi, min(2 * hi, m)

    point = np.einsum("qk,qkd->qd", barycentric, T[triangle])
    return ClosestPoints(triangle, barycentric, point, np.linalg.norm(P - point, axis=1))


def resolve_marker_layout(
    layout: MarkerLayout, V: np.ndarray, F: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Every marker of a layout as a surface point (triangle, barycentric) of the mesh.

    - ``"triangle"`` markers are kept as given, after checking the index and coordinates;
    - a ``"vertex"`` marker goes to the lowest-numbered triangle using that vertex, with the
      one-hot coordinate of that corner;
    - a ``"position"`` marker is snapped to its nearest surface point (:func:`closest_points`).

    Parameters
    ----------
    layout : service.geometry.marker_layout.MarkerLayout    M markers
    V : (n,3) float                             the actor's neutral vertices
    F : (m,3) int                               its triangles

    Returns
    -------
    triangle : (M,) int64
    barycentric : (M,3) float64     non-negative, summing to 1 (``"triangle"`` markers: as
                                    given if within ``BARYCENTRIC_TOLERANCE``, clipped at 0
                                    and divided by their sum)

    Raises
    ------
    ValueError
        Naming the first offending marker, e.g. ``"marker 'FH2': triangle 99999 out of range
        [0, 89152)"``: a triangle or vertex index out of range, a vertex no triangle uses,
        barycentrics that are not finite, negative, or do not sum to 1 within
        :data:`service.geometry.marker_layout.BARYCENTRIC_TOLERANCE`, a non-finite position, or an unknown
        kind. Also for a malformed mesh (see :func:`closest_points`).
    """
    V, F = _check_mesh(V, F)
    n, m = len(V), len(F)
    names = tuple(layout.names)
    kinds = np.asarray(layout.kinds, dtype=str)
    M = len(names)
    _raise_first(names, ~np.isin(kinds, ["vertex", "triangle", "position"]), lambda i: (
        f"kind {str(kinds[i])!r}, expected 'vertex', 'triangle' or 'position'"))
    triangle = np.full(M, -1, np.int64)
    barycentric = np.zeros((M, 3))

    # triangle + barycentric: kept as given
    sel = np.flatnonzero(kinds == "triangle")
    tri = np.asarray(layout.triangle, dtype=np.int64)[sel]
    bary = np.asarray(layout.barycentric, dtype=np.float64).reshape(-1, 3)[sel]
    _raise_first(names, (tri < 0) | (tri >= m), lambda i: (
        f"triangle {tri[i]} out of range [0, {m})"), sel)
    total = bary.sum(axis=1)
    bad = ~np.isfinite(bary).all(axis=1) | (bary < -BARYCENTRIC_TOLERANCE).any(axis=1)
    bad |= ~(np.abs(total - 1) <= BARYCENTRIC_TOLERANCE)
    _raise_first(names, bad, lambda i: (
        f"barycentric {bary[i].tolist()} (sum {float(total[i])!r}); expected 3 non-negative "
        f"numbers summing to 1 within {BARYCENTRIC_TOLERANCE:g}"), sel)
    # within the tolerance but off (rounded exports): clipped at 0 and renormalized
    off = (bary < 0).any(axis=1) | (np.abs(total - 1) > RENORMALIZE_ABOVE)
    fixed = np.clip(bary[off], 0.0, None)
    bary[off] = fixed / fixed.sum(axis=1, keepdims=True)
    triangle[sel], barycentric[sel] = tri, bary

    # vertex: the first triangle using it, one-hot at that corner
    sel = np.flatnonzero(kinds == "vertex")
    vert = np.asarray(layout.vertex, dtype=np.int64)[sel]
    _raise_first(names, (vert < 0) | (vert >= n), lambda i: (
        f"vertex {vert[i]} out of range [0, {n})"), sel)
    used, first_corner = np.unique(F.ravel(), return_index=True)    # sorted, first occurrence
    at = np.minimum(np.searchsorted(used, vert), len(used) - 1)
    _raise_first(names, used[at] != vert, lambda i: (
        f"vertex {vert[i]} is used by no triangle, expected a vertex of the surface"), sel)
    triangle[sel] = first_corner[at] // 3
    barycentric[sel, first_corner[at] % 3] = 1.0

    # position: snapped to the surface
    sel = np.flatnonzero(kinds == "position")
    pos = np.asarray(layout.position, dtype=np.float64).reshape(-1, 3)[sel]
    _raise_first(names, ~np.isfinite(pos).all(axis=1), lambda i: (
        f"position {pos[i].tolist()}, expected 3 finite numbers"), sel)
    if len(sel):
        snapped = closest_points(V, F, pos)
        triangle[sel], barycentric[sel] = snapped.triangle, snapped.barycentric
    return triangle, barycentric


# ---------------------------------------------------------------------------- internals


def _check_mesh(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """V as (n,3) float64 and F as (m,3) int64, checked (m ≥ 1, indices in range, finite V)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices must have shape (n,3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise ValueError(f"triangles must have shape (m,3) with m >= 1, got {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"triangles must be integer indices, got dtype {F.dtype}")
    F = F.astype(np.int64, copy=False)
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"triangle indices must lie in [0, {len(V)}), "
                         f"got [{F.min()}, {F.max()}]")
    if not np.isfinite(V).all():
        raise ValueError("vertices must be finite")
    return V, F


def _raise_first(names, bad: np.ndarray, what, sel: np.ndarray | None = None) -> None:
    """Raise ``ValueError("marker '<name>': <what(i)>")`` for the first True of ``bad``.

    ``bad`` runs over the markers ``sel`` (all markers when None); ``what`` gets the position
    in ``bad``.
    """
    hits = np.flatnonzero(bad)
    if len(hits):
        i = hits[0]
        name = names[i if sel is None else sel[i]]
        raise ValueError(f"marker '{name}': {what(i)}")


def _is_sliver(T: np.ndarray) -> np.ndarray:
    """(m,) True where a triangle's height is below ``SLIVER_RTOL`` × its longest edge."""
    e = T[:, [1, 2, 0]] - T                                       # (m,3,3) edge vectors
    longest2 = np.einsum("mkd,mkd->mk", e, e).max(axis=1)
    twice_area = np.linalg.norm(np.cross(e[:, 0], -e[:, 2]), axis=1)
    return twice_area <= SLIVER_RTOL * longest2                   # height = 2A / longest


def _nearest_candidate(
    P: np.ndarray, cand: np.ndarray, T: np.ndarray, sliver: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest of the candidate triangles cand (s,c) for each point P (s,3).

    Returns triangle (s,) int64, barycentric (s,3) and distance (s,); chunked by
    ``CHUNK_PAIRS``. The first candidate wins ties.
    """
    s, c = cand.shape
    triangle = np.empty(s, np.int64)
    barycentric = np.empty((s, 3))
    distance = np.empty(s)
    rows = max(1, CHUNK_PAIRS // max(c, 1))
    for a in range(0, s, rows):
        b = min(a + rows, s)
        tri = cand[a:b].ravel()
        Q = np.repeat(P[a:b], c, axis=0)
        bary, dist = _closest_on_triangles(Q, T[tri])
        thin = np.flatnonzero(sliver[tri])
        if len(thin):
            e_bary, e_dist = _closest_on_edges(Q[thin], T[tri[thin]])
            closer = e_dist < dist[thin]
            bary[thin[closer]], dist[thin[closer]] = e_bary[closer], e_dist[closer]
        dist = dist.reshape(b - a, c)
        best = np.argmin(dist, axis=1)
        pick = np.arange(b - a) * c + best
        triangle[a:b] = tri[pick]
        barycentric[a:b] = bary[pick]
        distance[a:b] = dist[np.arange(b - a), best]
    return triangle, barycentric, distance


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """``num / den`` clipped to [0, 1], and 0 where ``den`` is not positive (no NaN)."""
    ok = den > 0
    return np.clip(np.where(ok, num / np.where(ok, den, 1.0), 0.0), 0.0, 1.0)


def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("nd,nd->n", x, y)


def _closest_on_triangles(P: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of triangle T[i] (N,3,3) to P[i] (N,3): barycentric (N,3), distance (N,).

    Ericson (2005) §5.1.5: classify P into the Voronoi region of a corner, an edge or the
    face by signs of dot products, tested in his order (the first region that matches
    wins). His edge/face determinants ``va, vb, vc`` (``vc = d1 d4 − d3 d2`` ...) are the
    same numbers written as triple products ``n · (bp × cp)`` ... by the Binet–Cauchy
    identity, which cancel less on thin triangles. The coordinates are clipped to ≥ 0 and
    renormalized against rounding; every division is guarded, so a degenerate triangle
    gives a finite point of itself (not necessarily its nearest: see ``SLIVER_RTOL``).
    """
    A, B, C = T[:, 0], T[:, 1], T[:, 2]
    ab, ac = B - A, C - A
    ap, bp, cp = P - A, P - B, P - C
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    n = np.cross(ab, ac)
    va = _dot(n, np.cross(bp, cp))          # = d3 d6 − d5 d4   (u of the face, × |n|²)
    vb = _dot(n, np.cross(cp, ap))          # = d5 d2 − d1 d6   (v)
    vc = _dot(n, np.cross(ap, bp))          # = d1 d4 − d3 d2   (w)

    regions = [
        (d1 <= 0) & (d2 <= 0),                                    # corner A
        (d3 >= 0) & (d4 <= d3),                                   # corner B
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),                        # edge AB
        (d6 >= 0) & (d5 <= d6),                                   # corner C
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),                        # edge AC
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),              # edge BC
    ]
    t_ab = _ratio(d1, d1 - d3)
    t_ac = _ratio(d2, d2 - d6)
    t_bc = _ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    den = va + vb + vc                                            # = |n|²
    face = [_ratio(va, den), _ratio(vb, den), _ratio(vc, den)]
    zero, one = np.zeros(len(P)), np.ones(len(P))
    u = np.select(regions, [one, zero, 1 - t_ab, zero, 1 - t_ac, zero], face[0])
    v = np.select(regions, [zero, one, t_ab, zero, zero, 1 - t_bc], face[1])
    w = np.select(regions, [zero, zero, zero, one, t_ac, t_bc], face[2])
    bary = np.stack([u, v, w], axis=1)
    total = bary.sum(axis=1, keepdims=True)
    bary = np.where(total > 0, bary / np.where(total > 0, total, 1.0), [1.0, 0.0, 0.0])
    point = np.einsum("nk,nkd->nd", bary, T)
    return bary, np.linalg.norm(P - point, axis=1)


def _closest_on_edges(P: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of the three edges of T[i] (N,3,3) to P[i] (N,3).

    Returns barycentric (N,3) and distance (N,). Zero-length edges are their corner.
    """
    best_bary = np.zeros((len(P), 3))
    best_dist = np.full(len(P), np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):                         # three edges, not points
        a, e = T[:, i], T[:, j] - T[:, i]
        t = _ratio(_dot(P - a, e), _dot(e, e))
        dist = np.linalg.norm(P - (a + t[:, None] * e), axis=1)
        closer = dist < best_dist
        bary = np.zeros((len(P), 3))
        bary[:, i], bary[:, j] = 1 - t, t
        best_bary[closer], best_dist[closer] = bary[closer], dist[closer]
    return best_bary, best_dist

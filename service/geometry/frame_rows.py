"""The float32 frames of one pose of :class:`service.geometry.tangent_frames.FrameField`,
compiled (issue 23): what a normal map (and the PDM's detailed mesh) reads of the medium
mesh's frames every frame.

:meth:`FrameField._rows32 <service.geometry.tangent_frames.FrameField._rows32>` did it as three
sparse products per component (the edges, dP/du accumulated from them, the normals from the
triangles' cross products) and about 30 elementwise passes over (3,n) rows (5.2 ms of a
level-1 PDM maps frame under cProfile). Here it is three Numba kernels over ranges
(:func:`service.geometry.ranges.run`): per triangle its two edges (float64 differences,
rounded once) and their cross product; per vertex T and N accumulated from the same CSR
operators in their stored order, N normalized and T projected off it; then, with the largest
|T| component over the mesh (FrameField's cancellation threshold), per vertex the fallback
tangent, T normalized and B = N × T.

The same operations in the same order and precision as the NumPy passes (compiled without
fast-math; each sparse row summed from 0 in its stored order, as SciPy's CSR products), so
the frames are theirs bit for bit (tests/geometry/test_tangent_frames.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64


@njit(nogil=True, cache=True, error_model="numpy")
def triangle_rows(lo, hi, ptr, idx, val, V, m, e, fn):
    """Triangles [lo, hi): the edges e1 = P1 − P0 (column t) and e2 = P2 − P0 (column m + t)
    of ``e`` (3,2m) float32, rows t and m + t of the edge operator (CSR ``ptr``, ``idx``,
    ``val`` float64) applied to V (n,3) float64 and rounded once, and ``fn`` (3,m) float32
    = e1 × e2."""
    mm = uint64(m)
    for t in range(uint64(lo), uint64(hi)):
        for r in (t, t + mm):
            for c in range(3):
                s = 0.0
                for jj in range(ptr[r], ptr[r + uint64(1)]):
                    s += val[jj] * V[idx[jj], c]
                e[c, r] = np.float32(s)
        a0, a1, a2 = e[0, t], e[1, t], e[2, t]
        b0, b1, b2 = e[0, t + mm], e[1, t + mm], e[2, t + mm]
        fn[0, t] = a1 * b2 - a2 * b1
        fn[1, t] = a2 * b0 - a0 * b2
        fn[2, t] = a0 * b1 - a1 * b0


@njit(nogil=True, cache=True, error_model="numpy")
def triangle_edges(lo, hi, F, V, m, e, fn):
    """:func:`triangle_rows` of the edge operator of the triangles ``F`` (m,3) uint32 itself
    (rows t: +1 at corner 1, −1 at corner 0; rows m + t: +1 at corner 2, −1 at corner 0), from
    the corners instead of its CSR arrays: ``e = (0 + P1) − P0`` in float64, rounded once.
    The CSR row sum is ``0 + P1 − P0`` or ``0 − P0 + P1`` by its stored column order; the
    products by ±1 are exact and both sums start from +0, so each gives this value and this
    sign of zero for finite vertices, bit for bit (tests/geometry/test_tangent_frames.py).
    It does not read the operator (5.7 MB a frame at level 1): a level-1 PDM maps frame
    42.30 → 41.74 ms of CPU (median of 55, alternating in one process, load 6)."""
    mm = uint64(m)
    for t in range(uint64(lo), uint64(hi)):
        a, b, c = F[t, 0], F[t, 1], F[t, 2]
        for k in range(3):
            p0 = V[a, k]
            e[k, t] = np.float32((0.0 + V[b, k]) - p0)
            e[k, t + mm] = np.float32((0.0 + V[c, k]) - p0)
        a0, a1, a2 = e[0, t], e[1, t], e[2, t]
        b0, b1, b2 = e[0, t + mm], e[1, t + mm], e[2, t + mm]
        fn[0, t] = a1 * b2 - a2 * b1
        fn[1, t] = a2 * b0 - a0 * b2
        fn[2, t] = a0 * b1 - a1 * b0


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _row_sums(ptr, idx, val, X, v):
    """Row v of the float32 CSR (ptr, idx, val) times the three rows of X (3,k): each sum
    from 0 over the row's entries in their stored order (SciPy's CSR product)."""
    s0 = s1 = s2 = np.float32(0)
    for jj in range(ptr[v], ptr[v + uint64(1)]):
        w, q = val[jj], idx[jj]
        s0 += w * X[0, q]
        s1 += w * X[1, q]
        s2 += w * X[2, q]
    return s0, s1, s2


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _unit(x0, x1, x2):
    """(x0, x1, x2) float32 times 1/|x| (|x|² summed x, y, z in order), zero kept zero (the
    arithmetic of ``tangent_frames._normalize_rows``)."""
    nn = x0 * x0
    nn += x1 * x1
    nn += x2 * x2
    norm = np.sqrt(nn)
    inv = np.float32(1.0) / norm if norm > 0 else np.float32(0)
    return x0 * inv, x1 * inv, x2 * inv


@njit(nogil=True, cache=True, error_model="numpy")
def vertex_rows(lo, hi, tptr, tidx, tval, e, nptr, nidx, nval, fn, T, N, tmax):
    """Vertices [lo, hi): ``T`` (3,n) float32 = dP/du accumulated from the edges ``e``
    (float32 CSR ``du_edges``), ``N`` (3,n) the unit sum of the incident ``fn`` (float32 CSR
    ``incidence``; 0 where it vanishes), T projected off N, and ``tmax`` (n,) its largest
    |component|."""
    for v in range(uint64(lo), uint64(hi)):
        t0, t1, t2 = _row_sums(tptr, tidx, tval, e, v)
        n0, n1, n2 = _row_sums(nptr, nidx, nval, fn, v)
        n0, n1, n2 = _unit(n0, n1, n2)
        d = t0 * n0
        d += t1 * n1
        d += t2 * n2
        t0, t1, t2 = t0 - d * n0, t1 - d * n1, t2 - d * n2
        T[0, v], T[1, v], T[2, v] = t0, t1, t2
        N[0, v], N[1, v], N[2, v] = n0, n1, n2
        tmax[v] = max(abs(t0), abs(t1), abs(t2))


@njit(nogil=True, cache=True, error_model="numpy")
def finish_rows(lo, hi, T, N, threshold, B, has_n):
    """Vertices [lo, hi): where the vertex has a normal (``has_n``: |N|² > 0.25) and
    ``|T| ≤ threshold`` (float32), T replaced by the least-aligned axis projected off N (in
    float64, rounded once); T normalized (in place); ``B`` (3,n) = N × T."""
    for v in range(uint64(lo), uint64(hi)):
        t0, t1, t2 = T[0, v], T[1, v], T[2, v]
        n0, n1, n2 = N[0, v], N[1, v], N[2, v]
        nn = n0 * n0
        nn += n1 * n1
        nn += n2 * n2
        h = nn > np.float32(0.25)
        has_n[v] = h
        tt = t0 * t0
        tt += t1 * t1
        tt += t2 * t2
        if h and not (np.sqrt(tt) > threshold):
            a0, a1, a2 = abs(n0), abs(n1), abs(n2)
            j = 0 if (a0 <= a1 and a0 <= a2) else (1 if a1 <= a2 else 2)
            d = np.float64(n0) if j == 0 else (np.float64(n1) if j == 1 else np.float64(n2))
            t0 = np.float32((1.0 if j == 0 else 0.0) - d * np.float64(n0))
            t1 = np.float32((1.0 if j == 1 else 0.0) - d * np.float64(n1))
            t2 = np.float32((1.0 if j == 2 else 0.0) - d * np.float64(n2))
        t0, t1, t2 = _unit(t0, t1, t2)
        T[0, v], T[1, v], T[2, v] = t0, t1, t2
        B[0, v] = n1 * t2 - n2 * t1
        B[1, v] = n2 * t0 - n0 * t2
        B[2, v] = n0 * t1 - n1 * t0

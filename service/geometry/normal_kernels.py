"""The per-face and per-vertex passes of :func:`service.geometry.normals.vertex_normals`
(angle weighting), compiled (issue 23: the shape-space ``/enhance`` displacement's input
normals, 14 of a 140 ms level-1 frame as NumPy passes).

The NumPy form makes about 25 (m,3) and (m,3,3) float64 temporaries per frame. Here one
pass over the faces writes what the corner angles need (twice the area and the negated
edge dot products), the angles themselves stay NumPy's ``arctan2`` — called on arrays of
the same shapes and strides as before, so with the same implementation (NumPy's SIMD
``arctan2`` is not libm's: compiled, the angles would differ by an ulp) — and a second pass
adds each corner's contribution to its vertex in corner order and normalizes.

Bit for bit the NumPy passes (tests/geometry/test_normals.py): the same float64 operations
in the same order (products rounded before they are added or subtracted, the reciprocal of
twice the area multiplied, the per-vertex sums in corner order as ``bincount`` forms them),
compiled without fast-math. A sum of three products ``einsum("...d,...d->...")`` forms as
``(p0 + p2) + p1`` (its two-lane SIMD loop: lanes d = 0 and 1, the third added to lane 0,
then the lanes), :func:`sum3`; :func:`service.geometry.normals.vertex_normals` checks once
per process that this NumPy's ``einsum`` does so, and keeps its NumPy passes where not.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True, error_model="numpy")
def sum3(p0, p1, p2):
    """``p0 + p1 + p2`` in the order ``einsum`` sums a length-3 axis: ``(p0 + p2) + p1``."""
    return (p0 + p2) + p1


def sum3_numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`sum3` of the products ``a[..., d] * b[..., d]`` as NumPy passes (the probe's
    reference against ``einsum``)."""
    return (a[..., 0] * b[..., 0] + a[..., 2] * b[..., 2]) + a[..., 1] * b[..., 1]


@njit(nogil=True, cache=True, error_model="numpy")
def face_terms(P, F, twice_area, negdot):
    """Per face f of frame P (n,3): ``twice_area[f]`` = |(P1 − P0) × (P2 − P0)| and
    ``negdot[k, f]`` = −(a · b) of the edge pair at corner k ((e01, e20), (e12, e01),
    (e20, e12)), whose ``arctan2(twice_area, negdot)`` is the corner's interior angle."""
    for f in range(F.shape[0]):
        i, j, k = F[f, 0], F[f, 1], F[f, 2]
        a0, a1, a2 = P[i, 0], P[i, 1], P[i, 2]
        b0, b1, b2 = P[j, 0], P[j, 1], P[j, 2]
        c0, c1, c2 = P[k, 0], P[k, 1], P[k, 2]
        e01 = (b0 - a0, b1 - a1, b2 - a2)
        e12 = (c0 - b0, c1 - b1, c2 - b2)
        e20 = (a0 - c0, a1 - c1, a2 - c2)
        x = e20[1] * e01[2] - e20[2] * e01[1]
        y = e20[2] * e01[0] - e20[0] * e01[2]
        z = e20[0] * e01[1] - e20[1] * e01[0]
        twice_area[f] = np.sqrt(sum3(x * x, y * y, z * z))
        negdot[0, f] = -sum3(e01[0] * e20[0], e01[1] * e20[1], e01[2] * e20[2])
        negdot[1, f] = -sum3(e12[0] * e01[0], e12[1] * e01[1], e12[2] * e01[2])
        negdot[2, f] = -sum3(e20[0] * e12[0], e20[1] * e12[1], e20[2] * e12[2])


@njit(nogil=True, cache=True, error_model="numpy")
def vertex_sums(P, F, twice_area, angles, N):
    """Unit vertex normals N (n,3) of frame P (n,3): each face's unit normal (its cross
    product times the reciprocal of twice its area; zero for a degenerate face) times the
    corner's angle ``angles[f, k]`` added at the corner's vertex, corners in order, then each
    vertex's sum scaled to unit length (zero stays zero)."""
    N[:] = 0.0
    for f in range(F.shape[0]):
        i, j, k = F[f, 0], F[f, 1], F[f, 2]
        e01 = (P[j, 0] - P[i, 0], P[j, 1] - P[i, 1], P[j, 2] - P[i, 2])
        e20 = (P[i, 0] - P[k, 0], P[i, 1] - P[k, 1], P[i, 2] - P[k, 2])
        t = twice_area[f]
        inv = 1.0 / t if t > 0 else 0.0
        x = (e20[1] * e01[2] - e20[2] * e01[1]) * inv
        y = (e20[2] * e01[0] - e20[0] * e01[2]) * inv
        z = (e20[0] * e01[1] - e20[1] * e01[0]) * inv
        for c in range(3):
            v = F[f, c]
            a = angles[f, c]
            N[v, 0] += a * x
            N[v, 1] += a * y
            N[v, 2] += a * z
    for v in range(N.shape[0]):
        x, y, z = N[v, 0], N[v, 1], N[v, 2]
        norm = np.sqrt(sum3(x * x, y * y, z * z))
        inv = 1.0 / norm if norm > 0 else 0.0
        N[v, 0], N[v, 1], N[v, 2] = x * inv, y * inv, z * inv

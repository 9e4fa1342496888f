"""Unit face and vertex normals of triangle meshes, for one mesh or a batch of frames.

Vertex normals are angle-weighted (Thürmer & Wüthrich 1998, "Computing vertex normals from
polygonal meshes"): each incident triangle contributes its unit normal times its interior
angle at the vertex. Unlike area weighting, the result does not depend on how a polygon is
triangulated (the ICT rig's quads are split along one diagonal, which would tilt
area-weighted normals towards the side with the larger triangle), and a vertex normal of a
finely sampled sphere is the radial direction to second order.

Degenerate triangles (zero area) get a zero face normal and contribute nothing; a vertex
with no non-degenerate incident triangle (e.g. unreferenced) gets a zero normal.
Everything is float64.
"""

from __future__ import annotations

import numpy as np

#: Triangle-frames processed at once by :func:`vertex_normals` (~100k: a few MB per temporary).
CHUNK_ELEMENTS = 100_000


def _flatten_frames(V: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """(B,n,3) float64 view of (n,3) or (...,n,3) vertices, and the leading shape."""
    V = np.asarray(V, dtype=np.float64)
    if V.ndim < 2 or V.shape[-1] != 3:
        raise ValueError(f"vertices must be (n,3) or (...,n,3), got {V.shape}")
    return V.reshape(-1, *V.shape[-2:]), V.shape[:-2]


def _normalize(X: np.ndarray) -> np.ndarray:
    """Rows of X (...,3) scaled to unit length; zero rows stay zero."""
    norm = np.sqrt(np.einsum("...d,...d->...", X, X))
    with np.errstate(divide="ignore"):
        inv = np.where(norm > 0, 1.0 / norm, 0.0)            # per row: cheaper than a masked divide
    return X * inv[..., None]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` for (...,3) arrays, written out (np.cross is several times slower)."""
    c = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b, np.float32))
    c[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    c[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    c[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return c


def face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unit normals of the triangles, oriented by the corner order (counter-clockwise = front).

    Parameters
    ----------
    V : (n,3) or (frames,n,3) float   vertices (any unit)
    F : (m,3) int                     triangles

    Returns
    -------
    N : (m,3) or (frames,m,3) float64   unit normals; zero for degenerate triangles
    """
    F = np.asarray(F, dtype=np.int64)
    P = np.asarray(V, dtype=np.float64)
    return _normalize(_cross(P[..., F[:, 1], :] - P[..., F[:, 0], :],
                               P[..., F[:, 2], :] - P[..., F[:, 0], :]))


def corner_angles(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Interior angle at every triangle corner, radians.

    Parameters
    ----------
    V : (n,3) or (frames,n,3) float
    F : (m,3) int

    Returns
    -------
    angles : (m,3) or (frames,m,3) float64   ``angles[..., f, k]`` at corner ``F[f,k]``;
             0 for degenerate triangles
    """
    F = np.asarray(F, dtype=np.int64)
    P = np.asarray(V, dtype=np.float64)[..., F, :]            # (...,m,3,3)
    a = np.roll(P, -1, axis=-2) - P
    b = np.roll(P, -2, axis=-2) - P
    # atan2(|a×b|, a·b) is accurate for all angles, unlike acos of the normalized dot
    return np.arctan2(np.linalg.norm(_cross(a, b), axis=-1), np.einsum("...d,...d->...", a, b))


def _angle_weighted_normals(P: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(b,m,3,3) corner contributions θ_k · n̂ of frames P (b,n,3) float64: the interior
    angle at corner k (``atan2(|e × e'|, e · e')``, as :func:`corner_angles`) times the unit
    face normal (:func:`face_normals`), from one cross product per face — the three corners'
    |e × e'| are all twice the area — instead of one per corner (the same values to a few
    ulp; at 89k triangles 28 + 7 → ~8 ms)."""
    P0, P1, P2 = P[:, F[:, 0]], P[:, F[:, 1]], P[:, F[:, 2]]
    e01, e12, e20 = P1 - P0, P2 - P1, P0 - P2
    cross = _cross(e20, e01)                                   # (P1 − P0) × (P2 − P0)
    twice_area = np.sqrt(np.einsum("...d,...d->...", cross, cross))
    with np.errstate(divide="ignore"):
        unit = cross * np.where(twice_area > 0, 1.0 / twice_area, 0.0)[..., None]
    angles = np.empty(P0.shape)                                # (b,m,3): corner k of face f
    for k, (a, b) in enumerate(((e01, e20), (e12, e01), (e20, e12))):
        # the angle between a and −b
        np.arctan2(twice_area, -np.einsum("...d,...d->...", a, b), out=angles[..., k])
    return angles[..., None] * unit[:, :, None, :]


_EINSUM_ORDER: list[bool] = []


def _einsum_sums_as_compiled() -> bool:
    """Whether this NumPy's ``einsum("...d,...d->...")`` of (k,3) rows sums the three products
    as :func:`.normal_kernels.sum3` does (checked once per process on 4096 seeded rows of
    mixed magnitudes); if not, :func:`vertex_normals` keeps the NumPy passes."""
    if not _EINSUM_ORDER:
        from service.geometry.normal_kernels import sum3_numpy

        rng = np.random.default_rng(23)
        a = rng.normal(size=(4096, 3)) * 10.0 ** rng.integers(-3, 4, size=(4096, 3))
        b = rng.normal(size=(4096, 3)) * 10.0 ** rng.integers(-3, 4, size=(4096, 3))
        _EINSUM_ORDER.append(bool(np.array_equal(np.einsum("...d,...d->...", a, b), sum3_numpy(a, b))))
    return _EINSUM_ORDER[0]


def _compiled_angle_normals(Vb: np.ndarray, F: np.ndarray, n: int) -> np.ndarray:
    """Angle-weighted unit normals (b,n,3) of frames Vb (b,n,3) float64 on the compiled
    passes of :mod:`.normal_kernels` (bit for bit :func:`_angle_weighted_normals` summed in
    corner order and normalized): the angles are NumPy's ``arctan2`` of arrays laid out as
    that function's (twice the area and the negated dot products contiguous, each corner's
    angles a stride-3 column of an (m,3) array), so they are the same values."""
    if F.size and (F.min() < 0 or F.max() >= n):
        raise IndexError(f"a triangle refers to a vertex outside [0, {n})")
    from service.geometry.normal_kernels import face_terms, vertex_sums   # Numba: on first use

    m = len(F)
    N = np.empty((len(Vb), n, 3))
    twice_area, negdot, angles = np.empty(m), np.empty((3, m)), np.empty((m, 3))
    for f, P in enumerate(Vb):
        face_terms(P, F, twice_area, negdot)
        for k in range(3):
            np.arctan2(twice_area, negdot[k], out=angles[:, k])
        vertex_sums(P, F, twice_area, angles, N[f])
    return N


def vertex_normals(V: np.ndarray, F: np.ndarray, weighting: str = "angle") -> np.ndarray:
    """Unit vertex normals, the weighted mean of the incident face normals.

    Parameters
    ----------
    V : (n,3) or (frames,n,3) float   vertices (any unit)
    F : (m,3) int                     triangles
    weighting : ``"angle"`` (default; Thürmer & Wüthrich 1998, tessellation-independent)
                or ``"area"`` (cross products summed, the classical Gouraud normal)

    Returns
    -------
    N : (n,3) or (frames,n,3) float64   unit normals; zero where no non-degenerate
                                        triangle touches the vertex
    """
    F = np.asarray(F, dtype=np.int64)
    if weighting not in ("angle", "area"):
        raise ValueError(f"weighting must be 'angle' or 'area', got {weighting!r}")
    Vb, lead = _flatten_frames(V)
    nb, n = Vb.shape[:2]
    m = len(F)
    if weighting == "angle" and m and nb and _einsum_sums_as_compiled():
        return _compiled_angle_normals(Vb, np.ascontiguousarray(F), n).reshape(*lead, n, 3)
    corners = F.ravel()
    N = np.empty((nb, n, 3))
    acc = np.empty((n, 3))
    step = max(1, CHUNK_ELEMENTS // max(m, 1))      # frames at once: temporaries stay cached
    for s in range(0, nb, step):
        B = Vb[s:s + step]
        if weighting == "angle":          # every corner its own contribution
            contrib = _angle_weighted_normals(B, F)
        else:                             # the face's cross product at all three corners
            P = B[:, F]                                                      # (b,m,3,3)
            cross = _cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0])
            contrib = np.broadcast_to(cross[:, :, None, :], (len(B), m, 3, 3))
        contrib = contrib.reshape(len(B), 3 * m, 3)
        for f in range(len(B)):
            # summed per vertex in corner order (as a (n,3m) scatter matrix product sums,
            # bit for bit), without building that matrix per call
            for d in range(3):
                acc[:, d] = np.bincount(corners, contrib[f, :, d], minlength=n)
            N[s + f] = _normalize(acc)
    return N.reshape(*lead, n, 3)

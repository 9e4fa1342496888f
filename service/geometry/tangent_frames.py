"""Per-vertex tangent frames that follow a mesh's UV layout (for tangent-space details).

bickel2008 §3 and §5.2 store fine-scale displacements "per-vertex in local tangent
frames", and UV-space detail maps are interpreted in the same frames, so the frame's
tangent must follow the texture's +u direction. Per triangle, the surface derivatives
dP/du and dP/dv follow from the UV edge differences (the standard normal-mapping
tangent, e.g. Lengyel 2001; mikktspace):

    [dP/du  dP/dv] = [e1  e2] · [[Δu1, Δu2], [Δv1, Δv2]]⁻¹,   e_k = P_k − P_0,  Δ(u,v)_k = uv_k − uv_0.

Each triangle's unit dP/du is accumulated at its corners with the corner angle as weight
(like :func:`service.geometry.normals.vertex_normals`), orthogonalized against the
angle-weighted vertex normal N (Gram-Schmidt) to give T, and ``B = N × T``.

Conventions
-----------
``frames[..., i, :, :]`` has **rows** (T, B, N): orthonormal, right-handed (det = +1),
T along increasing u. ``frames[i] @ d`` expresses a world vector d in the frame (tangent,
bitangent, normal components), ``frames[i].T @ c`` maps back.

Seams and mirrored charts
-------------------------
- A vertex with several UVs (a seam) averages the contributions of all its charts.
- Mirrored charts (UV triangles with clockwise orientation, det < 0) have
  ``dP/du × dP/dv = −N``. The frame stays right-handed with the surface normal
  (``B = N × T``, which then points along −v); :func:`uv_handedness` gives the sign per
  vertex (``+v = handedness · B``, mikktspace's w). Where mirrored and unmirrored charts
  meet, only triangles of the vertex's majority handedness contribute, so opposite u
  directions do not cancel.
- Triangles degenerate in UV (``|det| ≤ UV_DEGENERATE_SIN · |Δuv1| |Δuv2|``) are skipped.
- A vertex whose contributions vanish or cancel exactly gets a tangent perpendicular to
  N along the coordinate axis least aligned with N; a vertex without any non-degenerate
  triangle (no normal) gets the identity frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from service.geometry.normals import _cross, _flatten_frames, _normalize, corner_angles, vertex_normals

#: UV triangles whose UV-space angle sine is below this are degenerate (skipped)
UV_DEGENERATE_SIN = 1e-8
#: accumulated tangent shorter than this fraction of the summed weights counts as cancelled
CANCEL_RTOL = 1e-6
#: :class:`FrameField`'s sparse operators (its fields after ``faces``, in order)
OPERATORS = ("incidence", "du", "edges", "du_edges")


def _uv_determinants(uv: np.ndarray, uv_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """UV edge differences d1, d2 (m,2) and det = Δu1 Δv2 − Δu2 Δv1 (m,) per triangle."""
    U = uv[uv_faces]                                  # (m,3,2)
    d1 = U[:, 1] - U[:, 0]
    d2 = U[:, 2] - U[:, 0]
    return d1, d2, d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]


def _check(F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray):
    F = np.asarray(F, dtype=np.int64)
    uv = np.asarray(uv, dtype=np.float64)
    uv_faces = np.asarray(uv_faces, dtype=np.int64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must be (K,2), got {uv.shape}")
    if uv_faces.shape != F.shape or F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"F and uv_faces must both be (m,3), got {F.shape} and {uv_faces.shape}")
    if len(uv_faces) and (uv_faces.min() < 0 or uv_faces.max() >= len(uv)):
        raise ValueError(f"uv_faces index out of range [0, {len(uv)})")
    return F, uv, uv_faces


def _triangle_signs(uv: np.ndarray, uv_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """d1, d2, det and the per-triangle handedness (+1, −1, or 0 if UV-degenerate)."""
    d1, d2, det = _uv_determinants(uv, uv_faces)
    scale = np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1)
    ok = np.abs(det) > UV_DEGENERATE_SIN * scale
    return d1, d2, det, np.where(ok, np.sign(det), 0.0)


def uv_handedness(F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray, n: int) -> np.ndarray:
    """Per-vertex UV handedness: +1 where the UV chart keeps the orientation, −1 mirrored.

    Parameters
    ----------
    F : (m,3) int          triangles over n vertices
    uv : (K,2) float       UV coordinates
    uv_faces : (m,3) int   per-corner indices into uv
    n : int                vertex count

    Returns
    -------
    sign : (n,) float64   ±1 by the majority (by triangle count) of the incident,
                          non-degenerate UV triangles; +1 where there is none. The +v
                          direction at vertex i is ``sign[i] * frames[i, 1]``.
    """
    F, uv, uv_faces = _check(F, uv, uv_faces)
    return _vertex_signs(F, _triangle_signs(uv, uv_faces)[3], n)


def _vertex_signs(F: np.ndarray, tri_sign: np.ndarray, n: int) -> np.ndarray:
    """:func:`uv_handedness` from the triangles' handedness tri_sign (m,) (of :func:`_triangle_signs`)."""
    vote = np.bincount(F.ravel(), weights=np.repeat(tri_sign, 3), minlength=n)
    return np.where(vote < 0, -1.0, 1.0)


def tangent_frames(
    V: np.ndarray, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """Orthonormal per-vertex frames (T, B, N) with T along +u (see the module notes).

    Parameters
    ----------
    V : (n,3) or (frames,n,3) float   vertices (rest pose or deformed frames), mm
    F : (m,3) int                     triangles
    uv : (K,2) float                  UV coordinates (any tile/scale)
    uv_faces : (m,3) int              per-corner indices into uv (seams: several per vertex)
    normals : (n,3) or (frames,n,3) float, optional
        unit vertex normals to use as N (default: angle-weighted
        :func:`~service.geometry.normals.vertex_normals`)

    Returns
    -------
    frames : (n,3,3) or (frames,n,3,3) float64
        rows T, B, N; orthonormal and right-handed (det +1) at every vertex
    """
    F, uv, uv_faces = _check(F, uv, uv_faces)
    Vb, lead = _flatten_frames(V)
    nb, n = Vb.shape[:2]
    m = len(F)
    N = vertex_normals(Vb, F) if normals is None else _normalize(
        np.asarray(normals, dtype=np.float64).reshape(nb, n, 3))

    d1, d2, det, tri_sign = _triangle_signs(uv, uv_faces)
    # keep, per corner, only triangles of the vertex's majority handedness
    vert_sign = _vertex_signs(F, tri_sign, n)
    use = (tri_sign[:, None] != 0) & (tri_sign[:, None] == vert_sign[F])        # (m,3)
    inv_det = np.divide(1.0, det, out=np.zeros(m), where=tri_sign != 0)

    P = Vb[:, F]                                                                 # (B,m,3,3)
    e1 = P[:, :, 1] - P[:, :, 0]
    e2 = P[:, :, 2] - P[:, :, 0]
    dPdu = _normalize((e1 * d2[:, 1, None] - e2 * d1[:, 1, None]) * inv_det[:, None])
    w = corner_angles(Vb, F) * use                                               # (B,m,3)
    contrib = w[..., None] * dPdu[:, :, None, :]                                 # (B,m,3,3)

    S = sp.csr_matrix((np.ones(3 * m), (F.ravel(), np.arange(3 * m))), shape=(n, 3 * m))
    T = (S @ np.ascontiguousarray(contrib.transpose(1, 2, 0, 3)).reshape(3 * m, nb * 3))
    T = T.reshape(n, nb, 3).transpose(1, 0, 2)                                   # (B,n,3)
    wsum = (S @ w.transpose(1, 2, 0).reshape(3 * m, nb)).T                       # (B,n)

    # Gram-Schmidt against N, with fallbacks for cancelled / missing tangents
    T = T - np.einsum("bnd,bnd->bn", T, N)[..., None] * N
    tn = np.linalg.norm(T, axis=-1)
    has_n = np.linalg.norm(N, axis=-1) > 0.5
    weak = has_n & ~(tn > CANCEL_RTOL * wsum)
    if weak.any():
        Nw = N[weak]
        axis = np.eye(3)[np.argmin(np.abs(Nw), axis=1)]
        T[weak] = axis - np.einsum("kd,kd->k", axis, Nw)[:, None] * Nw
    T = _normalize(T)
    B = np.cross(N, T)
    frames = np.stack([T, B, N], axis=-2)                                       # (B,n,3,3)
    frames[~has_n] = np.eye(3)
    return frames.reshape(*lead, n, 3, 3)


def _dot_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products (n,) of component-major vectors a, b (3,n), summed x, y, z in order."""
    out = a[0] * b[0]
    out += a[1] * b[1]
    out += a[2] * b[2]
    return out


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` (3,n) of component-major vectors (3,n) (the arithmetic of
    :func:`service.geometry.normals._cross`)."""
    c = np.empty(a.shape, np.result_type(a, b))
    c[0] = a[1] * b[2] - a[2] * b[1]
    c[1] = a[2] * b[0] - a[0] * b[2]
    c[2] = a[0] * b[1] - a[1] * b[0]
    return c


def _normalize_rows(X: np.ndarray) -> np.ndarray:
    """Component-major vectors X (3,n) scaled to unit length, zero ones kept zero (the
    arithmetic of :func:`service.geometry.normals._normalize`)."""
    norm = np.sqrt(_dot_rows(X, X))
    with np.errstate(divide="ignore"):
        inv = np.where(norm > 0, 1.0 / norm, 0.0)
    return X * inv


@dataclass(frozen=True)
class FrameField:
    """Tangent frames of many deformed poses of one mesh, two sparse products per pose.

    :func:`tangent_frames` recomputes corner angles and per-triangle unit dP/du for every
    pose (≈ 90 ms for 45k vertices). For a per-frame synthesis loop this class freezes the
    weights at the rest pose, which makes both accumulations linear in the vertices:

        N_i ∝ Σ_{f∋i} (P1 − P0) × (P2 − P0)              (area-weighted normal)
        T_i ∝ Σ_{f∋i} α_fi [dP/du]_f,  [dP/du]_f = (e1 Δv2 − e2 Δv1) / det_f

    with α the rest corner angles (majority handedness only, as in :func:`tangent_frames`)
    and the unnormalized dP/du (mm per uv unit, near-uniform inside a chart), so that
    ``T_raw = D @ V`` is one sparse product. T is then Gram-Schmidt-orthogonalized against
    N and ``B = N × T``; rows, handedness and fallbacks follow :func:`tangent_frames`. At
    the rest pose the two agree to within the weighting difference (a few degrees at most
    where triangles of very different size meet).

    Attributes
    ----------
    faces : (m,3) int64
    incidence : (n,m) sparse    vertex–triangle incidence (sums triangle normals)
    du : (n,n) sparse           vertices ↦ accumulated dP/du at the vertices
    edges : (2m,n) sparse       vertices ↦ the edges e1 = P1 − P0 (rows :m), e2 = P2 − P0
                                (a sparse product is several times faster than gathering)
    du_edges : (n,2m) sparse    edges ↦ the same accumulated dP/du (``du = du_edges @ edges``
                                up to rounding), for the float32 path

    Precision: float64 by default. ``dtype=np.float32`` (:meth:`frames`, :meth:`to_world`;
    the per-frame synthesis path) differences the edges in float64 (vertices far from the
    origin; one cheap sparse product) and runs everything after on float32 copies of the
    operators, with dP/du accumulated from the edges (``du_edges``) rather than from the
    positions, whose large cancelling coefficients (1/det of small UV triangles) would
    lose ~1e-3 of T in float32. Frames then agree with float64 to ~1e-6 (tests bound it).
    """

    faces: np.ndarray
    incidence: sp.csr_matrix
    du: sp.csr_matrix
    edges: sp.csr_matrix
    du_edges: sp.csr_matrix | None = None

    @classmethod
    def build(cls, V: np.ndarray, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray) -> "FrameField":
        """Weights from the rest pose V (n,3) mm with layout (uv (K,2), uv_faces (m,3))."""
        F, uv, uv_faces = _check(F, uv, uv_faces)
        V = np.asarray(V, dtype=np.float64)
        n, m = len(V), len(F)
        d1, d2, det, tri_sign = _triangle_signs(uv, uv_faces)
        vert_sign = _vertex_signs(F, tri_sign, n)
        use = (tri_sign[:, None] != 0) & (tri_sign[:, None] == vert_sign[F])
        inv_det = np.divide(1.0, det, out=np.zeros(m), where=tri_sign != 0)
        # [dP/du]_f = a P0 + b P1 + c P2 with e1 = P1 − P0, e2 = P2 − P0
        cb, cc = d2[:, 1] * inv_det, -d1[:, 1] * inv_det
        coef = np.stack([-(cb + cc), cb, cc], axis=1)                        # (m,3) per corner
        w = corner_angles(V, F) * use                                        # (m,3) per vertex
        rows = np.repeat(F.ravel(), 3)                                       # vertex receiving
        cols = np.tile(F, (1, 3)).ravel()                                    # corner providing
        vals = (w.ravel()[:, None] * np.repeat(coef, 3, axis=0)).ravel()
        du = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
        incidence = sp.csr_matrix((np.ones(3 * m), (F.ravel(), np.repeat(np.arange(m), 3))),
                                  shape=(n, m))
        # the same sum on the edges: [dP/du]_f = cb e1 + cc e2
        du_edges = sp.csr_matrix((np.concatenate([w.ravel() * np.repeat(cb, 3), w.ravel() * np.repeat(cc, 3)]),
                                  (np.tile(F.ravel(), 2), np.concatenate([np.repeat(np.arange(m), 3),
                                                                          m + np.repeat(np.arange(m), 3)]))),
                                 shape=(n, 2 * m))
        rows = np.repeat(np.arange(2 * m), 2)
        cols = np.stack([np.column_stack([F[:, 1], F[:, 0]]), np.column_stack([F[:, 2], F[:, 0]])]).ravel()
        edges = sp.csr_matrix((np.tile([1.0, -1.0], 2 * m), (rows, cols)), shape=(2 * m, n))
        return cls(F, incidence, du, edges, du_edges)

    def operators(self) -> dict[str, sp.csr_matrix]:
        """The sparse operators by field name (``incidence``, ``du``, ``edges``,
        ``du_edges``): what :meth:`from_operators` takes back (e.g. from a model's cache)."""
        return {k: getattr(self, k) for k in OPERATORS}

    @classmethod
    def from_operators(cls, F: np.ndarray, operators: dict) -> "FrameField | None":
        """The FrameField of triangles F (m,3) over n vertices with the CSR ``operators`` of
        :meth:`operators` (as stored: no copy, so frames are those of the field that was
        stored bit for bit), if all are there with the shapes :meth:`build` makes, else None
        (then build it: ~70 ms of a level-1 PDM load)."""
        F = np.asarray(F, np.int64)
        m = len(F)
        inc = operators.get("incidence")
        n = inc.shape[0] if sp.issparse(inc) else -1
        want = {"incidence": (n, m), "du": (n, n), "edges": (2 * m, n), "du_edges": (n, 2 * m)}
        if not all(sp.issparse(a := operators.get(k)) and a.format == "csr" and a.shape == shape
                   for k, shape in want.items()):
            return None
        return cls(F, *(operators[k] for k in OPERATORS))

    def frames(self, V: np.ndarray, dtype=np.float64) -> np.ndarray:
        """Frames (n,3,3) or (frames,n,3,3) of ``dtype`` (float64 or float32, see the class
        notes), rows (T, B, N), of poses V (n,3) or (frames,n,3)."""
        if np.dtype(dtype) == np.float32:
            Vb, lead = _flatten_frames(V)
            out = np.empty(Vb.shape[:2] + (3, 3), np.float32)
            for b, pose in enumerate(Vb):
                T, B, N, has_n = self._rows32(pose)
                for i, row in enumerate((T, B, N)):
                    out[b, :, i, :] = row.T
                out[b, ~has_n] = np.eye(3)
            return out.reshape(*lead, Vb.shape[1], 3, 3)
        T, B, N, has_n, lead = self._rows(V, dtype)
        frames = np.stack([T, B, N], axis=-2)
        frames[~has_n] = np.eye(3)
        return frames.reshape(*lead, T.shape[1], 3, 3)

    def rows32(self, V: np.ndarray) -> list[tuple]:
        """The float32 frames of poses V (…,n,3), one (T, B, N (3,n) float32 component-major,
        has_n (n,) bool) per pose in V's flattened order (:meth:`_rows32`), for
        :meth:`to_world` and :meth:`to_frame` of the same poses (the frames computed once)."""
        Vb, _ = _flatten_frames(V)
        return [self._rows32(pose) for pose in Vb]

    def to_frame(self, V: np.ndarray, W: np.ndarray, rows: list | None = None) -> np.ndarray:
        """World vectors W (…,n,3) of poses V (…,n,3) in their float32 frames (…,n,3) float32:
        ``C_i = row_i · W`` (identity frames where there is no normal), the inverse of
        :meth:`to_world`; equal to ``einsum("...nij,...nj->...ni", frames(V, np.float32), W)``
        within float32 rounding. ``rows``: :meth:`rows32` of V where already computed."""
        Vb, lead = _flatten_frames(V)
        rows = self.rows32(Vb) if rows is None else rows
        Wb = np.asarray(W, np.float32).reshape(Vb.shape)
        out = np.empty((len(Vb), 3, Vb.shape[1]), np.float32)           # component-major
        for b, (T, B, N, has_n) in enumerate(rows):
            Wc = np.ascontiguousarray(Wb[b].T)                           # (3,n)
            for i, row in enumerate((T, B, N)):
                np.multiply(row[0], Wc[0], out=out[b, i])
                out[b, i] += row[1] * Wc[1]
                out[b, i] += row[2] * Wc[2]
                out[b, i, ~has_n] = Wc[i, ~has_n]                        # identity frames
        return out.transpose(0, 2, 1).reshape(*lead, Vb.shape[1], 3)

    def to_world(self, V: np.ndarray, C: np.ndarray, dtype=np.float64, rows: list | None = None) -> np.ndarray:
        """Frame coordinates C (…,n,3) of poses V (…,n,3) as world vectors ``Σ_j C_j row_j``.

        Equal to ``einsum("...nji,...nj->...ni", frames(V), C)`` without forming the frames;
        ``dtype`` float32 computes the frames and the sum in float32 (class notes), one pose
        at a time component-major (:meth:`_rows32`; ``rows``: :meth:`rows32` of V where
        already computed).
        """
        if np.dtype(dtype) == np.float32:
            Vb, lead = _flatten_frames(V)
            Cb = np.asarray(C, np.float32).reshape(Vb.shape)
            out = np.empty((len(Vb), 3, Vb.shape[1]), np.float32)       # component-major
            for b, pose in enumerate(Vb):
                T, B, N, has_n = self._rows32(pose) if rows is None else rows[b]
                Cc = np.ascontiguousarray(Cb[b].T)                       # (3,n)
                for j in range(3):
                    np.multiply(Cc[0], T[j], out=out[b, j])
                    out[b, j] += Cc[1] * B[j]
                    out[b, j] += Cc[2] * N[j]
                    out[b, j, ~has_n] = Cc[j, ~has_n]                   # identity frames
            return out.transpose(0, 2, 1).reshape(*lead, Vb.shape[1], 3)
        T, B, N, has_n, lead = self._rows(V, dtype)
        C = np.asarray(C).reshape(T.shape)
        out = C[..., 0:1] * T
        out += C[..., 1:2] * B
        out += C[..., 2:3] * N
        out[~has_n] = C[~has_n]                     # identity frames
        return out.reshape(*lead, T.shape[1], 3)

    def normal_rows(self, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What a normal map of pose V (n,3) reads of its frames (float32, :meth:`frames`
        with ``dtype=np.float32``, rows T and N, identity frames where there is no normal)
        without forming them: ``TN`` (6,n) float32, rows (Tx, Ty, Tz, Nx, Ny, Nz), and the
        triangles' edges (3,2m) float32 the frames were computed from (component rows; e1
        = P1 − P0 in columns :m, e2 = P2 − P0 after), for
        :meth:`service.geometry.normal_map.NormalMapper.normal_map`'s ``rows``."""
        T, _, N, has_n, e = self._rows32(V, edges=True)
        TN = np.concatenate([T, N])
        if not has_n.all():
            TN[:, ~has_n] = np.array([1, 0, 0, 0, 0, 1], np.float32)[:, None]
        return TN, e

    def _rows32(self, V: np.ndarray, edges: bool = False):
        """T, B, N (3,n) float32, component-major, and has_n (n,) of one pose V (n,3) (with
        ``edges``, also the triangles' float32 edges (3,2m) they were computed from): the
        float32 path of :meth:`_rows`, on the compiled kernels of
        :mod:`service.geometry.frame_rows` (issue 23: the sparse products and ~30 passes over
        (3,n) rows before, the same arithmetic in the same order, bit for bit: tests)."""
        from service.geometry import ranges
        from service.geometry.frame_rows import (   # Numba (issue 23)
            finish_rows, triangle_edges, triangle_rows, vertex_rows,
        )

        edges_op, du_op, inc_op = self._kernel_operators
        m, n = len(self.faces), self.incidence.shape[0]
        # the edges differenced in float64 and rounded once, their cross products (from the
        # corners where the edge operator is the faces' own); T, N per vertex from the
        # float32 operators; the fallbacks and B (module frame_rows)
        e = np.empty((3, 2 * m), np.float32)
        fn = np.empty((3, m), np.float32)
        V = np.ascontiguousarray(V, np.float64)
        if self._edge_faces is not None:
            ranges.run(triangle_edges, m, self._edge_faces, V, m, e, fn)
        else:
            ranges.run(triangle_rows, m, *edges_op, V, m, e, fn)
        T, N, B = (np.empty((3, n), np.float32) for _ in range(3))
        tmax = np.empty(n, np.float32)
        ranges.run(vertex_rows, n, *du_op, e, *inc_op, fn, T, N, tmax)
        threshold = CANCEL_RTOL * np.maximum(tmax.max(initial=np.float32(0)), np.float32(0))
        has_n = np.empty(n, np.bool_)
        ranges.run(finish_rows, n, T, N, np.float32(threshold), B, has_n)
        if edges:
            return T, B, N, has_n, e
        return T, B, N, has_n

    @cached_property
    def _kernel_operators(self) -> tuple[tuple, tuple, tuple]:
        """(ptr (r+1,) uint64, idx (nnz,) uint32, val) of ``edges`` (float64) and of the float32
        ``du_edges`` and ``incidence``: the CSR arrays :mod:`service.geometry.frame_rows` reads,
        with unsigned indices (Numba then checks no index for wraparound: 4.2 → 2.4 ms of the
        level-1 frames), made on the first float32 call."""
        return tuple((A.indptr.astype(np.uint64), A.indices.astype(np.uint32), A.data)
                     for A in (self.edges, self._float32[1], self._float32[0]))

    @cached_property
    def _edge_faces(self) -> np.ndarray | None:
        """``faces`` (m,3) uint32 if ``edges`` is exactly their edge operator (rows t: +1 at
        corner 1 and −1 at corner 0; rows m + t: +1 at corner 2, −1 at corner 0; as
        :meth:`build` makes it, in any column order), so that
        :func:`~service.geometry.frame_rows.triangle_edges` may difference the corners
        instead of reading the operator; else None."""
        E, F = self.edges, np.asarray(self.faces, np.int64)
        m = len(F)
        if E.shape[0] != 2 * m or not np.array_equal(E.indptr, 2 * np.arange(2 * m + 1)):
            return None
        cols, vals = E.indices.reshape(2 * m, 2), E.data.reshape(2 * m, 2)
        plus = np.where(vals[:, 0] == 1, cols[:, 0], cols[:, 1])
        minus = np.where(vals[:, 0] == 1, cols[:, 1], cols[:, 0])
        signs = np.sort(vals, axis=1)
        ok = ((signs == [-1.0, 1.0]).all() and np.array_equal(plus, np.concatenate([F[:, 1], F[:, 2]]))
              and np.array_equal(minus, np.concatenate([F[:, 0], F[:, 0]])))
        return np.ascontiguousarray(F, np.uint32) if ok else None

    @cached_property
    def _float32(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """(incidence, du_edges) as float32 (made on the first float32 call)."""
        if self.du_edges is None:
            raise ValueError("this FrameField has no du_edges (build it with FrameField.build)")
        return self.incidence.astype(np.float32), self.du_edges.astype(np.float32)

    def _rows(self, V: np.ndarray, dtype=np.float64):
        """T, B, N (b,n,3) float64, has_n (b,n) and the leading shape of poses V (the float32
        frames are :meth:`_rows32`'s)."""
        Vb, lead = _flatten_frames(V)
        nb, n = Vb.shape[:2]
        m = len(self.faces)
        if np.dtype(dtype) != np.float64:
            raise ValueError(f"dtype must be float64 or float32, got {dtype}")
        # vertex-major (n, 3·b) throughout: sparse products instead of gathers, no copies for b = 1
        Vn = Vb.transpose(1, 0, 2).reshape(n, 3 * nb)
        e = self.edges @ Vn                                                        # (2m, 3b)
        T = (self.du @ Vn).reshape(n, nb, 3)
        e = e.reshape(2, m, nb, 3)
        fn = _cross(e[0], e[1])                                                    # (m,b,3)
        N = _normalize((self.incidence @ fn.reshape(m, 3 * nb)).reshape(n, nb, 3))
        T -= np.einsum("nbd,nbd->nb", T, N)[..., None] * N
        has_n = np.einsum("nbd,nbd->nb", N, N) > 0.25
        tn = np.sqrt(np.einsum("nbd,nbd->nb", T, T))
        weak = has_n & ~(tn > CANCEL_RTOL * np.maximum(np.abs(T).max(), 1e-300))
        if weak.any():
            Nw = N[weak]
            axis = np.eye(3)[np.argmin(np.abs(Nw), axis=1)]
            T[weak] = axis - np.einsum("kd,kd->k", axis, Nw)[:, None] * Nw
        T = _normalize(T)
        B = _cross(N, T)
        return (T.transpose(1, 0, 2), B.transpose(1, 0, 2), N.transpose(1, 0, 2),
                has_n.T, lead)

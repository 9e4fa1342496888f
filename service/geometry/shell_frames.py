"""Float32 tangent frames of a thin-shell pose from its displacement, and the per-frame mesh
of bickel2008 §5.3 "at run-time" built on them: the shell plus corrections "stored
per-vertex in local tangent frames", rotated into the current shell's frames, head pose put
back — compiled (Numba, ``nogil``) over a cache-friendly vertex order. Both methods' per-frame
meshes use it: the pose-space kinds (:meth:`ShellFrames.shell`, frames and composition in
one pass) and the PDM (:mod:`service.methods.pdm.shell_mesh`: the frames once with
:meth:`ShellFrames.rows`, then the medium fallback in them, :meth:`ShellFrames.coordinates`,
and the mesh, :meth:`ShellFrames.place`, with the rest pose in float64).

The frames are those of :class:`service.geometry.tangent_frames.FrameField` (weights frozen
at the rest pose; rows T, B, N; N the area-weighted normal, T the rest-corner-angle-weighted
dP/du Gram-Schmidt-orthogonalized against N, ``B = N × T``; the same fallbacks), computed
for a shell ``X = X̄ + u`` from

* the **rest edges** of X̄ (float64 differences rounded once to float32, stored) plus the
  edges of the float32 displacement ``u = B u_H`` — the positions are never differenced in
  float32 (at ~100 mm from the origin that would lose ~1e-5 mm per edge), the displacement
  (a few mm) is, and the rest edges carry the rest of the edge;
* per-triangle dP/du ``cb e1 + cc e2`` (UV coefficients), accumulated at each vertex over
  its incident triangles with the rest corner angles (``angle`` of the vertex → triangle
  incidence), the normal as the sum of the incident ``e1 × e2``;
* a **vertex order** of small bandwidth (reverse Cuthill–McKee of the mesh graph, triangles
  sorted by their first vertex in that order), in which a vertex's incident triangles and
  their corners lie in nearby memory. Callers move per-vertex arrays into that order with
  :meth:`ShellFrames.to_internal` and back with :meth:`ShellFrames.to_vertices`.

Per frame the displacement ``u = B u_H`` (:func:`displacements`, the basis rows stored in
the internal order), a pass over the triangles (:func:`triangle_terms`: dP/du and e1 × e2) and two over
the vertices (:func:`frame_sums`, then :func:`compose`): the first accumulates T and N at
every vertex (the normal normalized, T projected off it), the second
needs the largest tangent component over the whole mesh (FrameField's threshold for a
cancelled tangent) and finishes the frames, rotates the corrections, adds the rest pose and
the displacement and applies the head pose. Both run over contiguous vertex ranges on
:func:`service.geometry.ranges.kernel_threads` threads.

Why compiled: the same operations as NumPy array passes read and write every per-triangle
and per-vertex temporary once per operation (about 40 passes over (3,m) and (3,n) float32
rows); fused per vertex they read the displacement, the triangles and the incidence once.
Measured in :mod:`benchmarks.pose_space_report`'s speed section (issue 18's report).

Arrays are component-major (3,n) float32 (contiguous rows per coordinate). Against
:meth:`FrameField.frames` in float64 of the same shell the frames agree to ~1e-6 (tests
bound it). The frames of the smallest triangles also turn with the float32 displacement's
own rounding (~1e-6 mm against the float64 product ``B u_H``; level 1 has edges down to
0.009 mm): ~5e-5 against the frames of the float64 product at level 1, where FrameField's
float32 frames of the BLAS float32 product measured 1.3e-4.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit, uint64
from scipy.sparse.csgraph import reverse_cuthill_mckee

from service.geometry import ranges
from service.geometry.normals import corner_angles
from service.geometry.tangent_frames import CANCEL_RTOL, _triangle_signs, _vertex_signs

#: LLVM flags of the kernels: reassociation and contraction only (no finite-math
#: assumptions, so the zero tests of the fallbacks keep their meaning). The kernels index
#: with unsigned integers (loop ranges, ``faces``, ``ptr``, ``tri``, ``order``, the points'
#: ``at`` and ``dest``): Numba checks every signed index for a negative value to wrap around
#: (measured ~40 % of a gather-heavy loop)
FASTMATH = {"reassoc", "contract"}


def locality_order(F: np.ndarray, n: int) -> np.ndarray:
    """A vertex order (n,) of small bandwidth: reverse Cuthill–McKee of the mesh's edge graph."""
    F = np.asarray(F, np.int64)
    A = sp.csr_matrix((np.ones(F.size, np.int8), (F.ravel(), np.roll(F, 1, axis=1).ravel())), shape=(n, n))
    return np.asarray(reverse_cuthill_mckee((A + A.T).tocsr(), symmetric_mode=True), np.int64)


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def _unit(x, y, z, xx):
    """(x, y, z) / sqrt(xx) in float32, xx its squared length; zeros where xx is not > 0."""
    if xx > 0:
        s = np.float32(1.0) / np.sqrt(xx)
        return x * s, y * s, z * s
    return np.float32(0.0), np.float32(0.0), np.float32(0.0)


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def _row_product(B, k, u):
    """``u B[k]`` (3 float32): row k of a basis B (n,h) times handle displacements u (3,h)."""
    x = y = z = np.float32(0.0)
    for j in range(uint64(B.shape[1])):
        b = B[k, j]
        x += b * u[0, j]
        y += b * u[1, j]
        z += b * u[2, j]
    return x, y, z


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def displacements(lo, hi, B, u, U):
    """Vertices [lo, hi): the shell displacement ``U[:, k] = u B[k]`` (3,n) float32 of handle
    displacements u (3,h) float32 and the thin-shell basis rows B (n,h) float32 in the
    internal order (bickel2008 §4: u = B u_H, one row of B per vertex, read once)."""
    for k in range(uint64(lo), uint64(hi)):
        U[0, k], U[1, k], U[2, k] = _row_product(B, k, u)


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def displacement_pair(lo, hi, B, Bc, u, U, Uc):
    """Vertices [lo, hi): :func:`displacements` of two bases B, Bc (n,h) float32 for the same
    u (3,h) in one pass, ``U = u Bᵀ`` and ``Uc = u Bcᵀ`` (3,n): row k of both read back to
    back (two streams in flight instead of one pass each; each row's sum is the same
    :func:`_row_product`, so both equal :func:`displacements` bit for bit)."""
    for k in range(uint64(lo), uint64(hi)):
        U[0, k], U[1, k], U[2, k] = _row_product(B, k, u)
        Uc[0, k], Uc[1, k], Uc[2, k] = _row_product(Bc, k, u)


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def triangle_terms(lo, hi, U, F, rest, out):
    """Triangles [lo, hi): ``out[t] = (dP/du, e1 × e2)`` (m,6) float32 of the shell whose
    displacement is U (3,n) (internal order); ``rest`` (m,8) holds the rest edges e1, e2 and
    the UV coefficients cb, cc of dP/du = cb e1 + cc e2."""
    for t in range(uint64(lo), uint64(hi)):
        a, b, c = F[t, 0], F[t, 1], F[t, 2]
        e1x = (U[0, b] - U[0, a]) + rest[t, 0]
        e1y = (U[1, b] - U[1, a]) + rest[t, 1]
        e1z = (U[2, b] - U[2, a]) + rest[t, 2]
        e2x = (U[0, c] - U[0, a]) + rest[t, 3]
        e2y = (U[1, c] - U[1, a]) + rest[t, 4]
        e2z = (U[2, c] - U[2, a]) + rest[t, 5]
        cb, cc = rest[t, 6], rest[t, 7]
        out[t, 0] = cb * e1x + cc * e2x
        out[t, 1] = cb * e1y + cc * e2y
        out[t, 2] = cb * e1z + cc * e2z
        out[t, 3] = e1y * e2z - e1z * e2y
        out[t, 4] = e1z * e2x - e1x * e2z
        out[t, 5] = e1x * e2y - e1y * e2x


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def frame_sums(lo, hi, terms, ptr, tri, angle, T, N, tmax):
    """Vertices [lo, hi): unit normal N and tangent T projected off it (3,n) float32, and
    tmax (n,) the largest |T| component, from the incident triangles' :func:`triangle_terms`
    (T the angle-weighted sum of dP/du, N the normalized sum of e1 × e2)."""
    for k in range(uint64(lo), uint64(hi)):
        tx = ty = tz = np.float32(0.0)
        nx = ny = nz = np.float32(0.0)
        for q in range(ptr[k], ptr[k + uint64(1)]):
            t = tri[q]
            w = angle[q]
            tx += w * terms[t, 0]
            ty += w * terms[t, 1]
            tz += w * terms[t, 2]
            nx += terms[t, 3]
            ny += terms[t, 4]
            nz += terms[t, 5]
        nx, ny, nz = _unit(nx, ny, nz, nx * nx + ny * ny + nz * nz)
        d = tx * nx + ty * ny + tz * nz
        tx, ty, tz = tx - d * nx, ty - d * ny, tz - d * nz
        T[0, k], T[1, k], T[2, k] = tx, ty, tz
        N[0, k], N[1, k], N[2, k] = nx, ny, nz
        tmax[k] = max(abs(tx), abs(ty), abs(tz))


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def compose(lo, hi, T, N, floor, U, rest, C, R, t, order, aligned, world, Bout):
    """Vertices [lo, hi): finish the frames of :func:`frame_sums` (a tangent with
    ``|T|² ≤ floor`` replaced by the least-aligned axis projected off N, as FrameField;
    T normalized; ``B = N × T``) and compose ``X = rest + U + (C₀T + C₁B + C₂N)`` (C as is
    where there is no normal). Writes, where the output has columns: ``aligned`` (3,n) X
    in the internal order; ``world`` (n,3) ``Rᵀ (X − t)`` at vertex ``order[k]``;
    T normalized in place and ``Bout`` (3,n)."""
    want_aligned = aligned.shape[1] > 0
    want_world = world.shape[0] > 0
    want_frames = Bout.shape[1] > 0
    for k in range(uint64(lo), uint64(hi)):
        nx, ny, nz = N[0, k], N[1, k], N[2, k]
        tx, ty, tz = T[0, k], T[1, k], T[2, k]
        has_n = nx != 0 or ny != 0 or nz != 0
        tt = tx * tx + ty * ty + tz * tz
        if has_n and not tt > floor:
            ax, ay, az = abs(nx), abs(ny), abs(nz)
            j = 0 if ax <= ay and ax <= az else (1 if ay <= az else 2)
            n0, n1, n2 = np.float64(nx), np.float64(ny), np.float64(nz)
            d = n0 if j == 0 else (n1 if j == 1 else n2)
            tx = np.float32((1.0 if j == 0 else 0.0) - d * n0)
            ty = np.float32((1.0 if j == 1 else 0.0) - d * n1)
            tz = np.float32((1.0 if j == 2 else 0.0) - d * n2)
            tt = tx * tx + ty * ty + tz * tz
        tx, ty, tz = _unit(tx, ty, tz, tt)
        bx = ny * tz - nz * ty
        by = nz * tx - nx * tz
        bz = nx * ty - ny * tx
        c0, c1, c2 = C[0, k], C[1, k], C[2, k]
        if has_n:
            wx = c0 * tx + c1 * bx + c2 * nx
            wy = c0 * ty + c1 * by + c2 * ny
            wz = c0 * tz + c1 * bz + c2 * nz
        else:
            wx, wy, wz = c0, c1, c2
        x = (rest[0, k] + U[0, k]) + wx
        y = (rest[1, k] + U[1, k]) + wy
        z = (rest[2, k] + U[2, k]) + wz
        if want_aligned:
            aligned[0, k], aligned[1, k], aligned[2, k] = x, y, z
        if want_world:
            x, y, z = x - t[0], y - t[1], z - t[2]
            v = order[k]
            for i in range(3):
                world[v, i] = x * R[0, i] + y * R[1, i] + z * R[2, i]
        if want_frames:
            T[0, k], T[1, k], T[2, k] = tx, ty, tz
            Bout[0, k], Bout[1, k], Bout[2, k] = bx, by, bz


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def frame_coordinates(lo, hi, at, dest, T, B, N, W, base, sub, out):
    """Points [lo, hi) of a list sorted by vertex: ``out[dest[p]] = Frame(v) (base[:, v] +
    W[:, v]) − sub[:, v]`` (P,3) at the internal position ``v = at[p]``, in the finished
    frames T, B, N (3,n) of :meth:`ShellFrames.rows` (the vector unrotated where the vertex
    has no normal, FrameField's identity frame). With ``at`` ascending the vertex rows are
    read in order and each point costs one scattered 12-byte write."""
    for p in range(uint64(lo), uint64(hi)):
        v = at[p]
        wx = base[0, v] + W[0, v]
        wy = base[1, v] + W[1, v]
        wz = base[2, v] + W[2, v]
        nx, ny, nz = N[0, v], N[1, v], N[2, v]
        if nx != 0 or ny != 0 or nz != 0:
            c0 = T[0, v] * wx + T[1, v] * wy + T[2, v] * wz
            c1 = B[0, v] * wx + B[1, v] * wy + B[2, v] * wz
            c2 = nx * wx + ny * wy + nz * wz
        else:
            c0, c1, c2 = wx, wy, wz
        q = dest[p]
        out[q, 0] = c0 - sub[0, v]
        out[q, 1] = c1 - sub[1, v]
        out[q, 2] = c2 - sub[2, v]


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def compose_framed(lo, hi, T, B, N, U, rest, C, R, t, order, aligned, world):
    """Vertices [lo, hi): ``X = (rest + U) + (C₀T + C₁B + C₂N)`` in the finished frames of
    :meth:`ShellFrames.rows` (C as is where there is no normal), C (n,3) per internal
    position; the arithmetic in the type of ``rest`` (float64: X̄ exact, the float32 terms
    added to it). Writes, where the output has rows: ``aligned`` (n,3) X at vertex
    ``order[k]``; ``world`` (n,3) float32 ``(X − t)`` rounded to float32, then times R
    (``Rᵀ (X − t)``, R float32) at vertex ``order[k]``."""
    want_aligned = aligned.shape[0] > 0
    want_world = world.shape[0] > 0
    for k in range(uint64(lo), uint64(hi)):
        nx, ny, nz = N[0, k], N[1, k], N[2, k]
        c0, c1, c2 = C[k, 0], C[k, 1], C[k, 2]
        if nx != 0 or ny != 0 or nz != 0:
            wx = c0 * T[0, k] + c1 * B[0, k] + c2 * nx
            wy = c0 * T[1, k] + c1 * B[1, k] + c2 * ny
            wz = c0 * T[2, k] + c1 * B[2, k] + c2 * nz
        else:
            wx, wy, wz = c0, c1, c2
        x = (rest[0, k] + U[0, k]) + wx
        y = (rest[1, k] + U[1, k]) + wy
        z = (rest[2, k] + U[2, k]) + wz
        v = order[k]
        if want_aligned:
            aligned[v, 0], aligned[v, 1], aligned[v, 2] = x, y, z
        if want_world:
            x32 = np.float32(x - t[0])
            y32 = np.float32(y - t[1])
            z32 = np.float32(z - t[2])
            for i in range(3):
                world[v, i] = x32 * R[0, i] + y32 * R[1, i] + z32 * R[2, i]


@dataclass(frozen=True)
class ShellFrames:
    """Tangent frames of shells ``X̄ + u`` in an internal vertex order, and the per-frame
    shell mesh on them (module docstring).

    Attributes
    ----------
    order : (n,) uint32      internal position k holds vertex ``order[k]``
    rank : (n,) uint32       the inverse: vertex v is at internal position ``rank[v]``
    faces : (m,3) uint32     triangles over internal positions (sorted by first corner)
    rest : (m,8) float32     per triangle the rest edges e1 = P1 − P0, e2 = P2 − P0 of X̄ and
                             cb, cc with dP/du = cb e1 + cc e2 (0 for UV-degenerate ones)
    ptr : (n+1,) uint64, tri : (3m,) uint32, angle : (3m,) float32
                             vertex → incident triangles (CSR by internal position, triangles
                             ascending) and the rest corner angle there (0 where the triangle's
                             UV handedness is not the vertex's majority one)
    """

    order: np.ndarray
    rank: np.ndarray
    faces: np.ndarray
    rest: np.ndarray
    ptr: np.ndarray
    tri: np.ndarray
    angle: np.ndarray

    @classmethod
    def build(cls, V: np.ndarray, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray) -> "ShellFrames":
        """From the rest pose X̄ (n,3) mm, triangles F (m,3) and the UV layout (uv (K,2),
        uv_faces (m,3)) — the inputs of :meth:`FrameField.build`."""
        V = np.asarray(V, np.float64)
        F = np.asarray(F, np.int64)
        uv = np.asarray(uv, np.float64)
        uv_faces = np.asarray(uv_faces, np.int64)
        n, m = len(V), len(F)
        d1, d2, det, tri_sign = _triangle_signs(uv, uv_faces)
        use = (tri_sign[:, None] != 0) & (tri_sign[:, None] == _vertex_signs(F, tri_sign, n)[F])
        inv_det = np.divide(1.0, det, out=np.zeros(m), where=tri_sign != 0)
        cb, cc = d2[:, 1] * inv_det, -d1[:, 1] * inv_det
        w = corner_angles(V, F) * use                                             # (m,3)
        order = locality_order(F, n)
        rank = np.empty(n, np.int64)
        rank[order] = np.arange(n)
        Fi = rank[F]
        tri = np.argsort(Fi.min(axis=1), kind="stable")
        Fi, F, cb, cc, w = Fi[tri], F[tri], cb[tri], cc[tri], w[tri]
        rows, cols = Fi.ravel(), np.repeat(np.arange(m), 3)
        inc = np.lexsort((cols, rows))                                            # by vertex, then triangle
        ptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))]).astype(np.int64)
        rest = np.column_stack([V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]], cb, cc]).astype(np.float32)
        return cls(order.astype(np.uint32), rank.astype(np.uint32), Fi.astype(np.uint32), rest,
                   ptr.astype(np.uint64), cols[inc].astype(np.uint32), w.ravel()[inc].astype(np.float32))

    def arrays(self) -> dict[str, np.ndarray]:
        """The fields by name (what :meth:`from_arrays` reads back, e.g. from a model's cache)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_arrays(cls, arrays: dict, n: int, m: int) -> "ShellFrames | None":
        """The ShellFrames of :meth:`arrays` (e.g. memory-mapped from a model's cache) if they
        are all there, of the dtypes and shapes :meth:`build` makes for n vertices and m
        triangles, else None (then build them). Level-1 PDM: 77 ms of a load not spent."""
        want = {"order": (np.uint32, (n,)), "rank": (np.uint32, (n,)), "faces": (np.uint32, (m, 3)),
                "rest": (np.float32, (m, 8)), "ptr": (np.uint64, (n + 1,)), "tri": (np.uint32, (3 * m,)),
                "angle": (np.float32, (3 * m,))}
        if not all(isinstance(a := arrays.get(k), np.ndarray) and a.dtype == dt and a.shape == shape
                   and a.flags.c_contiguous for k, (dt, shape) in want.items()):
            return None
        return cls(**{k: arrays[k] for k in want})

    @property
    def n_vertices(self) -> int:
        return len(self.order)

    def to_internal(self, X: np.ndarray) -> np.ndarray:
        """Per-vertex values X (n,3) in vertex order → (3,n) float32 in the internal order."""
        Xt = np.ascontiguousarray(np.asarray(X).T, dtype=np.float32)             # contiguous rows
        return np.take(Xt, self.order, axis=1)

    def to_vertices(self, Xi: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Internal-order (3,n) values → (n,3) in vertex order (into ``out`` if given)."""
        out = np.empty((self.n_vertices, 3), Xi.dtype) if out is None else out
        for i in range(3):
            out[:, i] = np.take(Xi[i], self.rank)
        return out

    def internal_basis(self, basis: np.ndarray) -> np.ndarray:
        """The thin-shell basis (n,h) with its rows in the internal order, C-contiguous
        float32 (what :meth:`displacement` reads: one vertex's row contiguous)."""
        return np.ascontiguousarray(np.asarray(basis)[self.order], dtype=np.float32)

    def displacement(self, B: np.ndarray, u_H: np.ndarray, threads: int | None = None,
                     out: np.ndarray | None = None) -> np.ndarray:
        """U (3,n) float32, internal order (into ``out`` if given): the shell displacement
        ``B u_H`` of handle displacements u_H (h,3) mm, B from :meth:`internal_basis`. Equals
        :func:`~service.geometry.thin_shell.apply_basis` up to float32 summation order."""
        u = np.ascontiguousarray(np.asarray(u_H, np.float32).T)
        U = np.empty((3, self.n_vertices), np.float32) if out is None else out
        ranges.run(displacements, self.n_vertices, B, u, U, threads=threads)
        return U

    def _sums(self, U: np.ndarray, threads: int | None,
              frames: tuple | None = None) -> tuple[np.ndarray, np.ndarray, np.float32]:
        """:func:`frame_sums` over every vertex: T, N (3,n) (into ``frames`` if given) and
        FrameField's cancellation floor."""
        n = self.n_vertices
        T, N = frames or (np.empty((3, n), np.float32), np.empty((3, n), np.float32))
        tmax = ranges.scratch("shell_frames.tmax", (n,))
        terms = ranges.scratch("shell_frames.terms", (len(self.faces), 6))
        ranges.run(triangle_terms, len(self.faces), U, self.faces, self.rest, terms, threads=threads)
        ranges.run(frame_sums, n, terms, self.ptr, self.tri, self.angle, T, N, tmax, threads=threads)
        floor = np.float32(CANCEL_RTOL * max(float(tmax.max(initial=0.0)), 1e-30)) ** 2
        return T, N, floor

    def rows(self, U: np.ndarray, threads: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """T, B, N (3,n) float32 (internal order) of the shell X̄ + u, u given as U (3,n)
        float32 in the internal order (:meth:`to_internal`); zero rows where a vertex has
        no normal (and so no frame)."""
        U = np.ascontiguousarray(U, np.float32)
        T, N, floor = self._sums(U, threads)
        B = np.empty_like(T)
        ranges.run(compose, self.n_vertices, T, N, floor, U, U, U, _EYE, _ZERO3, self.order,
                   _NO_ALIGNED, _NO_WORLD, B, threads=threads)
        return T, B, N

    def shell(self, U: np.ndarray, rest: np.ndarray, C: np.ndarray, R: np.ndarray | None = None,
              t: np.ndarray | None = None, aligned: bool = False, world: np.ndarray | None = None,
              threads: int | None = None) -> np.ndarray | None:
        """The detailed shell ``X = rest + U + Frame(X̄ + U)ᵀ C`` of one frame (§5.3 run time).

        Parameters
        ----------
        U : (3,n) float32      shell displacement B u_H, internal order, mm
        rest : (3,n) float32   the rest pose X̄, internal order, mm
        C : (3,n) float32      corrections in the tangent frames (T, B, N), internal order, mm
        R, t : (3,3), (3,)     head pose of the frame (world = Rᵀ (X − t)), with ``world``
        aligned : bool         return X (3,n) float32 in the internal order (neutral-aligned)
        world : (n,3) float32  filled with Rᵀ (X − t) in vertex order, if given

        Vertices without a normal take C unrotated (FrameField's identity frame).
        """
        U = np.ascontiguousarray(U, np.float32)
        n = self.n_vertices
        T, N, floor = self._sums(U, threads, (ranges.scratch("shell_frames.T", (3, n)),
                                              ranges.scratch("shell_frames.N", (3, n))))
        Xa = np.empty((3, n), np.float32) if aligned else _NO_ALIGNED
        W = _NO_WORLD if world is None else world
        R32 = _EYE if R is None else np.ascontiguousarray(R, np.float32)
        t32 = _ZERO3 if t is None else np.ascontiguousarray(t, np.float32)
        ranges.run(compose, n, T, N, floor, U, np.ascontiguousarray(rest, np.float32),
                   np.ascontiguousarray(C, np.float32), R32, t32, self.order, Xa, W, _NO_FRAMES,
                   threads=threads)
        return Xa if aligned else None


    def points(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points on the vertices ``vertices`` (P,) (e.g. UV points, several per seam vertex)
        as :meth:`coordinates` reads them: their internal positions ascending and, for each,
        the point's index, both (P,) uint32 (the kernel's indices are unsigned)."""
        at = self.rank[np.asarray(vertices, np.int64)]
        dest = np.argsort(at, kind="stable")
        return at[dest], dest.astype(np.uint32)

    def coordinates(self, frames: tuple, W: np.ndarray, base: np.ndarray, sub: np.ndarray,
                    points: tuple, out: np.ndarray | None = None,
                    threads: int | None = None) -> np.ndarray:
        """(P,3) float32: the world vectors ``base + W`` (3,n) in the frames T, B, N of
        :meth:`rows` less ``sub`` (3,n), at the points ``points`` of :meth:`points`
        (:func:`frame_coordinates`; FrameField's ``to_frame`` of the shell's frames, gathered)."""
        T, B, N = frames
        at, dest = points
        out = np.empty((len(at), 3), np.float32) if out is None else out
        ranges.run(frame_coordinates, len(at), at, dest, T, B, N, W, base, sub, out, threads=threads)
        return out

    def place(self, frames: tuple, U: np.ndarray, rest: np.ndarray, C: np.ndarray,
              R: np.ndarray | None = None, t: np.ndarray | None = None, aligned: bool | np.ndarray = False,
              world: np.ndarray | None = None, threads: int | None = None) -> np.ndarray | None:
        """The shell ``X = rest + U + Frame(X̄ + U)ᵀ C`` in frames already computed
        (:meth:`rows` of U; :func:`compose_framed`), as :meth:`shell` but with C (n,3) per internal
        position and the vertex-order outputs: ``aligned`` (True, or an (n,3) array of
        ``rest``'s dtype to fill) returns X (n,3) in vertex order in ``rest``'s dtype (float64
        keeps the rest pose exact); ``world`` (n,3) float32 is filled with ``Rᵀ (X − t)``
        (X − t rounded to float32 first)."""
        T, B, N = frames
        n = self.n_vertices
        if isinstance(aligned, np.ndarray):
            Xa = aligned
        else:
            Xa = np.empty((n, 3) if aligned else (0, 3), rest.dtype)
        aligned = Xa.shape[0] > 0
        W = _NO_WORLD if world is None else world
        R32 = _EYE if R is None else np.ascontiguousarray(R, np.float32)
        t = np.zeros(3, rest.dtype) if t is None else np.ascontiguousarray(t, rest.dtype)
        ranges.run(compose_framed, n, T, B, N, U, rest, C, R32, t, self.order, Xa, W, threads=threads)
        return Xa if aligned else None


_EYE = np.eye(3, dtype=np.float32)
_ZERO3 = np.zeros(3, np.float32)
_NO_ALIGNED = np.empty((3, 0), np.float32)
_NO_WORLD = np.empty((0, 3), np.float32)
_NO_FRAMES = np.empty((3, 0), np.float32)

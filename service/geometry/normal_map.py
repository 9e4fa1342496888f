"""Tangent-space normal maps of a displacement map on a (deformed) triangle mesh.

The standard bump → normal-map conversion (Blinn 1978, "Simulation of wrinkled surfaces"),
done in the surface's true metric rather than assuming one texel is one unit of length: the
``normal_map`` output of API.md, for renderers that shade the fine-scale displacement of
ma2008 §5 step 5-6 without tessellating it (ma2008 §3 goes the other way, integrating
measured normal maps into displacement maps). A displacement map h (H,W), mm, moves the
surface along its unit normal, ``P' = P + h N``; to first order in h (the ``h ∂N/∂u``
terms dropped, as in all normal mapping) the displaced normal is

    N' ∝ N − g,    g = J (JᵀJ)⁻¹ ∇_uv h,    J = [∂P/∂u  ∂P/∂v]  (3×2, per triangle)

with g the surface gradient of h. J comes from the triangle's edges on the *current* mesh
and its UV edges: ``E = [e1 e2] = J D`` with ``D = [d1 d2]`` the UV edge differences, so

    g = E (EᵀE)⁻¹ Dᵀ ∇_uv h = Ku ∂h/∂u + Kv ∂h/∂v                               (1)

(no inverse of D is needed; ``g · e_k`` is the change of h along edge k). ``∇_uv h`` comes
from finite differences on the map in texel units, ``∂/∂u = W ∂/∂x``, ``∂/∂v = −H ∂/∂y``
(rows go down as v goes up; map convention of :mod:`service.geometry.uv_raster`).

The per-texel frame is the barycentric interpolation of the vertex frames of
:func:`~service.geometry.tangent_frames.tangent_frames`, re-orthonormalized by Gram-Schmidt
with the normal first: ``N̂ = N/|N|``, ``T̂ ∝ T − (T·N̂) N̂``, ``B̂ = N̂ × T̂``. The output is
the unit vector ``(−T̂·g, −B̂·g, 1)`` normalized: x along T (+u), y along B, z along N. This
is N − g with g projected onto the texel's tangent plane; the component of g along N̂ (the
angle between the flat triangle and the interpolated normal times |g|, an artefact of the
faceting) is dropped, so a map is (0,0,1) wherever h is locally constant.

Conventions
-----------
- Mirrored charts (UV triangles with det D < 0) need no special case: (1) gives the world
  gradient for either orientation, and the frames follow +u (T) on every chart. There
  ``B = N × T`` points along −v, and y is along B as given: a renderer that uses mikktspace's
  signed bitangent ``w (N × T)`` (+v on every chart) must multiply y by
  :func:`~service.geometry.tangent_frames.uv_handedness`.
- Finite differences are central where both neighbours along the axis are covered texels of
  the same UV chart (connected component of ``uv_faces``), one-sided where one is, and zero
  where neither is; uncovered texels of h are never read (they may hold NaN). Charts packed
  side by side in the atlas therefore do not mix.
- Uncovered texels are (0,0,1), and so are texels of triangles degenerate in 3D (no
  gradient). Where the interpolated frame degenerates (``|T×N|²`` below
  ``FRAME_DEGENERATE``, e.g. opposite tangents meeting inside a triangle at a mirror seam)
  the denominators of the projections are clamped, so the slopes fade to 0 with ``|T×N|``
  instead of blowing up: every output is finite and unit for finite inputs.
- Only T and N of the frames are read; the y axis is ``N̂ × T̂``, which is B for the
  right-handed frames of ``tangent_frames``.

Precision and cost
------------------
Edges are differenced in float64; everything after (the operators (1), the per-texel
interpolation, gradient, frame and normalization) runs in float32, the dtype of the output,
per texel in one compiled pass (:mod:`service.geometry.normal_texels`). The slopes agree
with a float64 evaluation of the definition to ~1e-6 (tests). A float16 output takes the
float32 normals rounded in that pass, a block of texels at a time (NumPy's
``astype(np.float16)`` bit for bit; level-1 map 9.4 → 9.8 ms, against ~1.6 ms more to convert
a float32 map afterwards). Cost: see :class:`NormalMapper`.
"""

from __future__ import annotations


import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from service.geometry import ranges
from service.geometry.uv_raster import UVRaster

#: a triangle whose corner-0 angle has a sine below this is degenerate in 3D (no gradient)
TRIANGLE_DEGENERATE_SIN = 1e-6
#: clamp of |T×N|² and |N|²|T×N|² of the interpolated frame (both ≈ 1 for unit vertex
#: frames that roughly agree): below it the slopes fade out instead of dividing by ~0
FRAME_DEGENERATE = 1e-6

_EPS = np.float32(FRAME_DEGENERATE)
_SIN2 = np.float32(TRIANGLE_DEGENERATE_SIN ** 2)


def uv_chart_labels(uv_faces: np.ndarray, K: int) -> np.ndarray:
    """UV chart of each triangle: connected components of the UV layout.

    Parameters
    ----------
    uv_faces : (m,3) int   per-corner indices into the K UV coordinates
    K : int                number of UV coordinates

    Returns
    -------
    chart : (m,) int64   component label; triangles sharing a UV index share a chart
    """
    UF = np.asarray(uv_faces, dtype=np.int64)
    A = sp.csr_matrix((np.ones(3 * len(UF)), (UF.ravel(), np.roll(UF, -1, axis=1).ravel())),
                      shape=(K, K))
    _, label = connected_components(A, directed=False)
    return label[UF[:, 0]].astype(np.int64)


def stencil_codes(chart: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The finite-difference stencils of a map's texels (module notes), as the compiled
    texel pass reads them.

    Parameters
    ----------
    chart : (H,W) int   UV chart of each texel (:func:`uv_chart_labels` of its triangle),
                        negative where uncovered

    Returns
    -------
    code : (H,W) uint8     bits :data:`~service.geometry.normal_texels.U_FWD`, ``U_BWD``,
                           ``V_FWD``, ``V_BWD``: the neighbour along +x, −x, +y, −y is a
                           texel of the same chart (meaningful at covered texels)
    scales : (2,3) float32 rows u and v, by the count of usable sides (0, 1, 2): texel
                           differences → ∂h/∂u (W × (0, 1, 1/2)) or ∂h/∂v (−H × (0, 1, 1/2))
    """
    from service.geometry.normal_texels import U_BWD, U_FWD, V_BWD, V_FWD

    H, W = chart.shape
    code = np.zeros((H, W), np.uint8)
    same = (chart[:, 1:] == chart[:, :-1]).view(np.uint8)           # x and x + 1
    code[:, :-1] |= same * np.uint8(U_FWD)
    code[:, 1:] |= same * np.uint8(U_BWD)
    same = (chart[1:] == chart[:-1]).view(np.uint8)                 # y and y + 1
    code[:-1] |= same * np.uint8(V_FWD)
    code[1:] |= same * np.uint8(V_BWD)
    scales = np.float32([[0.0, float(W), W / 2], [0.0, float(-H), -H / 2]])
    return code, scales


class NormalMapper:
    """Tangent-space normal maps for one UV layout and map size, many displacement maps.

    Everything that depends only on the layout is precomputed once: the covered texels and
    their triangles, the barycentric weights on the triangles' vertices, the UV edges of the
    used triangles, the finite-difference stencils (one byte of neighbour bits per texel,
    :func:`stencil_codes`) and the runs of uncovered texels. Each :meth:`normal_map` call
    then costs one compiled pass over the used triangles (the gradient operators (1) of the
    module notes on the current mesh, :func:`service.geometry.normal_texels.triangle_operators`),
    one writing (0,0,1) over the uncovered runs, and one over the covered texels
    (:func:`service.geometry.normal_texels.normal_texels`: finite differences,
    interpolation, gradient, frame, normal, written into the map): every texel of the
    output written once, no zero fill.

    Parameters
    ----------
    raster : UVRaster       :func:`~service.geometry.uv_raster.rasterize_uv` of
                            ``(uv, uv_faces)`` at the map size H×W
    F : (m,3) int           position triangles, one-to-one with ``uv_faces``
    uv : (K,2) float        UV coordinates
    uv_faces : (m,3) int    per-corner indices into ``uv`` (seams: several UVs per vertex)
    n : int                 vertex count

    Attributes
    ----------
    shape : (H, W)          map size
    n : int                 vertex count

    Notes
    -----
    Static memory ≈ 33 bytes per covered texel (24 MB for the 715k of a 1024² map; 53
    with int64 indices and float32 stencil scales before).

    Per call, 1024² map, 45k-vertex / 89k-triangle mesh, one core of a 2-core AMD EPYC VM
    (NumPy 2.4, SciPy 1.17): the NumPy passes this replaced took 39-42 ms best, ≈ 45 ms
    median on an idle machine (sparse interpolation of (T, N) 9 ms and its transpose 2,
    gathering (Ku, Kv) 4.5, per-texel arithmetic 12, output 5, finite differences 3.5,
    operators (1) 3.5); the compiled texel pass took a level-1 PDM maps frame from 59.5 to
    47.2 ms of CPU (issue 23, alternating in one run, load 1.8), the maps bit for bit.
    Then the finite differences moved into the texel pass (they were two (H·W) difference
    images, gathers and patches per axis: 5.6 ms of cProfile), the zero fill became the
    uncovered runs, and the operators (1) a per-triangle kernel (3.3 ms as NumPy passes):
    one call 18.1 → 9.7 ms of CPU on the level-1 map (main's mapper against this one,
    alternating in one process, same inputs, load 1.0; bit for bit). Tried and not kept:
    (T, N) and (Ku, Kv) interleaved per vertex / triangle ((n,6), transposed per call:
    within noise, 11.4 vs 11.4 ms) and padded to 8 floats (13.3 ms: the strided copies).
    Built in ≈ 40 ms at 1024² (level-1 PDM load; 100 ms with ``np.unique`` and per-texel
    int64 stencils).
    """

    def __init__(self, raster: UVRaster, F: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
                 n: int):
        F = np.asarray(F, dtype=np.int64)
        uv = np.asarray(uv, dtype=np.float64)
        UF = np.asarray(uv_faces, dtype=np.int64)
        n = int(n)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"uv must be (K,2), got {uv.shape}")
        if F.ndim != 2 or F.shape[1] != 3 or UF.shape != F.shape:
            raise ValueError(f"F and uv_faces must both be (m,3), got {F.shape} and {UF.shape}")
        if len(F) and (F.min() < 0 or F.max() >= n):
            raise ValueError(f"F index out of range [0, {n})")
        if len(UF) and (UF.min() < 0 or UF.max() >= len(uv)):
            raise ValueError(f"uv_faces index out of range [0, {len(uv)})")
        triangle = np.asarray(raster.triangle)
        if not np.issubdtype(triangle.dtype, np.signedinteger):
            triangle = triangle.astype(np.int64)
        if triangle.max(initial=-1) >= len(F):
            raise ValueError(f"raster refers to triangle {triangle.max()}, but F has {len(F)}")
        H, W = triangle.shape
        self.shape = (H, W)
        self.n = n

        flat = triangle.ravel()
        texel = np.flatnonzero(flat >= 0)                               # (N,) row-major
        tri = flat[texel]
        used = np.flatnonzero(np.bincount(tri, minlength=len(F)))       # (mu,) increasing
        into_used = np.zeros(len(F), np.uint32)
        into_used[used] = np.arange(len(used), dtype=np.uint32)
        self._faces_t = np.ascontiguousarray(F[used].T)                  # (3,mu)
        self._used = used.astype(np.uint32)                              # (mu,) into F
        self._m = len(F)
        U = uv[UF[used]]                                                 # (mu,3,2)
        d1, d2 = U[:, 1] - U[:, 0], U[:, 2] - U[:, 0]
        self._uv_edges = np.stack([d1[:, 0], d1[:, 1], d2[:, 0], d2[:, 1]]).astype(np.float32)

        label = np.append(uv_chart_labels(UF, len(uv)).astype(np.int32), np.int32(-1))
        code, self._scales = stencil_codes(label[triangle])             # −1 (uncovered) → −1
        self._code = code.ravel()[texel]
        gap = np.diff((flat < 0).view(np.int8), prepend=np.int8(0), append=np.int8(0))
        self._runs = np.column_stack([np.flatnonzero(gap == 1), np.flatnonzero(gap == -1)]).astype(np.uint32)

        self._lam = np.ascontiguousarray(raster.barycentric.reshape(-1, 3)[texel], dtype=np.float32)
        self._corners = F.astype(np.uint32)[tri]                         # (N,3) the texels' vertices
        self._texel = texel.astype(np.uint32)
        self._triangle = into_used[tri]                                  # (N,) into the used triangles
        import service.geometry.normal_texels  # noqa: F401   Numba, loaded where a mapper (a model) is built

    #: what :meth:`arrays` holds: name → (dtype, shape with ``N`` covered texels, ``mu`` used
    #: triangles, ``r`` uncovered runs)
    _ARRAYS = {"faces_t": (np.int64, (3, "mu")), "used": (np.uint32, ("mu",)),
               "uv_edges": (np.float32, (4, "mu")), "scales": (np.float32, (2, 3)),
               "code": (np.uint8, ("N",)), "runs": (np.uint32, ("r", 2)), "lam": (np.float32, ("N", 3)),
               "corners": (np.uint32, ("N", 3)), "texel": (np.uint32, ("N",)), "triangle": (np.uint32, ("N",))}

    def arrays(self) -> dict[str, np.ndarray]:
        """What the mapper holds, by name, with its size ``shape`` (2,) and ``counts`` (n, m):
        what :meth:`from_arrays` reads back (a model's cache; issue 23's cold start)."""
        return {"shape": np.array(self.shape, np.int64), "counts": np.array([self.n, self._m], np.int64),
                **{k: getattr(self, f"_{k}") for k in self._ARRAYS}}

    @classmethod
    def from_arrays(cls, arrays: dict, n: int, m: int) -> "NormalMapper | None":
        """The mapper of :meth:`arrays` (e.g. memory-mapped from a model's cache) for n
        vertices and m triangles if every array is there with the dtype and a consistent
        shape and its indices are in range, else None (then build it from the rasterization:
        ≈ 40 ms at 1024², and the 16 MB rasterization read)."""
        try:
            shape = tuple(int(x) for x in arrays["shape"])
            counts = [int(x) for x in arrays["counts"]]
            a = {k: arrays[k] for k in cls._ARRAYS}
        except (KeyError, TypeError, ValueError):
            return None
        if len(shape) != 2 or counts != [int(n), int(m)]:
            return None
        size = {"N": len(a["texel"]), "mu": len(a["used"]), "r": len(a["runs"])}
        for k, (dtype, dims) in cls._ARRAYS.items():
            x = a[k]
            if (not isinstance(x, np.ndarray) or x.dtype != dtype or not x.flags.c_contiguous
                    or x.shape != tuple(size.get(d, d) for d in dims)):
                return None
        H, W = shape
        if size["N"] and (a["texel"].max() >= H * W or a["triangle"].max() >= size["mu"]
                          or a["corners"].max() >= n):
            return None
        if size["mu"] and (a["used"].max() >= m or a["faces_t"].min() < 0 or a["faces_t"].max() >= n):
            return None
        if size["r"] and a["runs"].max() > H * W:
            return None
        mapper = cls.__new__(cls)
        mapper.shape, mapper.n, mapper._m = (H, W), int(n), int(m)
        for k, x in a.items():
            setattr(mapper, f"_{k}", x)
        import service.geometry.normal_texels  # noqa: F401   Numba, as __init__
        return mapper

    @property
    def texels(self) -> np.ndarray:
        """(N,) uint32 flat (row-major) indices of the covered texels."""
        return self._texel

    def gradient_operators(self, V: np.ndarray, edges: np.ndarray | None = None) -> np.ndarray:
        """Per-triangle maps from ``(∂h/∂u, ∂h/∂v)`` to the surface gradient, eq. (1).

        ``E (EᵀE)⁻¹ = [a1 a2]`` is the dual basis of the edges in the triangle's plane
        (``a_i · e_j = δ_ij``): ``a1 = (e2 × n) / |n|²``, ``a2 = (n × e1) / |n|²`` with
        ``n = e1 × e2``, so ``Ku = Δu1 a1 + Δu2 a2`` and ``Kv = Δv1 a1 + Δv2 a2``. The edges
        are differenced in float64 (vertices far from the origin), the rest is float32;
        ``|n|²`` has no cancellation, unlike ``|e1|²|e2|² − (e1·e2)²``.

        Parameters
        ----------
        V : (n,3) float   current vertices, mm
        edges : (3,2m) float32, optional   the edges of all m triangles of V, component rows,
                          e1 = P1 − P0 (columns :m) and e2 = P2 − P0, differenced in float64
                          and rounded once (:meth:`~service.geometry.tangent_frames.FrameField.normal_rows`
                          made them for the frames): the same values, read instead of gathered

        Returns
        -------
        K : (6,mu) float32   rows (Ku, Kv) of the used triangles (in increasing index), uv
                             units per mm: ``g = K[:3] ∂h/∂u + K[3:] ∂h/∂v``; zero for
                             triangles degenerate in 3D
        """
        from service.geometry.normal_texels import triangle_operators

        if edges is None:
            Vt = np.ascontiguousarray(np.asarray(V, dtype=np.float64).T)    # (3,n)
            p0 = np.take(Vt, self._faces_t[0], axis=1)
            edges = np.concatenate([np.take(Vt, self._faces_t[1], axis=1) - p0,
                                    np.take(Vt, self._faces_t[2], axis=1) - p0], axis=1).astype(np.float32)
            used, m = np.arange(len(self._used), dtype=np.uint32), len(self._used)
        else:
            if edges.shape != (3, 2 * self._m) or edges.dtype != np.float32:
                raise ValueError(f"edges must be float32 (3,{2 * self._m}), got {edges.dtype} {edges.shape}")
            used, m = self._used, self._m
        K = np.empty((6, len(self._used)), dtype=np.float32)
        ranges.run(triangle_operators, len(used), np.ascontiguousarray(edges), used, m, self._uv_edges,
                   _SIN2, K)
        return K

    def normal_map(self, h: np.ndarray, V: np.ndarray, frames: np.ndarray | None,
                   out: np.ndarray | None = None, rows: tuple[np.ndarray, np.ndarray] | None = None,
                   threads: int | None = None) -> np.ndarray:
        """Tangent-space normal map of the displacement map h on the mesh V.

        Parameters
        ----------
        h : (H,W) float            displacement along the normal, mm (uncovered texels are
                                   not read)
        V : (n,3) float            current vertices, mm
        frames : (n,3,3) float     vertex frames of V, rows (T, B, N) as from
                                   :func:`~service.geometry.tangent_frames.tangent_frames`
        out : (H,W,3) float32 or float16, C-contiguous, optional   written and returned (e.g. a
                                   frame of the caller's output array: no copy of the map);
                                   float16 takes the normals rounded by the texel pass itself,
                                   bit for bit ``astype(np.float16)`` of the float32 map
        rows : ((6,n) float32, (3,2m) float32), optional   instead of ``frames`` (then None):
                                   the vertex (T, N) as component rows and the triangles'
                                   edges, as :meth:`~service.geometry.tangent_frames.FrameField.normal_rows`
                                   gives them (the frames' T and N and the edges
                                   :meth:`gradient_operators` would difference: same result)
        threads : int, optional    the per-texel kernel's threads (default
                                   :func:`service.geometry.ranges.kernel_threads`)

        Returns
        -------
        normals : (H,W,3) float32 (or ``out``'s float16)   unit (x, y, z) along (T, B, N) of
                                    the texel frame; (0,0,1) at uncovered texels
        """
        h = np.asarray(h)
        if h.shape != self.shape:
            raise ValueError(f"h must be {self.shape}, got {h.shape}")
        if h.dtype not in (np.float32, np.float64):
            h = h.astype(np.float64)
        V = np.asarray(V, dtype=np.float64)
        if V.shape != (self.n, 3):
            raise ValueError(f"V must be ({self.n},3), got {V.shape}")
        if rows is None:
            frames = np.asarray(frames)
            if frames.shape != (self.n, 3, 3):
                raise ValueError(f"frames must be ({self.n},3,3), got {frames.shape}")
        elif rows[0].shape != (6, self.n) or rows[0].dtype != np.float32:
            raise ValueError(f"rows[0] must be float32 (6,{self.n}), got {rows[0].dtype} {rows[0].shape}")

        H, W = self.shape
        hf = np.ascontiguousarray(h).reshape(-1)
        if rows is None:
            K = self.gradient_operators(V)
            TN = np.empty((6, self.n), dtype=np.float32)                # rows Tx, Ty, Tz, Nx, Ny, Nz
            TN[:3] = frames[:, 0].T
            TN[3:] = frames[:, 2].T
        else:
            TN, edges = rows
            K = self.gradient_operators(V, edges)
        if out is None:
            out = np.empty((H, W, 3), dtype=np.float32)
        elif (out.shape != (H, W, 3) or out.dtype not in (np.float32, np.float16)
              or not out.flags.c_contiguous):
            raise ValueError(f"out must be a C-contiguous float32 or float16 ({H},{W},3) array")
        from service.geometry.normal_texels import FLAT, FLAT_HALF, flat_runs, normal_texels

        half = out.dtype == np.float16
        flat = out.reshape(H * W, 3).view(np.uint16) if half else out.reshape(H * W, 3)
        ranges.run(flat_runs, len(self._runs), self._runs, flat, FLAT_HALF if half else FLAT, threads=threads)
        ranges.run(normal_texels, len(self._texel), self._texel, self._triangle, self._lam, self._corners,
                   self._code, self._scales, W, hf, K, np.ascontiguousarray(TN, np.float32), _EPS, flat,
                   threads=threads)
        return out


def tangent_space_normal_map(h: np.ndarray, raster: UVRaster, V: np.ndarray, F: np.ndarray,
                             uv: np.ndarray, uv_faces: np.ndarray,
                             frames: np.ndarray) -> np.ndarray:
    """One-off tangent-space normal map: ``NormalMapper(raster, F, uv, uv_faces, len(V))``
    applied to ``(h, V, frames)``; build a :class:`NormalMapper` to convert many maps.

    Parameters
    ----------
    h : (H,W) float           displacement along the normal, mm
    raster : UVRaster         rasterization of ``(uv, uv_faces)`` at H×W
    V : (n,3) float           vertices, mm
    F : (m,3) int             triangles
    uv : (K,2) float          UV coordinates
    uv_faces : (m,3) int      per-corner indices into uv
    frames : (n,3,3) float    vertex frames (T, B, N) of V

    Returns
    -------
    normals : (H,W,3) float32   unit, tangent space (x along T, y along B, z along N)
    """
    return NormalMapper(raster, F, uv, uv_faces, len(V)).normal_map(h, V, frames)

"""The PDM's per-frame medium mesh on the compiled shell kernels (issue 23).

ma2008 §5 synthesizes a frame's medium mesh as the base surface ``X = X̄ + B u_H`` plus the
medium band's offsets in X's tangent frames, with the medium fallback of :mod:`.validity`
(the detailed neutral's thin shell, :func:`.model.shell_fallback`) expressed in the same
frames. Per frame this used two BLAS products with the (n,M) float32 bases, FrameField's
float32 frames of X (sparse products over NumPy rows) and NumPy passes for the fallback and
the composition. Here the same steps run on the kernels of
:mod:`service.geometry.shell_frames` (Numba, ``nogil``, over vertex ranges on
:func:`service.geometry.ranges.kernel_threads` threads, in its cache-friendly vertex order):

1. ``U = B u_H`` and ``U_c = (B_det − B) u_H`` in one pass over both bases
   (:func:`~service.geometry.shell_frames.displacement_pair`, the bases' rows stored in the
   internal order);
2. the float32 frames T, B, N of X̄ + U from the rest edges plus U's edges
   (:meth:`ShellFrames.rows`; FrameField's frames, ~1e-6 apart);
3. the fallback at the UV points: ``Frame(X) (V − X̄ + U_c) − neutral_offset``
   (:meth:`ShellFrames.coordinates`);
4. the medium offsets (:func:`.model.medium_offsets`) with the seam average's rows in the
   internal order, so they come out per internal position;
5. ``X̄ + U + Frame(X)ᵀ C`` in float64 (X̄ exact) and the head pose put back in float32
   (:meth:`ShellFrames.place`: ``(X − t)`` rounded to float32, times R, as
   :meth:`.base_surface.HeadPose.restore32`).

The vertices agree with the float64 path to ~1e-5 mm (tests bound them by 1e-3 mm, as the
float32 frames before). Numba is imported here, so this module is imported where an
evaluator is built (:meth:`.model.PdmEvaluator.build`), never by ``facesynth serve``'s start.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from service.geometry import ranges
from service.geometry.shell_frames import ShellFrames, displacement_pair
from service.methods.footprint import COPY


@dataclass(frozen=True)
class ShellMesh:
    """What the compiled mesh path reads, in :attr:`frames`' internal vertex order.

    Attributes (n vertices, M markers, K UV points)
    ----------
    frames : ShellFrames              vertex order, rest edges, incidence of the smooth neutral
    basis : (n,M) float32             thin-shell basis B, rows in the internal order (C order)
    correction : (n,M) float32        B_det − B (:meth:`.model.PdmEvaluator.shell_fallback`), the same
    smooth : (3,n) float64            X̄, internal order
    offset : (3,n) float32            V − X̄, the detailed minus the smooth neutral
    neutral_rows : (3,n) float32      the neutral's static medium offset (subtracted by the fallback)
    neutral_offset : (n,3) float32    the same per internal position (added by the medium offsets)
    uv_points : tuple                 the UV points' vertices (:meth:`ShellFrames.points`)
    seam_average : (n,K) CSR          UV points → vertices, rows in the internal order
    """

    frames: ShellFrames
    basis: np.ndarray = dataclasses.field(metadata=COPY)   # the base's, reordered: one is read per frame
    correction: np.ndarray
    smooth: np.ndarray
    offset: np.ndarray
    neutral_rows: np.ndarray
    neutral_offset: np.ndarray
    uv_points: tuple
    seam_average: sp.csr_matrix

    @classmethod
    def build(cls, smooth: np.ndarray, faces: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
              basis: np.ndarray, correction: np.ndarray, offset: np.ndarray, neutral_offset: np.ndarray,
              uv_vertex: np.ndarray, seam_average: sp.csr_matrix, stored: dict | None = None) -> "ShellMesh":
        """From the evaluator's arrays: the smooth neutral X̄ (n,3), its triangles and UV
        layout, the basis B and ``correction`` (n,M), ``offset`` (n,3) V − X̄, the static
        ``neutral_offset`` (n,3), the UV points' vertices (K,) and the seam average (n,K).

        ``stored``: the :meth:`stored` arrays of a saved ShellMesh (a model's cache,
        memory-mapped): its two bases in the internal order are used as they are when they
        were made in this vertex order (``order`` equal to the one built here) for bases of
        this shape — then ``basis`` and ``correction`` are not read at all, and a load
        neither copies nor holds the (n,M) permuted copies (level 1: 2 × 27 MB); else
        (a model stored without them) they are permuted here. Likewise the ShellFrames
        (``frames_*``, :meth:`ShellFrames.arrays`): read as stored when all are there with
        the shapes of this mesh, else built (77 ms at level 1)."""
        stored = stored or {}
        sf = ShellFrames.from_arrays({k[len("frames_"):]: v for k, v in stored.items() if k.startswith("frames_")},
                                     len(smooth), len(faces))
        sf = sf or ShellFrames.build(smooth, faces, uv, uv_faces)
        order = sf.order
        neutral = np.ascontiguousarray(np.asarray(neutral_offset, np.float32)[order])
        ok = ("order" in stored and np.array_equal(stored["order"], order)
              and all(stored.get(k) is not None and stored[k].shape == np.shape(b) and stored[k].dtype == np.float32
                      and stored[k].flags.c_contiguous for k, b in (("basis", basis), ("correction", correction))))
        B, Bc = (stored["basis"], stored["correction"]) if ok else (sf.internal_basis(basis),
                                                                     sf.internal_basis(correction))
        return cls(sf, B, Bc,
                   np.ascontiguousarray(np.asarray(smooth, np.float64)[order].T),
                   sf.to_internal(offset), np.ascontiguousarray(neutral.T), neutral,
                   sf.points(uv_vertex), seam_average.tocsr()[order])

    @property
    def order(self) -> np.ndarray:
        return self.frames.order

    def stored(self) -> dict[str, np.ndarray]:
        """What :meth:`build` reads back instead of permuting the bases and building the
        frames: ``order`` (n,) uint32 the internal vertex order, ``basis`` and ``correction``
        (n,M) float32 in it, ``frames_<field>`` the :class:`ShellFrames` (:meth:`ShellFrames.arrays`,
        6.5 MB at level 1)."""
        return {"order": self.order, "basis": self.basis, "correction": self.correction,
                **{f"frames_{k}": v for k, v in self.frames.arrays().items()}}

    def surface(self, u_H: np.ndarray, threads: int | None = None,
                correction: bool = False) -> tuple[np.ndarray, tuple, np.ndarray | None]:
        """One frame's base surface: U = B u_H (3,n) float32 and its frames (T, B, N) (3,n)
        float32, internal order, for handle displacements u_H (M,3); with ``correction``
        also ``Uc = (B_det − B) u_H`` (3,n) float32 that :meth:`fallback` reads (else None),
        both products in one pass over the two bases (:func:`displacement_pair`, each
        bit for bit the product alone)."""
        sf = self.frames
        if correction:
            u = np.ascontiguousarray(np.asarray(u_H, np.float32).T)
            U, Uc = (np.empty((3, sf.n_vertices), np.float32) for _ in range(2))
            ranges.run(displacement_pair, sf.n_vertices, self.basis, self.correction, u, U, Uc, threads=threads)
        else:
            U, Uc = sf.displacement(self.basis, u_H, threads), None
        return U, sf.rows(U, threads), Uc

    def fallback(self, Uc: np.ndarray, frames: tuple, out: np.ndarray | None = None,
                 threads: int | None = None) -> np.ndarray:
        """The medium fallback (K,3) float32 at the UV points of one frame, from the
        correction's displacement ``Uc`` and the base surface's ``frames`` of
        :meth:`surface` (``correction=True``): :func:`.model.shell_fallback`."""
        return self.frames.coordinates(frames, Uc, self.offset, self.neutral_rows, self.uv_points, out,
                                        threads)

    def place(self, U: np.ndarray, frames: tuple, C: np.ndarray, R: np.ndarray, t: np.ndarray,
              aligned: bool | np.ndarray = False, world: np.ndarray | None = None,
              threads: int | None = None) -> np.ndarray | None:
        """The medium mesh ``X̄ + U + Frame(X)ᵀ C`` of one frame (C (n,3) medium offsets per
        internal position): ``world`` (n,3) float32 filled with the head pose put back (R
        (3,3), t (3,)), and with ``aligned`` (True or an (n,3) float64 array to fill) the
        neutral-aligned mesh (n,3) float64 returned."""
        C = np.asarray(C, np.float32)
        return self.frames.place(frames, U, self.smooth, C, R, t, aligned, world, threads)

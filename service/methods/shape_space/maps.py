"""The database's UV maps (fine displacement, albedo), blended like its detail (bermano2014 §5.4–5.5).

bermano2014's database frames are 1.2M-vertex scans, so pores and fine wrinkles travel with
the mesh detail of eq. 4, and §5.5 blends per-vertex colours with the same weights. A
database captured as meshes plus maps (the sample actor's, and the usual light-stage
delivery) keeps the fine band and the reflectance in UV maps instead; the same convex
weights then blend the maps texel by texel:

    m(x) = Σ_r  ω̂_r(x) Σ_k w_{r,k} M_k(x),

with ω̂_r(x) the normalized region weights interpolated to the texel. A displacement map
M_k is relative to database frame k's mesh (``Clip.displacement``), so m is relative to the
enhanced mesh; albedo maps (``Clip.albedo``) blend the same way.

Stored as float16 at the covered texels (as a half EXR: displacements below a few
millimetres keep a step ≤ 2.4e-4 mm at 0.5 mm; a 630-frame level-1 database holds 0.8 GB of
1024² displacement and 0.6 GB of 512² albedo).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from service.geometry.uv_raster import (
    interpolation_matrix, rasterize_uv, texel_centers_uv, uv_sampling_matrix,
)
from service.methods.inputs import ActorData, Clip, InvalidInput
from service.methods.shape_space.blending import blend


#: the Clip attributes that hold maps, and their channel counts
MAP_ATTRIBUTES = {"displacement": 1, "albedo": 3}


@dataclass(frozen=True)
class DatabaseMaps:
    """One kind of UV map of the database frames at the texels the neutral's layout covers
    (stored data: the store round-trips it; :class:`MapBlender` blends it).

    Attributes (N frames, P covered texels of an H×W map, C channels)
    ----------
    maps : (N,P,C) float16  e.g. normal displacement relative to each frame's mesh (mm, C = 1)
                            or linear RGB albedo (C = 3)
    texels : (P,) int64     flat (row-major) indices of the covered texels
    shape : (H, W)
    """

    maps: np.ndarray
    texels: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def from_clips(cls, actor: ActorData, clips: Sequence[Clip], stride: int,
                   attribute: str = "displacement") -> "DatabaseMaps | None":
        """The kept frames' (every ``stride``-th) maps of ``attribute`` (a key of
        :data:`MAP_ATTRIBUTES`), or None unless every clip has them.

        Raises
        ------
        InvalidInput   clips whose maps differ in size or are not (F,H,W[,C])
        """
        C = MAP_ATTRIBUTES[attribute]
        if not all(getattr(c, attribute) is not None for c in clips):
            return None
        shapes = {np.shape(getattr(c, attribute))[1:] for c in clips}
        H, W = next(iter(shapes))[:2]
        if len(shapes) != 1 or next(iter(shapes)) != ((H, W) if C == 1 else (H, W, C)):
            raise InvalidInput(f"the clips' {attribute} maps must all be (F,H,W{'' if C == 1 else f',{C}'}) "
                               f"of one size, got {sorted(str(s) for s in shapes)}")
        texels = np.flatnonzero(rasterize_uv(actor.uv, actor.uv_faces, H, W).mask.ravel())
        maps = np.concatenate([np.asarray(getattr(c, attribute)[::stride]).reshape(-1, H * W, C)[:, texels]
                               for c in clips])
        return cls(np.nan_to_num(maps).astype(np.float16), texels, (int(H), int(W)))

    def image(self, values: np.ndarray) -> np.ndarray:
        """Covered-texel values (F,P,C) as maps (F,H,W) for C = 1, else (F,H,W,C), float32, at
        the stored size; 0 where no triangle covers a texel."""
        values = np.asarray(values, dtype=np.float32)
        F, C = len(values), values.shape[-1]
        Hs, Ws = self.shape
        out = np.zeros((F, Hs * Ws, C), np.float32)
        out[:, self.texels] = values
        return out.reshape((F, Hs, Ws) if C == 1 else (F, Hs, Ws, C))


@dataclass(frozen=True)
class MapBlender:
    """What blending one kind of :class:`DatabaseMaps` needs, precomputed once.

    Attributes (R regions, P covered texels)
    ----------
    database : DatabaseMaps    the stored maps
    omega_hat : (R,P) float64  the normalized per-vertex region weights interpolated to the texels
    layout : (uv (K,2), uv_faces (m,3))   the neutral's UV layout (resampling to other sizes)
    resolution : int | None    the side :meth:`image` resamples to without building an operator
    resample : (resolution², P) CSR | None   that resampling (None: the stored size is square
                               and equal to it, or no resolution was given)
    """

    database: DatabaseMaps
    omega_hat: np.ndarray
    layout: tuple
    resolution: int | None = None
    resample: sp.csr_matrix | None = None

    @classmethod
    def build(cls, maps: DatabaseMaps, uv: np.ndarray, uv_faces: np.ndarray, faces: np.ndarray,
              vertex_omega_hat: np.ndarray, resolution: int | None = None,
              covered: np.ndarray | None = None) -> "MapBlender":
        """Interpolate the normalized per-vertex region weights (R,n) to the texels, and build
        the resampling to ``resolution`` texels per side if it is not the stored size
        (``covered`` (resolution, resolution) bool: the texels the layout covers at that size,
        if the caller has rasterized it already)."""
        raster = rasterize_uv(uv, uv_faces, *maps.shape)
        P = interpolation_matrix(raster, faces, vertex_omega_hat.shape[1])[maps.texels]
        omega_hat = np.ascontiguousarray((P @ vertex_omega_hat.T).T)
        layout = (uv, uv_faces)
        resample = None
        if resolution is not None and (resolution, resolution) != maps.shape:
            resample = _resampling(maps, layout, resolution, covered)
        return cls(maps, omega_hat, layout, resolution, resample)

    @property
    def maps(self) -> np.ndarray:
        """(N,P,C) float16, the stored maps' values."""
        return self.database.maps

    @property
    def texels(self) -> np.ndarray:
        return self.database.texels

    @property
    def shape(self) -> tuple[int, int]:
        return self.database.shape

    def blend(self, weights: np.ndarray) -> np.ndarray:
        """The blended map m (P,C) float32 for convex weights (R,N) (eq. 4 per texel)."""
        return blend(self.database.maps, self.omega_hat, weights).astype(np.float32)

    def image(self, values: np.ndarray, H: int | None = None) -> np.ndarray:
        """Covered-texel values (F,P,C) as maps (F,H,W) for C = 1, else (F,H,W,C), float32;
        0 where no triangle covers a texel.

        With ``H`` other than the stored height, bilinearly resampled to the texels of an H×H
        map that the layout covers (the operator precomputed for ``resolution``, built for
        this call for any other size).
        """
        if H is None or (H, H) == self.shape:
            return self.database.image(values)
        S = self.resample if H == self.resolution else _resampling(self.database, self.layout, H)
        values = np.asarray(values, dtype=np.float32)
        F, C = len(values), values.shape[-1]
        out = (S @ values.transpose(1, 0, 2).reshape(len(self.texels), F * C))
        out = out.reshape(H * H, F, C).transpose(1, 0, 2).astype(np.float32)
        return out.reshape((F, H, H) if C == 1 else (F, H, H, C))


def _resampling(maps: DatabaseMaps, layout: tuple, H: int,
                covered: np.ndarray | None = None) -> sp.csr_matrix:
    """(H², P) bilinear resampling of the covered texels of ``maps`` to the texels of an H×H
    map that the UV ``layout`` covers (0 elsewhere; ``covered`` (H,H) bool that coverage,
    rasterized here if not given)."""
    mask = np.zeros(maps.shape[0] * maps.shape[1], bool)
    mask[maps.texels] = True
    S = uv_sampling_matrix(texel_centers_uv(H, H).reshape(-1, 2), mask.reshape(maps.shape))
    if covered is None:
        covered = rasterize_uv(*layout, H, H).mask
    return sp.csr_matrix(sp.diags(np.asarray(covered).ravel().astype(np.float64)) @ S[:, maps.texels])


__all__ = ["DatabaseMaps", "MAP_ATTRIBUTES", "MapBlender"]

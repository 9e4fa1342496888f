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

from dataclasses import dataclass, field
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


@dataclass
class DatabaseMaps:
    """One kind of UV map of the database frames at the texels the neutral's layout covers.

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
    # derived: the texels' normalized region weights (R,P) and resampling operators
    _omega_hat: np.ndarray | None = field(default=None, repr=False)
    _layout: tuple | None = field(default=None, repr=False)       # (uv, uv_faces)
    _resample: dict = field(default_factory=dict, repr=False)

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

    def prepare(self, uv: np.ndarray, uv_faces: np.ndarray, faces: np.ndarray,
                vertex_omega_hat: np.ndarray) -> "DatabaseMaps":
        """Interpolate the normalized per-vertex region weights (R,n) to the texels."""
        raster = rasterize_uv(uv, uv_faces, *self.shape)
        P = interpolation_matrix(raster, faces, vertex_omega_hat.shape[1])[self.texels]
        self._omega_hat = np.ascontiguousarray((P @ vertex_omega_hat.T).T)
        self._layout = (uv, uv_faces)
        return self

    def blend(self, weights: np.ndarray) -> np.ndarray:
        """The blended map m (P,C) float32 for convex weights (R,N) (eq. 4 per texel)."""
        return blend(self.maps, self._omega_hat, weights).astype(np.float32)

    def image(self, values: np.ndarray, H: int | None = None) -> np.ndarray:
        """Covered-texel values (F,P,C) as maps (F,H,W) for C = 1, else (F,H,W,C), float32;
        0 where no triangle covers a texel.

        With ``H`` other than the stored height, bilinearly resampled to the texels of an H×H
        map that the layout covers (the operator is built once per size).
        """
        values = np.asarray(values, dtype=np.float32)
        F, C = len(values), values.shape[-1]
        if H is None or (H, H) == self.shape:
            Hs, Ws = self.shape
            out = np.zeros((F, Hs * Ws, C), np.float32)
            out[:, self.texels] = values
        else:
            if H not in self._resample:
                mask = np.zeros(self.shape[0] * self.shape[1], bool)
                mask[self.texels] = True
                S = uv_sampling_matrix(texel_centers_uv(H, H).reshape(-1, 2), mask.reshape(self.shape))
                covered = rasterize_uv(*self._layout, H, H).mask.ravel()
                self._resample[H] = sp.csr_matrix(sp.diags(covered.astype(np.float64)) @ S[:, self.texels])
            Hs = Ws = H
            out = (self._resample[H] @ values.transpose(1, 0, 2).reshape(len(self.texels), F * C))
            out = out.reshape(H * H, F, C).transpose(1, 0, 2).astype(np.float32)
        return out.reshape((F, Hs, Ws) if C == 1 else (F, Hs, Ws, C))


__all__ = ["DatabaseMaps", "MAP_ATTRIBUTES"]

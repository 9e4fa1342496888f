"""The database's fine-scale displacement maps, blended like its detail (bermano2014 §5.4–5.5).

bermano2014's database frames are 1.2M-vertex scans, so pores and fine wrinkles travel with
the mesh detail of eq. 4. A database captured as meshes plus displacement maps (the
sample actor's, and the usual light-stage delivery) keeps that band in the maps instead;
the same convex weights then blend the maps texel by texel, exactly as §5.5 blends the
per-vertex colours:

    m(x) = Σ_r  ω̂_r(x) Σ_k w_{r,k} M_k(x),

with ω̂_r(x) the normalized region weights interpolated to the texel. M_k is relative to
database frame k's mesh (``Clip.displacement``), so m is relative to the enhanced mesh.

Stored as float16 at the covered texels (the maps' values are below a few millimetres, so
the step is ≤ 2.4e-4 mm at 0.5 mm; a 630-frame level-1 database holds 0.8 GB).
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


@dataclass
class FineMaps:
    """Fine displacement maps of the database frames at the texels the neutral's layout covers.

    Attributes (N frames, P covered texels of an H×W map)
    ----------
    maps : (N,P) float16    normal displacement relative to each frame's mesh, mm
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
    def from_clips(cls, actor: ActorData, clips: Sequence[Clip], stride: int) -> "FineMaps | None":
        """The kept frames' maps (every ``stride``-th), or None unless every clip has maps.

        Raises
        ------
        InvalidInput   clips whose maps differ in size or are not (F,H,W)
        """
        if not all(c.displacement is not None for c in clips):
            return None
        shapes = {np.shape(c.displacement)[1:] for c in clips}
        if len(shapes) != 1 or len(next(iter(shapes))) != 2:
            raise InvalidInput(f"the clips' displacement maps must all be (F,H,W) of one size, got "
                               f"{sorted(str(s) for s in shapes)}")
        H, W = next(iter(shapes))
        texels = np.flatnonzero(rasterize_uv(actor.uv, actor.uv_faces, H, W).mask.ravel())
        maps = np.concatenate([np.asarray(c.displacement[::stride]).reshape(-1, H * W)[:, texels]
                               for c in clips])
        return cls(np.nan_to_num(maps).astype(np.float16), texels, (int(H), int(W)))

    def prepare(self, uv: np.ndarray, uv_faces: np.ndarray, faces: np.ndarray,
                vertex_omega_hat: np.ndarray) -> "FineMaps":
        """Interpolate the normalized per-vertex region weights (R,n) to the texels."""
        raster = rasterize_uv(uv, uv_faces, *self.shape)
        P = interpolation_matrix(raster, faces, vertex_omega_hat.shape[1])[self.texels]
        self._omega_hat = np.ascontiguousarray((P @ vertex_omega_hat.T).T)
        self._layout = (uv, uv_faces)
        return self

    def blend(self, weights: np.ndarray) -> np.ndarray:
        """The blended map m (P,) float32 for convex weights (R,N) (eq. 4 per texel)."""
        return blend(self.maps[:, :, None], self._omega_hat, weights)[:, 0].astype(np.float32)

    def image(self, values: np.ndarray, H: int | None = None) -> np.ndarray:
        """Covered-texel values (F,P) as maps (F,H,W) float32, 0 where no triangle covers.

        With ``H`` other than the stored height, bilinearly resampled to the texels of an H×H
        map that the layout covers (the operator is built once per size).
        """
        values = np.asarray(values, dtype=np.float32)
        if H is None or (H, H) == self.shape:
            out = np.zeros((len(values), self.shape[0] * self.shape[1]), np.float32)
            out[:, self.texels] = values
            return out.reshape(len(values), *self.shape)
        if H not in self._resample:
            mask = np.zeros(self.shape[0] * self.shape[1], bool)
            mask[self.texels] = True
            S = uv_sampling_matrix(texel_centers_uv(H, H).reshape(-1, 2), mask.reshape(self.shape))
            covered = rasterize_uv(*self._layout, H, H).mask.ravel()
            self._resample[H] = sp.csr_matrix(sp.diags(covered.astype(np.float64)) @ S[:, self.texels])
        return (self._resample[H] @ values.T).T.reshape(len(values), H, H).astype(np.float32)


__all__ = ["FineMaps"]

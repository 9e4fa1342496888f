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

**Clips without maps.** A database may mix clips with maps and clips without (a long
performance captured as meshes, expression scans with maps). The maps are kept for the
frames K that have them, and the weight a region puts on frames without maps is given to
the mean map M̄ of the frames that have them:

    m(x) = Σ_r  ω̂_r(x) [ Σ_{k∈K} w_{r,k} M_k(x) + (1 − Σ_{k∈K} w_{r,k}) M̄(x) ],

continuous in the weights, equal to eq. 4 when all of a region's weight lies on frames with
maps, and the mean map (the database's typical pores and albedo) when none does. The
model's ``metrics["maps_partial"]`` says which clips had none.

Stored as 16-bit integers at the covered texels with one scale per frame, x ≈ s_k·q with
s_k = max|M_k| / 32767, so the step is ≤ max|M_k| / 32767 (1.5e-5 mm for a frame whose
largest displacement is 0.5 mm; a 630-frame level-1 database holds 0.8 GB of 1024²
displacement and 0.6 GB of 512² albedo). The scale folds into the blend's coefficients,
and int16 → float32 is a plain SIMD conversion: a level-1 request's fine-map blend of 12
active frames went from 100–110 ms to about 8 ms per frame against float16 storage, whose
conversion is unvectorized and, for the sub-1e-4 mm texels that are float16 subnormals,
slower again (4× in isolation). Models stored with float16 maps (``scale`` None) still load
and blend as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from service.geometry.uv_raster import (
    interpolation_matrix, rasterize_uv, sampling_matrix, texel_centers_uv, uv_sampling_matrix,
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
    maps : (N,P,C) int16    quantized per frame, the values ``scale[k] · maps[k]``: e.g.
                            normal displacement relative to each frame's mesh (mm, C = 1) or
                            linear RGB albedo (C = 3); with ``frames``, (K,P,C) for those;
                            float16 values themselves when ``scale`` is None (older models)
    texels : (P,) int64     flat (row-major) indices of the covered texels
    shape : (H, W)
    frames : (K,) int64 | None   the database frames the maps belong to, increasing, when
                            only some have maps (module docstring); None: every frame
    scale : (N,) float32 | None  each stored frame's quantization step (module docstring)
    """

    maps: np.ndarray
    texels: np.ndarray
    shape: tuple[int, int]
    frames: np.ndarray | None = None
    scale: np.ndarray | None = None

    @classmethod
    def from_clips(cls, actor: ActorData, clips: Sequence[Clip], stride: int,
                   attribute: str = "displacement") -> "DatabaseMaps | None":
        """The kept frames' (every ``stride``-th) maps of ``attribute`` (a key of
        :data:`MAP_ATTRIBUTES`) of the clips that have them (``frames`` set when some clips
        have none; module docstring), or None when no clip has them.

        Raises
        ------
        InvalidInput   clips whose maps differ in size or are not (F,H,W[,C])
        """
        C = MAP_ATTRIBUTES[attribute]
        have = [getattr(c, attribute) is not None for c in clips]
        if not any(have):
            return None
        kept = [len(range(0, c.frames, stride)) for c in clips]       # as the database frames
        start = np.concatenate([[0], np.cumsum(kept)[:-1]]).astype(np.int64)
        frames = None if all(have) else np.concatenate(
            [start[i] + np.arange(kept[i], dtype=np.int64) for i in range(len(clips)) if have[i]])
        clips = [c for c, h in zip(clips, have) if h]
        shapes = {np.shape(getattr(c, attribute))[1:] for c in clips}
        H, W = next(iter(shapes))[:2]
        if len(shapes) != 1 or next(iter(shapes)) != ((H, W) if C == 1 else (H, W, C)):
            raise InvalidInput(f"the clips' {attribute} maps must all be (F,H,W{'' if C == 1 else f',{C}'}) "
                               f"of one size, got {sorted(str(s) for s in shapes)}")
        texels = np.flatnonzero(rasterize_uv(actor.uv, actor.uv_faces, H, W).mask.ravel())
        maps = np.concatenate([np.asarray(getattr(c, attribute)[::stride]).reshape(-1, H * W, C)[:, texels]
                               for c in clips])
        # frame-major (C order): a request reads the active frames' maps (:mod:`.blending`);
        # the texel gather leaves them texel-major, and stored so, reading one frame's map
        # took a strided pass over the whole store (64–78 ns per texel against 7)
        q, scale = quantize(np.nan_to_num(maps))
        return cls(np.ascontiguousarray(q), texels, (int(H), int(W)), frames, scale)

    def values(self) -> np.ndarray:
        """(N,P,C) float32, the maps' values (dequantized)."""
        if self.scale is None:
            return self.maps.astype(np.float32)
        return self.maps.astype(np.float32) * self.scale[:, None, None]

    def image(self, values: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Covered-texel values (F,P,C) as maps (F,H,W) for C = 1, else (F,H,W,C), float32, at
        the stored size; 0 where no triangle covers a texel. ``out``: zeros of that shape
        (C-contiguous), written at the covered texels and returned."""
        values = np.asarray(values, dtype=np.float32)
        F, C = len(values), values.shape[-1]
        Hs, Ws = self.shape
        shape = (F, Hs, Ws) if C == 1 else (F, Hs, Ws, C)
        if out is None:
            out = np.zeros(shape, np.float32)
        elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(f"out must be C-contiguous float32 {shape}, got {out.dtype} {out.shape}")
        out.reshape(F, Hs * Ws, C)[:, self.texels] = values
        return out


@dataclass(frozen=True)
class MapBlender:
    """What blending one kind of :class:`DatabaseMaps` needs, precomputed once.

    Attributes (R regions, P covered texels)
    ----------
    database : DatabaseMaps    the stored maps
    omega_hat : (R,P) float32  the normalized per-vertex region weights interpolated to the texels
                               (the maps' blend runs in float32: :func:`.blending.blend`)
    layout : (uv (K,2), uv_faces (m,3))   the neutral's UV layout (resampling to other sizes)
    resolution : int | None    the side :meth:`image` resamples to without building an operator
    resample : (resolution², P) CSR | None   that resampling (None: the stored size is square
                               and equal to it, or no resolution was given)
    mean : (P,C) float32 | None   the mean map M̄ of the frames with maps, when only some
                               frames have maps (module docstring)
    vertex_sampler : (n,P) CSR | None   covered texels → vertices (bilinear at the vertices'
                               UVs, seams averaged), when asked for at build
    """

    database: DatabaseMaps
    omega_hat: np.ndarray
    layout: tuple
    resolution: int | None = None
    resample: sp.csr_matrix | None = None
    mean: np.ndarray | None = None
    vertex_sampler: sp.csr_matrix | None = None

    @classmethod
    def build(cls, maps: DatabaseMaps, uv: np.ndarray, uv_faces: np.ndarray, faces: np.ndarray,
              vertex_omega_hat: np.ndarray, resolution: int | None = None,
              covered: np.ndarray | None = None, vertex_sampler: bool = False) -> "MapBlender":
        """Interpolate the normalized per-vertex region weights (R,n) to the texels, and build
        the resampling to ``resolution`` texels per side if it is not the stored size
        (``covered`` (resolution, resolution) bool: the texels the layout covers at that size,
        if the caller has rasterized it already), and with ``vertex_sampler`` the texel →
        vertex sampler."""
        raster = rasterize_uv(uv, uv_faces, *maps.shape)
        P = interpolation_matrix(raster, faces, vertex_omega_hat.shape[1])[maps.texels]
        omega_hat = np.ascontiguousarray((P @ vertex_omega_hat.T).T, dtype=np.float32)
        layout = (uv, uv_faces)
        resample = None
        if resolution is not None and (resolution, resolution) != maps.shape:
            resample = _resampling(maps, layout, resolution, covered)
        mean = None
        if maps.frames is not None:
            mean = maps.values().astype(np.float64).mean(axis=0).astype(np.float32)
        sampler = None
        if vertex_sampler:
            mask = np.zeros(maps.shape[0] * maps.shape[1], bool)
            mask[maps.texels] = True
            sampler = sampling_matrix(uv, uv_faces, faces, vertex_omega_hat.shape[1],
                                      mask.reshape(maps.shape))[:, maps.texels].tocsr()
        return cls(maps, omega_hat, layout, resolution, resample, mean, sampler)

    @property
    def maps(self) -> np.ndarray:
        """(N,P,C) int16 (or float16), the stored maps (:class:`DatabaseMaps`)."""
        return self.database.maps

    @property
    def texels(self) -> np.ndarray:
        return self.database.texels

    @property
    def shape(self) -> tuple[int, int]:
        return self.database.shape

    def blend(self, weights: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """The blended map m (P,C) float32 for convex weights (R,N) over every database frame
        (eq. 4 per texel; the module docstring's rule when only some frames have maps),
        written into ``out`` (P,C) float32 if given."""
        frames, scale = self.database.frames, self.database.scale
        if frames is None:
            return blend(self.database.maps, self.omega_hat, weights, scale, dtype=np.float32, out=out)
        W = np.asarray(weights, dtype=np.float64)[:, frames]
        missing = np.clip(1.0 - W.sum(axis=1), 0.0, 1.0)                  # (R,)
        m = blend(self.database.maps, self.omega_hat, W, scale)
        m += (self.omega_hat.T @ missing)[:, None] * self.mean
        if out is None:
            return m.astype(np.float32)
        out[...] = m
        return out

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


def quantize(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values (N,…) float as (int16 (N,…), scale (N,) float32) with one step per leading
    index, ``values[k] ≈ scale[k] · q[k]``, |error| ≤ scale[k] / 2 = max|values[k]| / 65534."""
    values = np.asarray(values, np.float32)
    peak = np.abs(values.reshape(len(values), -1)).max(axis=1, initial=0.0)
    scale = np.where(peak > 0, peak / 32767, 1.0).astype(np.float32)
    shape = (-1,) + (1,) * (values.ndim - 1)
    q = np.clip(np.rint(values / scale.reshape(shape)), -32767, 32767).astype(np.int16)
    return q, scale


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

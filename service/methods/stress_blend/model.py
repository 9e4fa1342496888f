"""Training and synthesis of the stress-blend model (Digital Ira course 2014, "Real-Time
Rendering": surface stress blends the maps of the expression scans per vertex).

Training, from clips with displacement (and albedo) maps, e.g. the sample actor's training
clips (neutral → expression → neutral):

1. the local stress (:mod:`service.geometry.surface_strain`) of every frame with maps;
2. the scans: the frame of least mean stress over all clips is the neutral scan, and each
   clip's frame of largest mean stress is that clip's expression scan (the peak), K + 1
   scans in all, each with its stress field and its maps;
3. the wrinkle-map regions (:mod:`.regions`): masks from the scans' stresses and the
   per-expression importance (how much each scan's maps differ from the neutral's there).

Synthesis, for meshes (F,n,3) in vertex correspondence with the neutral (a tracked or
animated performance, e.g. the bone rig's playback; head motion does not matter, stress is
rotation invariant):

1. local stress per vertex, blend weights per vertex (:func:`.weights.shepard_weights`);
2. texel weights by barycentric interpolation over UV, blended maps
   ``M(texel) = Σ_k w_k(texel) M_k(texel)`` for displacement and albedo; the normal map
   of the blended displacement on the frame's mesh (:class:`~service.geometry.normal_map.NormalMapper`);
3. the engine's per-region weights (F,R,K) fitted to the per-vertex weights.

Maps follow :class:`~service.methods.inputs.Clip`: a displacement map is relative to its
scan's mesh, so the blended displacement is relative to the input mesh.

Departure: the course gives no formula for the stress or the blend; the stress is the
Green strain of the deformation gradients, the blend inverse-distance weighting in
stress space (both documented in their modules), chosen for the three properties the
issue asks (smooth, partition of unity, exact at the scans).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from service.geometry.laplacian import triangle_areas
from service.geometry.normal_map import NormalMapper
from service.geometry.tangent_frames import FrameField
from service.geometry.normals import vertex_normals
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv, sampling_matrix, splat
from service.methods.inputs import ActorData, Clip, InvalidInput, Progress, check_clips, no_progress
from service.methods.outputs import check_outputs
from service.methods.stress_blend import store
from service.methods.stress_blend.data import StressBlendData
from service.methods.stress_blend.outputs import DEFAULT_OUTPUTS, OUTPUTS
from service.methods.stress_blend.params import StressBlendParams
from service.methods.stress_blend.regions import RegionFit, engine_weights, region_masks
from service.geometry.surface_strain import StressField
from service.methods.stress_blend.weights import shepard_weights


@dataclass(frozen=True)
class MapBand:
    """The scans' maps of one kind at their covered texels.

    resolution : int;  index (P,) covered texels, row-major;  values (S,P,C) float32;
    interp (P,n) vertex → texel barycentric interpolation
    """

    resolution: int
    index: np.ndarray
    values: np.ndarray
    interp: sp.csr_matrix

    @classmethod
    def build(cls, uv, uv_faces, faces, n: int, maps: np.ndarray) -> "MapBand":
        """From scan maps (S,H,H[,C])."""
        H = maps.shape[1]
        raster = rasterize_uv(uv, uv_faces, H, H)
        index = np.flatnonzero(raster.mask.ravel())
        interp = interpolation_matrix(raster, faces, n)[index].tocsr()
        C = 1 if maps.ndim == 3 else maps.shape[3]
        values = maps.reshape(len(maps), H * H, C)[:, index].astype(np.float32)
        return cls(H, index, values, interp)

    def mask(self) -> np.ndarray:
        """(H,H) bool: the covered texels."""
        m = np.zeros(self.resolution ** 2, bool)
        m[self.index] = True
        return m.reshape(self.resolution, self.resolution)

    def blend(self, texel_weights: np.ndarray) -> np.ndarray:
        """Σ_k w_k M_k (P,C) for texel weights (P,S)."""
        out = texel_weights[:, :1] * self.values[0]
        for k in range(1, len(self.values)):
            out += texel_weights[:, k:k + 1] * self.values[k]
        return out

    def image(self, values: np.ndarray) -> np.ndarray:
        """(P,C) → (H,H[,C]) float32, 0 off the charts (channel axis dropped when C = 1)."""
        H = self.resolution
        out = np.zeros((H * H, values.shape[1]), np.float32)
        out[self.index] = values
        out = out.reshape(H, H, -1)
        return out[..., 0] if out.shape[2] == 1 else out


@dataclass(frozen=True)
class StressBlendEvaluator:
    """What synthesis reuses, derived once from :class:`StressBlendData`: the stress operator
    ``field``, the texel bands of the scans' maps (``albedo_band`` None without albedo), the
    engine's ``region_fit``, the normal-map machinery (``normal_mapper`` at the
    displacement resolution, ``frame_field`` the tangent frames of deformed poses) and
    ``disp_sampler`` (n,P) the displacement band's texels → vertices (``mesh_detailed``)."""

    field: StressField
    disp_band: MapBand
    albedo_band: MapBand | None
    region_fit: RegionFit
    frame_field: FrameField
    normal_mapper: NormalMapper
    disp_sampler: sp.csr_matrix

    @classmethod
    def build(cls, d: StressBlendData) -> "StressBlendEvaluator":
        n = d.n_vertices
        disp_band = MapBand.build(d.uv, d.uv_faces, d.faces, n, d.displacement)
        H = disp_band.resolution
        return cls(
            field=StressField.build(d.neutral, d.faces, d.uv, d.uv_faces, d.params.stress_smoothing),
            disp_band=disp_band,
            albedo_band=None if d.albedo is None else MapBand.build(d.uv, d.uv_faces, d.faces, n, d.albedo),
            region_fit=RegionFit.build(d.masks, d.importance, vertex_areas(d.neutral, d.faces)),
            frame_field=FrameField.build(d.neutral, d.faces, d.uv, d.uv_faces),
            normal_mapper=NormalMapper(rasterize_uv(d.uv, d.uv_faces, H, H), d.faces, d.uv, d.uv_faces, n),
            disp_sampler=sampling_matrix(d.uv, d.uv_faces, d.faces, n, disp_band.mask())[:, disp_band.index].tocsr())


class StressBlendModel:
    """A trained stress-blend model: its stored :class:`StressBlendData` and the
    :class:`StressBlendEvaluator` derived from it; :meth:`synthesize` turns meshes into
    blended maps. The stored fields read through (``model.masks`` is ``model.data.masks``);
    neither part changes after construction."""

    def __init__(self, data: StressBlendData, evaluator: StressBlendEvaluator | None = None):
        self.data = data
        self.evaluator = evaluator or StressBlendEvaluator.build(data)

    def __getattr__(self, name: str):
        # only reached for names that are not the model's own: the stored fields
        if name in _DATA_FIELDS and "data" in self.__dict__:
            return getattr(self.data, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def n_vertices(self) -> int:
        return self.data.n_vertices

    @property
    def n_scans(self) -> int:
        return self.data.n_scans

    @property
    def disp_band(self) -> MapBand:
        return self.evaluator.disp_band

    @property
    def albedo_band(self) -> MapBand | None:
        return self.evaluator.albedo_band

    # ------------------------------------------------------------------ synthesis
    def check_frames(self, vertices) -> np.ndarray:
        """(F,n,3) float64 frames; :class:`InvalidInput` for wrong shapes or non-finite frames."""
        X = np.asarray(vertices, np.float64)
        if X.ndim == 2:
            X = X[None]
        if X.ndim != 3 or X.shape[1:] != (self.n_vertices, 3) or len(X) == 0:
            raise InvalidInput(f"model expects vertices (F,{self.n_vertices},3) with F >= 1, got "
                               f"{np.shape(vertices)}")
        bad = np.flatnonzero(~np.isfinite(X).all(axis=(1, 2)))
        if len(bad):
            raise InvalidInput(f"frame {bad[0]} has non-finite vertices")
        return X

    def blend_weights(self, vertices) -> np.ndarray:
        """Per-vertex blend weights (F,n,S) of frames (F,n,3) (scan 0 the neutral)."""
        X = self.check_frames(vertices)
        return shepard_weights(self.evaluator.field.stress(X), self.data.scan_stress, self.data.params.power,
                               self.data.params.global_weight)

    def synthesize(self, vertices, outputs: Sequence[str] = DEFAULT_OUTPUTS,
                   clamp: bool = True) -> dict[str, np.ndarray]:
        """Blended maps and engine weights for meshes (F,n,3) (module docstring).

        ``clamp`` is accepted for the service's uniform call and has no effect: the Shepard
        weights are a partition of unity, so no blend leaves the scans' range.

        Returns (as asked in ``outputs``): ``vertices`` (F,n,3) float32 the input meshes
        (``mesh``); ``vertices_detailed`` (F,n,3) float32 the input meshes with the blended
        displacement sampled at the vertices and added along the vertex normals
        (``mesh_detailed``); ``displacement`` (F,H,H) mm along the normal,
        relative to the input mesh; ``albedo`` (F,Ha,Ha,3) linear RGB; ``normal_map``
        (F,H,H,3) tangent space; ``wrinkle_weights`` (F,R,K) the engine's per-region
        expression weights (:mod:`.regions`); ``blend_weights`` (F,n,S) float32; always
        ``faces``.
        """
        check_outputs(outputs, OUTPUTS)
        if "albedo" in outputs and self.albedo_band is None:
            raise InvalidInput("this model was trained without albedo maps; 'albedo' is not available")
        X = self.check_frames(vertices)
        W = shepard_weights(self.evaluator.field.stress(X), self.data.scan_stress, self.data.params.power,
                               self.data.params.global_weight)   # (F,n,S)
        out: dict[str, np.ndarray] = {"faces": self.data.faces.astype(np.int32)}
        want = set(outputs)
        if "mesh" in want:
            out["vertices"] = X.astype(np.float32)
        if want & {"displacement", "normal_map", "mesh_detailed"}:
            band = self.disp_band
            texels = [band.blend(band.interp @ w) for w in W]                 # (P,1) each
            disp = np.stack([band.image(t) for t in texels])
            if "mesh_detailed" in want:
                h = np.stack([self.evaluator.disp_sampler @ t[:, 0] for t in texels])   # (F,n)
                out["vertices_detailed"] = (X + h[..., None] * vertex_normals(X, self.data.faces)
                                            ).astype(np.float32)
            if "displacement" in want:
                out["displacement"] = disp
            if "normal_map" in want:
                out["normal_map"] = self.normal_maps(disp, X)
        if "albedo" in want:
            b = self.albedo_band
            out["albedo"] = np.stack([b.image(b.blend(b.interp @ w)) for w in W])
        if "wrinkle_weights" in want:
            out["wrinkle_weights"] = self.evaluator.region_fit.fit(W).astype(np.float32)
        if "blend_weights" in want:
            out["blend_weights"] = W.astype(np.float32)
        return out

    def normal_maps(self, displacement: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Tangent-space normal maps (F,H,H,3) of displacement maps (F,H,H) on meshes (F,n,3)."""
        ev = self.evaluator
        return np.stack([ev.normal_mapper.normal_map(d, V, ev.frame_field.frames(V))
                         for d, V in zip(displacement, X)])

    def engine_maps(self, wrinkle_weights: np.ndarray, kind: str = "displacement") -> np.ndarray:
        """The maps (F,H,H[,3]) a real-time engine renders from the region weights (F,R,K):
        ``M_0 + Σ_k (Σ_r mask_r ω_rk) (M_k − M_0)``, masks interpolated to the texels."""
        band = self.disp_band if kind == "displacement" else self.albedo_band
        if band is None:
            raise InvalidInput(f"this model has no {kind} maps")
        tm = band.interp @ self.data.masks                                      # (P,R)
        Wt = engine_weights(tm, np.asarray(wrinkle_weights, np.float64))  # (F,P,S)
        return np.stack([band.image(band.blend(w)) for w in Wt])

    def texel_masks(self) -> np.ndarray:
        """The region masks (R,H,H) at the displacement resolution (what an engine samples)."""
        tm = self.disp_band.interp @ self.data.masks
        return np.moveaxis(self.disp_band.image(tm.astype(np.float32)).reshape(
            self.disp_band.resolution, self.disp_band.resolution, -1), -1, 0)

    # ------------------------------------------------------------------ storage
    def save(self, path) -> dict:
        """Write the model directory (see :mod:`.store`)."""
        return store.write_model(self.data, self.texel_masks(), path)

    @classmethod
    def load(cls, path) -> "StressBlendModel":
        """Read a model directory written by :meth:`save`, verifying checksums."""
        return cls(store.read_model(path))


def vertex_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Barycentric vertex areas (n,) mm²."""
    A = triangle_areas(V, F) / 3.0
    return np.bincount(np.asarray(F).ravel(), weights=np.repeat(A, 3), minlength=len(V))


def _importance(actor: ActorData, maps: np.ndarray) -> np.ndarray:
    """Squared map change of each expression from the neutral at the vertices (K,n),
    normalized by its mean over vertices and expressions (maps (S,H,H[,C]))."""
    H = maps.shape[1]
    raster = rasterize_uv(actor.uv, actor.uv_faces, H, H)
    d = maps[1:].astype(np.float64) - maps[:1]
    sq = d * d if d.ndim == 3 else (d * d).sum(axis=-1)
    out = np.stack([splat(raster, s, actor.faces, actor.n_vertices, fill=0.0) for s in sq])
    return out / max(out.mean(), 1e-300)


def train(actor: ActorData, clips: Sequence[Clip], params: StressBlendParams = StressBlendParams(),
          progress: Progress = no_progress) -> StressBlendModel:
    """Pick the scans from clips with maps and build the model (module docstring).

    Raises :class:`InvalidInput` when clips do not match the actor or carry no
    displacement maps.
    """
    clips = list(clips)
    check_clips(actor, clips)
    if clips[0].displacement is None:
        raise InvalidInput("stress_blend needs clips with displacement maps (the expression scans' maps)")
    F = np.asarray(actor.faces, np.int64)
    progress(0.0, "stress")
    sf = StressField.build(actor.vertices, F, actor.uv, actor.uv_faces, params.stress_smoothing)
    stresses = []
    for i, c in enumerate(clips):
        stresses.append(sf.stress(c.vertices))
        progress(0.7 * (i + 1) / len(clips), "stress")
    level = [np.linalg.norm(s, axis=-1).mean(axis=1) for s in stresses]   # (F_c,) mean stress
    flat = np.concatenate(level)
    g = int(np.argmin(flat))
    starts = np.cumsum([0] + [c.frames for c in clips])
    ci = int(np.searchsorted(starts, g, side="right") - 1)
    picks = [(ci, g - starts[ci])] + [(i, int(np.argmax(lv))) for i, lv in enumerate(level)]
    names = [f"{clips[c].name}:{f}" for c, f in picks]
    scan_stress = np.stack([stresses[c][f] for c, f in picks])
    disp = np.stack([clips[c].displacement[f] for c, f in picks]).astype(np.float32)
    alb = (np.stack([clips[c].albedo[f] for c, f in picks]).astype(np.float32)
           if clips[0].albedo is not None else None)
    progress(0.75, "regions")
    imp = _importance(actor, disp)
    if alb is not None:
        imp = imp + _importance(actor, alb)
    masks = region_masks(actor.vertices, F, scan_stress[1:], params.regions,
                         params.region_stress_scale_mm, params.mask_smoothing, params.seed, imp)
    data = StressBlendData(params, np.asarray(actor.vertices, np.float64), F,
                           np.asarray(actor.uv, np.float64), np.asarray(actor.uv_faces, np.int64),
                           names, scan_stress, disp, alb, masks, imp)
    progress(0.85, "prepare")
    model = StressBlendModel(data)
    # the defining property, measured on the training scans themselves
    scans = np.stack([clips[c].vertices[f] for c, f in picks])
    out = model.synthesize(scans, ("displacement", "wrinkle_weights"))
    cover = model.disp_band.mask()
    dev = np.abs(out["displacement"] - disp)[:, cover].max(axis=1)
    eng = model.engine_maps(out["wrinkle_weights"])
    metrics = {
        "scans": names,
        "scan_mean_stress": [float(flat[g])] + [float(lv.max()) for lv in level],
        "scan_reproduction_max_abs_mm": float(dev.max()),
        "engine_scan_rms_mm": [float(np.sqrt(np.mean((e - d)[cover] ** 2)))
                               for e, d in zip(eng, disp)],
        "regions": int(masks.shape[1]),
        "params": params.model_dump(),
    }
    progress(1.0, "done")
    return StressBlendModel(dataclasses.replace(data, metrics=metrics), model.evaluator)


#: the stored fields a model reads through to its data
_DATA_FIELDS = frozenset(f.name for f in dataclasses.fields(StressBlendData))

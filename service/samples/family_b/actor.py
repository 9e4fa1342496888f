"""Build a family-b sample actor: the same files and manifest schema as family a, other everything.

``build_family_b(out, seed, level, units)`` writes exactly the layout of
:func:`service.samples.actor.build_sample_actor` (``manifest.json``, ``neutral.npz`` /
``.obj``, ``markers.json``, ``input_rig.npz``, ``performances/<name>.npz`` with the same
keys, dtypes and map conventions, ``tracking/``), so :mod:`service.samples.dataset`,
:func:`service.samples.uploads.sample_actor_uploads`, the methods, tests and benchmarks read
it unchanged. What differs, and where:

=====================  ====================================================================
identity               :mod:`~service.samples.family_b.skin` (extreme rig identities + warp)
mesh, UVs              :mod:`~service.samples.family_b.mesh`, :func:`~service.samples.family_b.skin.family_b_uv`
detail, albedo         :mod:`~service.samples.family_b.detail`
markers                :mod:`~service.samples.family_b.markers` (118, hex lattice)
performances           :mod:`~service.samples.family_b.performances` (25 fps, 10 clips)
unit                   ``units`` = ``"mm"`` (default), ``"cm"`` or ``"m"``: every length in
                       every file (positions, translations, displacement maps, the noise σ)
                       is written in that unit, recorded as the manifest's ``units`` and
                       ``unit_per_mm``
=====================  ====================================================================

Everything is computed in mm and scaled once when written (float64 → unit → float32).
Deterministic per seed: every random choice draws from ``np.random.default_rng([seed, …])``.
"""

from __future__ import annotations

import io
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from service.geometry.closest_point import surface_points
from service.geometry.normals import vertex_normals
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.io.atomic import atomic_open, sha256_file, write_bytes, write_npz
from service.io.markers import MarkerLayout, write_marker_layout
from service.samples import capture_noise
from service.samples.family_b import detail, markers, performances
from service.samples.family_b.skin import Skin, build_skin
from service.samples.rig import IctRig, load_ict_rig

UNITS = {"mm": 1.0, "cm": 0.1, "m": 0.001}
MAP_RESOLUTION = {0: 512, 1: 1024}
FRAME_CHUNK = 16
HELDOUT_MAP_STRIDE = 5
VARIANT_BASES = ("heldout_in_range", "heldout_combinations", "heldout_amplified")
TRACKING_STATIC = ("train_brow_raise", "train_smile", "train_brow_furrow")
TRACKING_FRAMES = 30
WORKERS = min(4, os.cpu_count() or 1)


@dataclass
class Texels:
    """Static per-texel data of the maps at one resolution."""

    resolution: int
    index: np.ndarray            # (k,) covered texels (flat)
    sampler: object              # (k,n) sparse float32: vertex values → texels
    patterns: np.ndarray         # (BANKS,k)
    amplitude: np.ndarray        # (k,)
    pores: detail.Pores
    base_albedo: np.ndarray      # (k,3)


@dataclass
class FamilyBActor:
    """Everything static about a family-b actor."""

    seed: int
    level: int
    rig: IctRig
    skin: Skin
    layout: MarkerLayout
    landmarks: detail.Landmarks
    strain: detail.StrainOperator
    patterns: np.ndarray         # (BANKS,n) at the vertices
    amplitude: np.ndarray        # (n,)
    vertex_albedo: np.ndarray    # (n,3)
    texels: Texels | None = None


def make_actor(seed: int = 1, level: int = 1, map_resolution: int | None = None,
               with_maps: bool = True) -> FamilyBActor:
    """The static part of a family-b actor (no performances)."""
    rig = load_ict_rig()
    skin = build_skin(rig, seed, level)
    V, F = skin.neutral, skin.faces
    L = skin.rig_neutral[rig.landmarks68]
    centre = V[skin.region < 2].mean(axis=0)
    axis = np.array([0.0, 0.0, centre[2] - 60.0])
    lm = detail.Landmarks(L, axis, float(np.median(np.linalg.norm((V - axis)[skin.region == 0][:, [0, 2]], axis=1))))
    layout = markers.place_markers(V, F, skin.region <= 1, L[36:48], L[48:60], seed)
    actor = FamilyBActor(seed, level, rig, skin, layout, lm, detail.StrainOperator.build(V, F),
                         detail.bank_patterns(V, lm, seed) * (skin.region <= 1),
                         detail.looseness(V, lm, seed) * (skin.region <= 1),
                         detail.base_albedo(V, lm, seed, freckles=False))
    if with_maps:
        actor.texels = _texels(actor, map_resolution or MAP_RESOLUTION[level])
    return actor


def _texels(actor: FamilyBActor, res: int) -> Texels:
    skin = actor.skin
    raster = rasterize_uv(skin.uv, skin.uv_faces, res, res)
    index = np.flatnonzero(raster.mask.ravel())
    sampler = interpolation_matrix(raster, skin.faces, len(skin.neutral))[index]
    P = sampler @ skin.neutral
    N = sampler @ vertex_normals(skin.neutral, skin.faces)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    face = (sampler @ (skin.region <= 1).astype(float)) > 0.5
    L = actor.landmarks.points
    nose_cheeks = np.exp(-np.sum((P - L[30]) ** 2, axis=1) / (2 * 20.0 ** 2))
    return Texels(res, index, sampler.astype(np.float32),
                  detail.bank_patterns(P, actor.landmarks, actor.seed) * face,
                  (detail.looseness(P, actor.landmarks, actor.seed) * face).astype(np.float32),
                  detail.pores(P, N, actor.seed, 1.0 + 0.5 * nose_cheeks),
                  detail.base_albedo(P, actor.landmarks, actor.seed, freckles=True).astype(np.float32))


def detail_maps(actor: FamilyBActor, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Displacement (H,W) mm and albedo (H/2,W/2,3) for vertex tensors c (3,n) of one frame."""
    tex = actor.texels
    res = tex.resolution
    ct = np.ascontiguousarray((tex.sampler @ c.T.astype(np.float32)).T)          # (3,k)
    crease, activation = detail.crease_height(ct, tex.patterns, tex.amplitude)
    pore, J = detail.pore_height(tex.pores, ct)
    disp = np.zeros(res * res, np.float32)
    disp[tex.index] = crease + pore
    albedo = np.zeros((res * res, 3), np.float32)
    albedo[tex.index] = detail.skin_albedo(tex.base_albedo, J, activation, crease, pore)
    albedo = albedo.reshape(res, res, 3)
    albedo = 0.25 * (albedo[0::2, 0::2] + albedo[0::2, 1::2] + albedo[1::2, 0::2] + albedo[1::2, 1::2])
    return disp.reshape(res, res), albedo


def render_performance(actor: FamilyBActor, perf: performances.Performance, map_frames,
                       albedo_frames=(), scale: float = 1.0) -> dict[str, np.ndarray]:
    """The arrays of one performance file (family a's keys), lengths × ``scale`` (unit per mm)."""
    skin, rig = actor.skin, actor.rig
    n, nf, M = len(skin.neutral), perf.frames, len(actor.layout.names)
    f32 = np.float32
    out = {
        "markers": np.empty((nf, M, 3), f32), "lowres": np.empty((nf, rig.n_vertices, 3), f32),
        "vertices_medium": np.empty((nf, n, 3), f32), "vertices": np.empty((nf, n, 3), f32),
        "vertex_albedo": np.empty((len(albedo_frames), n, 3), f32),
        "weights": perf.weights.astype(f32), "head_rotation": perf.rotation.astype(f32),
        "head_translation": (perf.translation * scale).astype(f32), "fps": f32(perf.fps),
        "map_frames": np.asarray(map_frames, np.int32),
    }
    tex = actor.texels
    if tex is not None:
        out["displacement"] = np.zeros((len(map_frames), tex.resolution, tex.resolution), f32)
        out["albedo"] = np.zeros((len(map_frames), tex.resolution // 2, tex.resolution // 2, 3), np.float16)
    map_slot = {int(f): i for i, f in enumerate(map_frames)}
    albedo_slot = {int(f): i for i, f in enumerate(albedo_frames)}
    for start in range(0, nf, FRAME_CHUNK):
        sl = slice(start, min(start + FRAME_CHUNK, nf))
        rig_v = skin.pose(rig, perf.weights[sl])
        medium = skin.upsample(rig_v)
        c = actor.strain.tensors(medium)                                   # (3,T,n)
        h, activation = detail.crease_height(c, actor.patterns, actor.amplitude)
        truth = medium + h[..., None] * vertex_normals(medium, skin.faces, weighting="area")
        for k in range(len(rig_v)):
            slot = albedo_slot.get(start + k)
            if slot is not None:
                out["vertex_albedo"][slot] = detail.skin_albedo(
                    actor.vertex_albedo, detail.area_ratio(c[:, k]), activation[k], h[k])
        if tex is not None:
            todo = [(map_slot[f], c[:, f - start]) for f in range(sl.start, sl.stop) if f in map_slot]
            with ThreadPoolExecutor(WORKERS) as pool:
                for (slot, _), (d, a) in zip(todo, pool.map(lambda job: detail_maps(actor, job[1]), todo)):
                    out["displacement"][slot] = d * scale
                    out["albedo"][slot] = a
        posed = performances.Performance(perf.name, perf.kind, perf.weights[sl], perf.rotation[sl],
                                         perf.translation[sl])
        world = posed.pose(truth)
        out["lowres"][sl] = posed.pose(rig_v) * scale
        out["vertices_medium"][sl] = posed.pose(medium) * scale
        out["vertices"][sl] = world * scale
        out["markers"][sl] = surface_points(world, skin.faces, actor.layout.triangle,
                                            actor.layout.barycentric) * scale
    return out


Progress = Callable[[float, str], None]


def build_family_b(out: str | Path, seed: int = 1, level: int = 1, units: str = "mm",
                   progress: Progress | None = None, with_tracking: bool | None = None,
                   map_resolution: int | None = None,
                   performance_names: tuple[str, ...] | None = None) -> dict:
    """Build a family-b actor into ``out`` and return its manifest.

    Parameters
    ----------
    seed : int           identity, warp, markers, performances, detail
    level : 0 or 1       mesh density (vertex counts in the manifest)
    units : "mm", "cm" or "m"   the unit of every length written
    with_tracking : camera images for the tracking method (default: when units is "mm";
                    refused in another unit, where the cameras' mm geometry would not apply)
    map_resolution : displacement map size (default 512 / 1024 by level; albedo is half)
    performance_names : build only these (variants ``<base>_noisy`` / ``_occluded`` included)
    """
    from service.io.mesh import Mesh, write_obj

    if units not in UNITS:
        raise ValueError(f"units must be one of {sorted(UNITS)}, got {units!r}")
    if with_tracking is None:
        with_tracking = units == "mm"
    if with_tracking and units != "mm":
        raise ValueError("tracking images are rendered with mm cameras: use units='mm' or with_tracking=False")
    scale = UNITS[units]
    t0 = time.perf_counter()
    report = progress or (lambda fraction, stage: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report(0.0, "identity, mesh, markers and detail")
    actor = make_actor(seed, level, map_resolution)
    skin, rig = actor.skin, actor.rig
    files: dict[str, dict] = {}

    def record(name, digest, **info):
        files[name] = {"sha256": digest, "bytes": (out / name).stat().st_size, **info}

    V = (skin.neutral * scale).astype(np.float32)
    record("neutral.npz", write_npz(out / "neutral.npz", {
        "vertices": V, "faces": skin.faces.astype(np.int32), "uv": skin.uv.astype(np.float32),
        "uv_faces": skin.uv_faces.astype(np.int32), "region": skin.region.astype(np.int8),
        "rig_vertices": (skin.rig_neutral * scale).astype(np.float32),
    }), description=f"high-resolution neutral mesh with UVs in [0,1]^2, {units}")
    with atomic_open(out / "neutral.obj") as f:
        write_obj(f, Mesh(V.astype(np.float64), skin.faces, skin.uv, skin.uv_faces))
    record("neutral.obj", sha256_file(out / "neutral.obj"), description="neutral.npz as OBJ")
    buf = io.BytesIO()
    write_marker_layout(buf, actor.layout)
    record("markers.json", write_bytes(out / "markers.json", buf.getvalue()),
           description="marker layout, API.md PUT /markers form")
    record("input_rig.npz", write_npz(out / "input_rig.npz", {
        "vertices": (skin.rig_neutral * scale).astype(np.float32),
        "faces": rig.triangles.astype(np.int32), "uv": skin.rig_uv.astype(np.float32),
        "uv_faces": rig.triangle_uv.astype(np.int32),
    }), description="low-resolution input rig (the ICT topology) in the actor's warped neutral")

    names = rig.expression_names
    perfs = performances.all_performances(names, seed)
    variants = {capture_noise.variant_name(b, v): b for b in VARIANT_BASES for v in capture_noise.VARIANTS}
    wanted = {p.name for p in perfs} | set(variants)
    if performance_names is not None:
        unknown = set(performance_names) - wanted
        if unknown:
            raise ValueError(f"unknown performances {sorted(unknown)}; known: {sorted(wanted)}")
        wanted = set(performance_names)
        perfs = [p for p in perfs if p.name in wanted or p.name in {variants[v] for v in wanted & set(variants)}]
        with_tracking = with_tracking and {"heldout_in_range", *TRACKING_STATIC} <= wanted
    total = sum(p.frames for p in perfs)
    done = 0
    static, tracked, written = {}, None, {}
    for perf in perfs:
        report(0.05 + 0.85 * done / total, f"performance {perf.name}")
        if perf.kind in ("training", "database"):
            map_frames = np.arange(perf.frames)
        else:
            map_frames = np.arange(0, perf.frames, HELDOUT_MAP_STRIDE)
        peak = int(np.argmax(perf.weights.sum(axis=1)))
        albedo_frames = ((0, peak) if with_tracking and perf.name in TRACKING_STATIC else
                         range(TRACKING_FRAMES) if with_tracking and perf.name == "heldout_in_range" else ())
        arrays = render_performance(actor, perf, map_frames, albedo_frames, scale)
        albedo = arrays.pop("vertex_albedo")
        if with_tracking and perf.name in TRACKING_STATIC:
            static.setdefault("neutral", (arrays["vertices"][0], albedo[0]))
            static[perf.name] = (arrays["vertices"][peak], albedo[1])
        if with_tracking and perf.name == "heldout_in_range":
            tracked = (arrays["vertices"][:TRACKING_FRAMES], albedo)
        entries = [(perf.name, arrays, {})] if perf.name in wanted else []
        if perf.name in VARIANT_BASES:
            made = capture_noise.marker_variants(arrays["markers"], perf.fps, scale, seed,
                                                 capture_noise.variant_salt(perf.name))
            entries += [(capture_noise.variant_name(perf.name, v),
                         capture_noise.variant_arrays(arrays, made[v]["markers"]),
                         {**made[v]["info"], "base": perf.name})
                        for v in capture_noise.VARIANTS if capture_noise.variant_name(perf.name, v) in wanted]
        for stem, data, info in entries:
            name = f"performances/{stem}.npz"
            record(name, write_npz(out / name, data), kind=perf.kind, frames=perf.frames,
                   map_frames=len(map_frames), **info)
            written[stem] = {"kind": perf.kind, "frames": perf.frames, **info}
        done += perf.frames

    if with_tracking:
        from service.samples.render import write_tracking_data

        report(0.9, "tracking cameras and images")
        shim = type("TrackedActor", (), {"skin": skin, "rig": rig})()
        for name, digest in write_tracking_data(shim, out, static, tracked, performances.FPS, WORKERS).items():
            record(name, digest)

    manifest = {
        "kind": "facesynth.sample_actor",
        "version": 1,
        "family": "b",
        "seed": seed,
        "level": level,
        "units": units,
        "unit_per_mm": scale,
        "axes": "x to the actor's left, y up, z out of the face",
        "vertices": int(len(skin.neutral)),
        "triangles": int(len(skin.faces)),
        "rig_vertices": int(rig.n_vertices),
        "markers": len(actor.layout.names),
        "map_resolution": actor.texels.resolution,
        "albedo_resolution": actor.texels.resolution // 2,
        "fps": performances.FPS,
        "identity": skin.identity.round(6).tolist(),
        "wrinkle_sites": [f"crease_bank_{round(180 * k / detail.BANKS)}deg" for k in range(detail.BANKS)],
        "expression_names": list(names),
        "performances": written,
        "head_pivot": (performances.HEAD_PIVOT_MM * scale).tolist(),
        "files": files,
        "build_seconds": round(time.perf_counter() - t0, 1),
        "source": "family b generator (service/samples/family_b) on the ICT-FaceKit Face Model "
                  "Light (MIT), service/samples/data/LICENSE",
    }
    write_bytes(out / "manifest.json", json.dumps(manifest, indent=1).encode())
    report(1.0, "done")
    return manifest

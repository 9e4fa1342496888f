"""Build the sample actor: skin, markers, performances with ground-truth detail, maps.

``build_sample_actor(out, seed, level)`` writes (all lengths in mm, float32):

    manifest.json              what is where, with sha256 of every file
    neutral.npz                vertices (V,3), faces, uv, uv_faces, region, rig_vertices
    neutral.obj                the same mesh as OBJ (vertex order preserved)
    markers.json               the marker layout (API.md PUT /markers, triangle + barycentric)
    input_rig.npz              the low-resolution rig topology (vertices, faces, uv, uv_faces)
    performances/<name>.npz    per frame: markers (F,M,3), lowres (F,n0,3), vertices_medium
                               (F,V,3) (no fine detail), vertices (F,V,3) (ground truth with
                               detail), weights (F,53), head_rotation (F,3,3),
                               head_translation (F,3), fps; and for the frames in
                               map_frames: displacement (f,H,W) (normal displacement over
                               vertices_medium, mm, float32) and albedo (f,H/2,W/2,3)
                               (linear RGB, float16 as in a half EXR); map_frames (f,)
                               (the database performance has maps at every frame up to
                               level 1; at level 2 it has no maps and no vertices_medium)
    performances/<base>_noisy.npz, performances/<base>_occluded.npz
                               for every base in VARIANT_BASES: the base performance's
                               arrays with noisy (σ 0.3 mm) or occluded (NaN bursts)
                               markers, the clean ones beside them as markers_clean
                               (service.samples.capture_noise); the manifest's entry names
                               its base and variant
    tracking/...               cameras and rendered images (see service.samples.render)

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

from service.geometry.normals import vertex_normals
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.io.atomic import atomic_open, sha256_file, write_bytes, write_npz
from service.io.markers import write_marker_layout
from service.samples import capture_noise, detail, performances
from service.samples.markers import MarkerLayout, place_markers
from service.samples.render import write_tracking_data
from service.samples.rig import IctRig, load_ict_rig
from service.samples.skin import Skin, build_skin, identity_coefficients

MARKER_COUNT = 150
FRAME_CHUNK = 48                    # frames processed at once (bounds peak memory)
HELDOUT_MAP_STRIDE = 5              # held-out performances get maps every 5th frame
DATABASE_MAPS_MAX_LEVEL = 1         # the database performance has maps up to this level
TRACKING_STATIC = ("train_brow_raise", "train_smile", "train_brow_furrow")  # + neutral
TRACKING_FRAMES = 30                # frames (1 s) of the held-out performance rendered per camera
MAP_RESOLUTION = {0: 512, 1: 1024, 2: 2048}
VARIANT_BASES = ("heldout_in_range", "heldout_combinations", "heldout_amplified")
WORKERS = min(4, os.cpu_count() or 1)   # threads for per-frame maps and camera images


@dataclass
class SampleActor:
    """Everything static about the sample actor (what the performances are rendered from)."""

    seed: int
    level: int
    rig: IctRig
    skin: Skin
    markers: MarkerLayout
    sites: list
    vertex_patterns: list
    rest_normals: np.ndarray          # (3,n) unit normals of the neutral (component-major)
    rest_strain: np.ndarray           # (6,n) strain tensors of the neutral itself (Voigt)
    vertex_albedo: np.ndarray         # (n,3) static albedo at the vertices
    wrinkle_faces: np.ndarray         # (w,) triangles touching a vertex some site displaces
    texels: "TexelData | None" = None


@dataclass
class TexelData:
    """Static per-texel data of the detail maps at one resolution."""

    resolution: int
    index: np.ndarray            # (k,) flat indices of covered texels
    sampler: object              # (k,n) sparse: vertex values → covered texels
    patterns: list
    pores: detail.PoreField
    base_albedo: np.ndarray      # (k,3)
    rest_strain: np.ndarray      # (6,k) float32 (Voigt, component-major)


def make_actor(seed: int = 1, level: int = 1, map_resolution: int | None = None,
               with_maps: bool = True) -> SampleActor:
    """The static part of the sample actor (no performances)."""
    rig = load_ict_rig()
    skin = build_skin(rig, identity_coefficients(seed), level)
    lm = skin.rig_neutral[rig.landmarks68]
    layout = place_markers(skin.neutral, skin.faces, skin.region == 0, lm[36:48], lm[60:68],
                           MARKER_COUNT, seed)
    sites = detail.wrinkle_sites(skin.rig_neutral, rig.landmarks68)
    N0 = vertex_normals(skin.neutral, skin.faces)
    Q0 = skin.S @ detail.surface_strain(skin.rig_neutral, skin.rig_neutral, rig.triangles)
    patterns = detail.site_patterns(sites, skin.neutral, N0)
    displaced = np.zeros(len(skin.neutral), bool)
    for idx, _, _ in patterns:
        displaced[idx] = True
    actor = SampleActor(seed, level, rig, skin, layout, sites, patterns,
                        np.ascontiguousarray(N0.T), np.ascontiguousarray(Q0.T),
                        detail.base_albedo(skin.neutral, lm, None, seed),
                        np.flatnonzero(displaced[skin.faces].any(axis=1)))
    if with_maps:
        actor.texels = _texel_data(actor, map_resolution or MAP_RESOLUTION[level], N0)
    return actor


def sample_neutral(level: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Neutral (V (n,3), F (m,3)) and marker handle vertices (150,) of the sample actor."""
    actor = make_actor(seed, level, with_maps=False)
    return actor.skin.neutral, actor.skin.faces, actor.markers.vertex


def _texel_data(actor: SampleActor, res: int, N0: np.ndarray) -> TexelData:
    skin = actor.skin
    raster = rasterize_uv(skin.uv, skin.uv_faces, res, res)
    index = np.flatnonzero(raster.mask.ravel())
    sampler = interpolation_matrix(raster, skin.faces, len(skin.neutral))[index].astype(np.float32)
    P = sampler @ skin.neutral
    N = sampler @ N0
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    tri = raster.triangle.ravel()[index]
    # rest Jacobian d(position)/d(uv) of every triangle, mm per uv unit
    Fp, Fu = skin.faces[tri], skin.uv_faces[tri]
    dP = np.stack([skin.neutral[Fp[:, 1]] - skin.neutral[Fp[:, 0]],
                   skin.neutral[Fp[:, 2]] - skin.neutral[Fp[:, 0]]], axis=-1)
    dU = np.stack([skin.uv[Fu[:, 1]] - skin.uv[Fu[:, 0]], skin.uv[Fu[:, 2]] - skin.uv[Fu[:, 0]]], axis=-1)
    J0 = dP @ np.linalg.inv(dU)
    r, c = np.divmod(index, res)
    uv = np.stack([(c + 0.5) / res, 1.0 - (r + 0.5) / res], axis=1)
    lm = actor.skin.rig_neutral[actor.rig.landmarks68]
    nose_cheeks = np.exp(-np.sum((P - lm[30]) ** 2, axis=1) / (2 * 18.0 ** 2))
    pores = detail.pore_field(uv, J0, N, actor.seed, 1.0 + 0.6 * nose_cheeks)
    # per-frame texel arithmetic runs in float32: detail is < 2 mm, so ~1e-7 mm rounding
    pores = detail.PoreField(*(np.asarray(x, np.float32) for x in vars(pores).values()))
    patterns = [(i, p.astype(np.float32), a.astype(np.float32))
                for i, p, a in detail.site_patterns(actor.sites, P, N)]
    return TexelData(res, index, sampler, patterns, pores,
                     detail.base_albedo(P, lm, index, actor.seed).astype(np.float32),
                     _at_texels(sampler, actor.rest_strain))


def _at_texels(sampler, X: np.ndarray) -> np.ndarray:
    """Component-major vertex values X (C,n) interpolated at the texels: (C,k) float32."""
    return np.ascontiguousarray((sampler @ X.T.astype(np.float32)).T)


def render_performance(actor: SampleActor, perf: performances.Performance,
                       map_frames: np.ndarray, albedo_frames=()) -> dict[str, np.ndarray]:
    """Markers, meshes and maps of one performance (keys in the module docstring).

    Per frame: rig pose → strain tensors of the rig surface → high-resolution medium
    surface ``S @ pose`` → wrinkles along its normals (ground truth) → head pose; markers
    sit on the ground-truth skin. Maps only for the frames listed in ``map_frames``;
    per-vertex albedo (key ``vertex_albedo``, (len(albedo_frames),n,3), for the camera
    images) only for ``albedo_frames``.
    """
    skin, rig = actor.skin, actor.rig
    n, nf = len(skin.neutral), perf.frames
    out = {
        "markers": np.empty((nf, MARKER_COUNT, 3), np.float32),
        "lowres": np.empty((nf, rig.n_vertices, 3), np.float32),
        "vertices_medium": np.empty((nf, n, 3), np.float32),
        "vertices": np.empty((nf, n, 3), np.float32),
        "vertex_albedo": np.empty((len(albedo_frames), n, 3), np.float32),
        "weights": perf.weights.astype(np.float32),
        "head_rotation": perf.rotation.astype(np.float32),
        "head_translation": perf.translation.astype(np.float32),
        "fps": np.float32(perf.fps),
        "map_frames": np.asarray(map_frames, dtype=np.int32),
    }
    tex = actor.texels
    if tex is not None:
        res = tex.resolution
        out["displacement"] = np.zeros((len(map_frames), res, res), np.float32)
        out["albedo"] = np.zeros((len(map_frames), res // 2, res // 2, 3), np.float16)
    map_slot = {int(f): i for i, f in enumerate(map_frames)}
    albedo_slot = {int(f): i for i, f in enumerate(albedo_frames)}
    for start in range(0, nf, FRAME_CHUNK):
        sl = slice(start, min(start + FRAME_CHUNK, nf))
        rig_v = skin.rig_neutral + rig.expression_offsets(perf.weights[sl])
        Q_rig = detail.surface_strain(skin.rig_neutral, rig_v, rig.triangles)
        medium = skin.upsample(rig_v)
        Q = np.ascontiguousarray(skin.upsample(Q_rig).transpose(2, 0, 1))   # (6,T,n)
        # normals are only needed where wrinkles displace: the triangles around those vertices
        normals = vertex_normals(medium, skin.faces[actor.wrinkle_faces], weighting="area")
        h, activation = detail.wrinkle_height(actor.sites, actor.vertex_patterns, Q,
                                              actor.rest_strain, n)
        truth = medium + h[..., None] * normals
        for k in range(len(rig_v)):
            slot = albedo_slot.get(start + k)
            if slot is not None:
                out["vertex_albedo"][slot] = detail.skin_albedo(
                    actor.vertex_albedo, detail.area_ratio(Q[:, k], actor.rest_normals,
                                                           actor.rest_strain), activation[k])
        if tex is not None:
            # NumPy releases the GIL in the large per-texel array operations: two threads
            # keep both cores busy
            todo = [(map_slot[f], Q[:, f - start]) for f in range(sl.start, sl.stop) if f in map_slot]
            with ThreadPoolExecutor(WORKERS) as pool:
                for (slot, _), maps in zip(todo, pool.map(lambda job: detail_maps(actor, job[1]), todo)):
                    out["displacement"][slot], out["albedo"][slot] = maps
        posed = performances.Performance(perf.name, perf.kind, perf.weights[sl],
                                         perf.rotation[sl], perf.translation[sl])
        out["lowres"][sl] = posed.pose(rig_v)
        out["vertices_medium"][sl] = posed.pose(medium)
        out["vertices"][sl] = posed_truth = posed.pose(truth)
        out["markers"][sl] = actor.markers.positions(posed_truth, skin.faces)
    return out


def detail_maps(actor: SampleActor, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Displacement (H,W) mm and albedo (H/2,W/2,3) maps for vertex strain tensors Q (6,n).

    Texels outside the UV charts are 0. Albedo is computed at full resolution and
    box-filtered 2×2 (anti-aliasing the pore darkening).
    """
    tex = actor.texels
    res, k = tex.resolution, len(tex.index)
    Qt = _at_texels(tex.sampler, Q)
    wrinkles, activation = detail.wrinkle_height(actor.sites, tex.patterns, Qt, tex.rest_strain, k)
    pores, area = detail.pore_height(tex.pores, Qt, tex.rest_strain)
    disp = np.zeros(res * res, np.float32)
    disp[tex.index] = wrinkles + pores
    albedo = np.zeros((res * res, 3), np.float32)
    albedo[tex.index] = detail.skin_albedo(tex.base_albedo, area, activation, pores)
    albedo = albedo.reshape(res, res, 3)
    albedo = 0.25 * (albedo[0::2, 0::2] + albedo[0::2, 1::2] + albedo[1::2, 0::2] + albedo[1::2, 1::2])
    return disp.reshape(res, res), albedo


Progress = Callable[[float, str], None]


def build_sample_actor(out: str | Path, seed: int = 1, level: int = 1,
                       progress: Progress | None = None,
                       with_tracking: bool = True,
                       map_resolution: int | None = None,
                       performance_names: tuple[str, ...] | None = None,
                       database_maps: bool | None = None) -> dict:
    """Build the sample actor into directory ``out`` and return its manifest.

    Parameters
    ----------
    seed : int         identity, marker layout, performances and detail are all seeded
    level : 0, 1, 2    rig resolution, ~45k or ~179k vertices
    progress : callable(fraction in [0,1], stage) or None
    with_tracking : also render camera images for the tracking method
    map_resolution : displacement map size (default 512/1024/2048 by level; albedo is half)
    performance_names : build only these performances (default: all)
    database_maps : give the database performance maps at every frame (and keep its
                    ``vertices_medium``, which makes them relative to its meshes), for
                    methods that transfer map detail (shape space). Default: at levels 0
                    and 1; at level 2 they would hold 14 GB (630 frames of 2048² maps)
    """
    from service.io.mesh import Mesh, write_obj

    t0 = time.perf_counter()
    report = progress or (lambda fraction, stage: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report(0.0, "skin, markers and detail sites")
    actor = make_actor(seed, level, map_resolution)
    skin, rig = actor.skin, actor.rig
    files: dict[str, dict] = {}

    def record(name: str, digest: str, **info) -> None:
        files[name] = {"sha256": digest, "bytes": (out / name).stat().st_size, **info}

    record("neutral.npz", write_npz(out / "neutral.npz", {
        "vertices": skin.neutral.astype(np.float32), "faces": skin.faces.astype(np.int32),
        "uv": skin.uv.astype(np.float32), "uv_faces": skin.uv_faces.astype(np.int32),
        "region": skin.region.astype(np.int8), "rig_vertices": skin.rig_neutral.astype(np.float32),
    }), description="high-resolution neutral mesh with UVs in [0,1]^2, mm")
    with atomic_open(out / "neutral.obj") as f:
        write_obj(f, Mesh(skin.neutral.astype(np.float32).astype(np.float64), skin.faces,
                          skin.uv, skin.uv_faces))
    record("neutral.obj", sha256_file(out / "neutral.obj"), description="neutral.npz as OBJ")
    layout_json = io.BytesIO()
    write_marker_layout(layout_json, actor.markers.to_layout())
    record("markers.json", write_bytes(out / "markers.json", layout_json.getvalue()),
           description="marker layout, API.md PUT /markers form")
    record("input_rig.npz", write_npz(out / "input_rig.npz", {
        "vertices": skin.rig_neutral.astype(np.float32), "faces": rig.triangles.astype(np.int32),
        "uv": skin.rig_uv.astype(np.float32),
        "uv_faces": rig.triangle_uv.astype(np.int32),
    }), description="low-resolution input rig (the ICT topology) in the actor's neutral")

    names = rig.expression_names
    perfs = (performances.training_clips(names, seed)
             + [performances.heldout_in_range(names, seed),
                performances.heldout_out_of_range(names, seed),
                performances.heldout_combinations(names, seed),
                performances.heldout_amplified(names, seed),
                performances.database_performance(names, seed)])
    variants = {capture_noise.variant_name(b, v): (b, v)
                for b in VARIANT_BASES for v in capture_noise.VARIANTS}
    wanted = {p.name for p in perfs} | set(variants)
    if performance_names is not None:
        unknown = set(performance_names) - wanted
        if unknown:
            raise ValueError(f"unknown performances {sorted(unknown)}; known: {sorted(wanted)}")
        wanted = set(performance_names)
        perfs = [p for p in perfs if p.name in wanted
                 or any(variants[v][0] == p.name for v in wanted & set(variants))]
        with_tracking = with_tracking and {"heldout_in_range", *TRACKING_STATIC} <= set(performance_names)
    if database_maps is None:
        database_maps = level <= DATABASE_MAPS_MAX_LEVEL
    total = sum(p.frames for p in perfs)
    done = 0
    static, tracked = {}, None
    written: dict[str, dict] = {}
    for perf in perfs:
        report(0.05 + 0.85 * done / total, f"performance {perf.name}")
        if perf.kind == "training" or (perf.kind == "database" and database_maps):
            map_frames = np.arange(perf.frames)
        elif perf.kind.startswith("heldout"):
            map_frames = np.arange(0, perf.frames, HELDOUT_MAP_STRIDE)
        else:
            map_frames = np.arange(0)
        peak = int(np.argmax(perf.weights.sum(axis=1)))
        albedo_frames = ((0, peak) if with_tracking and perf.name in TRACKING_STATIC else
                         range(TRACKING_FRAMES) if with_tracking and perf.kind == "heldout_in_range"
                         else ())
        arrays = render_performance(actor, perf, map_frames, albedo_frames)
        albedo = arrays.pop("vertex_albedo")
        if perf.name in TRACKING_STATIC and with_tracking:
            if not static:
                static["neutral"] = (arrays["vertices"][0], albedo[0])
            static[perf.name] = (arrays["vertices"][peak], albedo[1])
        if perf.kind == "heldout_in_range" and with_tracking:
            tracked = (arrays["vertices"][:TRACKING_FRAMES], albedo)
        if perf.kind == "database" and not database_maps:
            del arrays["vertices_medium"]
        entries = []
        if perf.name in wanted:
            entries.append((perf.name, arrays, {}))
        if perf.name in VARIANT_BASES:
            made = capture_noise.marker_variants(arrays["markers"], perf.fps, 1.0, seed,
                                                 capture_noise.variant_salt(perf.name))
            entries += [(capture_noise.variant_name(perf.name, v),
                         capture_noise.variant_arrays(arrays, made[v]["markers"]),
                         {**made[v]["info"], "base": perf.name})
                        for v in capture_noise.VARIANTS
                        if capture_noise.variant_name(perf.name, v) in wanted]
        for stem, data, info in entries:
            name = f"performances/{stem}.npz"
            record(name, write_npz(out / name, data), kind=perf.kind, frames=perf.frames,
                   map_frames=len(map_frames), **info)
            written[stem] = {"kind": perf.kind, "frames": perf.frames, **info}
        done += perf.frames

    if with_tracking:
        report(0.9, "tracking cameras and images")
        for name, digest in write_tracking_data(actor, out, static, tracked, performances.FPS, WORKERS).items():
            record(name, digest)

    manifest = {
        "kind": "facesynth.sample_actor",
        "version": 1,
        "seed": seed,
        "level": level,
        "units": "mm",
        "axes": "x to the actor's left, y up, z out of the face",
        "vertices": int(len(skin.neutral)),
        "triangles": int(len(skin.faces)),
        "rig_vertices": int(rig.n_vertices),
        "markers": MARKER_COUNT,
        "map_resolution": actor.texels.resolution,
        "albedo_resolution": actor.texels.resolution // 2,
        "fps": performances.FPS,
        "identity": identity_coefficients(seed).round(6).tolist(),
        "wrinkle_sites": [s.name for s in actor.sites],
        "expression_names": list(names),
        "performances": written,
        "files": files,
        "build_seconds": round(time.perf_counter() - t0, 1),
        "source": "ICT-FaceKit Face Model Light (MIT), service/samples/data/LICENSE",
    }
    write_bytes(out / "manifest.json", json.dumps(manifest, indent=1).encode())
    report(1.0, "done")
    return manifest

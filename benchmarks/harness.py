"""What the benchmark reports share: the sample actor's data, fresh-process workers with
peak-memory measurement, the cached model builds (PDM per order, shape-space and pose-space
model per parameter set, input-rig registration) and their workers, the fine-detail metric at
the map texels, the PDM baseline, and figure helpers. Each report imports this module (``import
harness``); no report imports another.

Workers (fresh processes, :func:`run_worker`): ``python benchmarks/harness.py train-pdm
ACTOR ORDER MODEL_DIR``, ``train-shape-space ACTOR PARAMS_JSON MODEL_DIR``,
``register-rig ACTOR OUT_NPZ``, ``train-pose-space ACTOR PARAMS_JSON MODEL_DIR``; each prints
its JSON record as the last line.

Peak memory: a worker resets the resident-set high-water mark (``echo 5 >
/proc/self/clear_refs``) and reports ``VmHWM − VmRSS`` at the reset, the peak resident
memory the measured step added (C allocations included).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SEED, LEVEL = 1, 1                     # the default sample actor
HELDOUT = ("heldout_in_range", "heldout_out_of_range")
FACE = "face"                          # actor region of the main metrics
BASIC_OUTPUTS = ("mesh", "displacement")
NEUTRAL_CLIP = "train_brow_raise"      # its frame 0 gives the static neutral map
SCORED_REGIONS = (FACE, "narrow_face") # ... and the marker-covered part of it (region 0)
GT_ROW = "ground truth (mesh + relative map)"
OUT = ROOT / "benchmarks" / "out"
PDM_MODELS = OUT / "pdm" / "models"    # pdm_report's models, one per order (also game_outputs_report's)
SHAPE_SPACE_MODELS = OUT / "shape_space" / "models"   # shape-space models, PDM, rig registrations
GENERALIZATION = OUT / "generalization"             # generalization_report's output (issue 17)
GENERALIZATION_MODELS = GENERALIZATION / "models"   # its PDMs (also confidence_factors') and pose-space models
#: issue 17's held-out input ranges (report name → performance) and marker conditions (→ file suffix)
HELDOUT_RANGES = {"in range": "heldout_in_range", "combinations": "heldout_combinations",
                  "out of range": "heldout_amplified"}
MARKER_CONDITIONS = {"clean": "", "noisy": "_noisy", "occluded": "_occluded"}
PDM_ORDERS = ("linear", "biquadratic")
SHAPE_SPACE_LIBRARY = ROOT / "service" / "methods" / "shape_space"
DATABASE = "database"                  # the shape-space database performance
SS_OUTPUTS = ("mesh", "displacement")  # displacement: the blended fine maps (database with maps)
QUICK_FRAMES = 6                       # held-out map frames per performance in quick runs
FIGURE_SEPARATION = 20                 # strong-expression figure frames at least this far apart
LANDMARKS = 40                         # detail-transfer landmark pairs (bickel2008 §5.4: ~40)


def actor_dir(family: str = "a", level: int = LEVEL) -> Path:
    """Where every report keeps the seed-1 sample actor of ``family`` at ``level``."""
    return OUT / (f"actor-{family}-l{level}" if family != "a" or level != LEVEL else "actor-l1")


def ensure_actor(actor_dir: Path, seed: int = SEED, level: int = LEVEL, family: str = "a",
                 with_tracking: bool = True) -> None:
    """Build a sample actor of ``family`` (default a, level 1, seed 1) into ``actor_dir``
    unless it is there."""
    if (actor_dir / "manifest.json").is_file():
        return
    print(f"building family {family} (level {level}) into {actor_dir} (a few minutes)", file=sys.stderr)
    if family == "a":
        from service.samples.actor import build_sample_actor

        build_sample_actor(actor_dir, seed=seed, level=level, with_tracking=with_tracking)
    else:
        from service.samples.family_b.actor import build_family_b

        build_family_b(actor_dir, seed=seed, level=level, with_tracking=with_tracking)


def sample_actor(family: str = "a", level: int = LEVEL, with_tracking: bool = True) -> Path:
    """The directory of the seed-1 sample actor of ``family`` at ``level``, built if missing."""
    path = actor_dir(family, level)
    ensure_actor(path, level=level, family=family, with_tracking=with_tracking)
    return path


def training_clips(actor_dir: Path, actor):
    from service.samples.dataset import load_clip, performance_names

    return [load_clip(actor_dir, name, actor) for name in performance_names(actor_dir, "train_")]


def farthest_points(V: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """Indices (k,) of k points of V (n,3) by farthest-point sampling from a seeded random start."""
    rng = np.random.default_rng(seed)
    idx = [int(rng.integers(len(V)))]
    d = np.linalg.norm(V - V[idx[0]], axis=1)
    for _ in range(k - 1):
        idx.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(V - V[idx[-1]], axis=1))
    return np.array(idx)


def face_landmarks(actor, k: int = LANDMARKS) -> np.ndarray:
    """Vertex indices (k,) of detail-transfer landmarks (bickel2008 §5.4): farthest-point
    samples of the actor's face-region vertices (an :class:`~service.methods.inputs.ActorData`)."""
    face = np.flatnonzero(actor.regions[FACE])
    return face[farthest_points(actor.vertices[face], k)]


@dataclass
class Heldout:
    """Ground truth of one held-out performance at its evaluated map frames (world pose).

    frames (k,) frame numbers; vertices, medium (k,n,3) float64 mm; markers (k,M,3);
    displacement (k,H,H) float32 mm, all detail along the normal of ``medium``;
    strength (k,) sum of the expression weights (to pick strong frames).
    """

    name: str
    frames: np.ndarray
    vertices: np.ndarray
    medium: np.ndarray
    markers: np.ndarray
    displacement: np.ndarray
    strength: np.ndarray


def load_heldout(actor_dir: Path, name: str, limit: int | None) -> Heldout:
    """The map frames of a held-out performance (``limit``: that many, evenly spaced)."""
    with np.load(actor_dir / "performances" / f"{name}.npz") as d:
        mf = d["map_frames"].astype(np.int64)
        slots = np.arange(len(mf))
        if limit is not None and limit < len(mf):
            slots = np.unique(np.round(np.linspace(0, len(mf) - 1, limit)).astype(np.int64))
        f = mf[slots]
        return Heldout(name, f, d["vertices"][f].astype(np.float64),
                       d["vertices_medium"][f].astype(np.float64), d["markers"][f].astype(np.float64),
                       d["displacement"][slots].astype(np.float32), d["weights"][f].sum(axis=1))


def status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def reset_peak() -> int:
    """Reset the high-water mark; the resident kB it is measured from."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return status_kb("VmRSS")
    except OSError:
        return status_kb("VmHWM")


def peak_mb(rss0_kb: int) -> float:
    return (status_kb("VmHWM") - rss0_kb) / 1024


def train_pdm(actor_dir: Path, order: str, model_dir: Path, marker_noise_mm: float | str = 0.0,
              params_json: str = "{}") -> dict:
    """Train a PDM of ``order`` (and ``marker_noise_mm``; other :class:`PdmParams` fields
    from ``params_json``) on the actor's training clips and save it into ``model_dir``; wall
    time and peak RSS of ``train`` (run it in a fresh process: :func:`run_worker`)."""
    from service.methods.pdm.model import PdmParams, train
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    clips = training_clips(actor_dir, actor)
    params = PdmParams(**{**json.loads(params_json), "order": order, "marker_noise_mm": marker_noise_mm})
    rss0 = reset_peak()
    t0 = time.perf_counter()
    model = train(actor, clips, params,
                  lambda fr, stage: print(f"    [{order}] {fr:4.0%} {stage}", file=sys.stderr))
    res = {"order": order, "train_s": time.perf_counter() - t0, "peak_rss_mb": peak_mb(rss0),
           "frames": sum(c.frames for c in clips)}
    model.save(model_dir)
    return res


def median_ms(fn, calls: int, warmup: int = 3) -> float:
    """Median wall time (ms) of ``calls`` calls ``fn(k)`` (k = 0, 1, …) after ``warmup``."""
    for k in range(warmup):
        fn(k)
    times = []
    for k in range(calls):
        t0 = time.perf_counter()
        fn(k)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def run_worker(script: str, *args: str, cores: int | None = None) -> dict:
    """Run ``script`` (a report's own file) as a worker in a fresh process; its JSON result
    (last stdout line). ``cores``: pinned to that many CPUs, thread pools to match."""
    env, preexec = dict(os.environ), None
    if cores:
        cpus = sorted(os.sched_getaffinity(0))[:cores]
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
            env[var] = str(len(cpus))
        preexec = lambda: os.sched_setaffinity(0, cpus)       # noqa: E731
    proc = subprocess.run([sys.executable, script, *args], stdout=subprocess.PIPE, text=True,
                          check=False, env=env, preexec_fn=preexec)
    if proc.returncode != 0:
        sys.exit(f"worker {' '.join(args)} failed (exit {proc.returncode})")
    return json.loads(proc.stdout.strip().splitlines()[-1])


@dataclass
class DetailTexels:
    """Fine-map texels and the operators of the detail-height metric (module docstring).

    index (P,) covered texels (row-major) of the H×H map; interp (P,n) vertex → texel;
    corner (P,) first vertex of each texel's triangle; regions: actor region → (P,) bool
    (the texel's triangle's first vertex in the region); split: training's band split.
    """

    H: int
    index: np.ndarray
    interp: object
    corner: np.ndarray
    regions: dict
    split: object                      # service.methods.pdm.model.BandFilter

    @property
    def face(self) -> np.ndarray:
        return self.regions[FACE]

    @classmethod
    def build(cls, actor, H: int, sigma: float) -> "DetailTexels":
        from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
        from service.methods.pdm.model import BandFilter

        raster = rasterize_uv(actor.uv, actor.uv_faces, H, H)
        index = np.flatnonzero(raster.mask.ravel())
        interp = interpolation_matrix(raster, actor.faces, actor.n_vertices)[index].tocsr()
        corner = actor.faces[raster.triangle.ravel()[index], 0]
        regions = {k: np.asarray(v, bool)[corner] for k, v in actor.regions.items()}
        return cls(H, index, interp, corner, regions, BandFilter.build(H, index, sigma))

    def normals(self, medium: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Unit normals (k,P,3) float32 of the medium surfaces (k,n,3) at the texels."""
        from service.geometry.normals import vertex_normals

        out = np.empty((len(medium), len(self.index), 3), np.float32)
        for f, V in enumerate(medium):
            n = self.interp @ vertex_normals(V, faces, weighting="area")
            out[f] = n / np.linalg.norm(n, axis=1, keepdims=True)
        return out

    def highpass(self, values: np.ndarray) -> np.ndarray:
        """The fine band ``h − G_σ∗h`` (P,) of heights at the covered texels (training's split)."""
        return self.split.highpass(np.asarray(values, np.float64))

    def heights(self, V: np.ndarray, medium: np.ndarray, normals: np.ndarray,
                d: np.ndarray | None) -> np.ndarray:
        """Detail heights ``n·(P V − P V_medium) + d`` (P,) of one frame's mesh V and map d (P,)."""
        h = np.einsum("pd,pd->p", normals, self.interp @ (V - medium))
        return h if d is None else h + d

    def texels(self, image: np.ndarray) -> np.ndarray:
        """Covered texels (…,P) of maps (…,H,H)."""
        return image.reshape(*image.shape[:-2], -1)[..., self.index]

    def truth_map(self, actor, gt) -> np.ndarray:
        """The ground truth's map relative to its own mesh at the covered texels (k,P):
        ``displacement − vertex_detail_map`` (what its scans' maps hold; with the truth's
        mesh it scores the metric's floor)."""
        from service.samples.dataset import vertex_detail_map

        return self.texels(gt.displacement - vertex_detail_map(actor, gt.vertices, gt.medium, self.H))

    def image(self, values: np.ndarray, only_face: bool = True) -> np.ndarray:
        """(P,) texel values → (H,H) map, NaN off the covered (face) texels."""
        img = np.full(self.H * self.H, np.nan)
        keep = self.face if only_face else np.ones(len(self.index), bool)
        img[self.index[keep]] = values[keep]
        return img.reshape(self.H, self.H)


def pdm_prediction(model, markers, tex: DetailTexels, clamp: bool = True):
    out = model.synthesize(markers, BASIC_OUTPUTS, clamp=clamp)
    return out["vertices"].astype(np.float64), tex.texels(out["displacement"]), out["clamped"]


def camera(actor, centre=None, zoom: float = 1.0, size: int = 480):
    """A front camera 600 mm away framing the narrow face (neutral pose), or ``zoom``× closer
    around ``centre`` (3,)."""
    from service.samples.render import face_cameras

    V = actor.vertices[np.asarray(actor.regions["narrow_face"])]
    lo, hi = V.min(axis=0), V.max(axis=0)
    if centre is None:
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
    return face_cameras(np.asarray(centre, np.float64), distance=600.0, size=size, yaws_deg=(0.0,),
                        field_mm=1.2 * (hi[1] - lo[1]) / zoom)[0]


def plot_grazing(meshes: list[tuple[str, np.ndarray]], actor, zoom_centre: np.ndarray, caption: str,
                 path: Path) -> None:
    """(d) grey meshes (head pose removed) under grazing light: whole face, and a 3× close-up."""
    from PIL import Image, ImageDraw, ImageFont

    from service.samples.gallery import GRAZING_LIGHT
    from service.samples.render import shade, to_srgb8, write_png

    full, close = camera(actor), camera(actor, zoom_centre, zoom=3.0)
    grey = np.full((actor.n_vertices, 3), 0.6)
    font = ImageFont.load_default(size=15)
    rows = []
    for cam, suffix in ((full, caption), (close, "3x close-up")):
        tiles = []
        for label, V in meshes:
            img = Image.fromarray(to_srgb8(shade(cam, V, actor.faces, grey, light_dir=GRAZING_LIGHT, ambient=0.05)))
            ImageDraw.Draw(img).multiline_text((8, 6), f"{label}\n{suffix}", fill=(255, 255, 255), font=font)
            tiles.append(np.asarray(img))
        rows.append(np.concatenate(tiles, axis=1))
    write_png(path, np.concatenate(rows, axis=0))


def zoom_centre(tex: DetailTexels, hp_gt: np.ndarray, vertices: np.ndarray, sigma: float = 15.0) -> np.ndarray:
    """Where the ground truth's fine detail is strongest: the vertex (3,) under the texel of
    largest Gaussian-smoothed squared high-passed height in the narrow face."""
    from scipy.ndimage import gaussian_filter

    img = np.zeros(tex.H * tex.H)
    img[tex.index] = hp_gt ** 2
    energy = gaussian_filter(img.reshape(tex.H, tex.H), sigma).ravel()[tex.index]
    energy[~tex.regions["narrow_face"]] = -1.0
    return vertices[tex.corner[np.argmax(energy)]]


def git_state() -> str:
    """Commit of the checkout and the library files with uncommitted changes (others edit in parallel)."""
    def git(*a):
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()

    dirty = [line[3:] for line in git("status", "--porcelain", "--", "service").splitlines()]
    return f"commit {git('rev-parse', '--short', 'HEAD')}" + (
        f", uncommitted changes in {', '.join(dirty)}" if dirty else ", service/ clean")


class DetailMetric:
    """The detail metric on held-out frames, for a study with ``actor`` and ``tex``
    (:class:`DetailTexels`): blend_study.py and local_blend_study.py."""

    def prepared(self, gt):
        """A held-out performance (``harness.Heldout``) with the truth's normals (k,P,3), detail
        ``hp`` (k,P) and map relative to its mesh ``rel_map`` (k,P) added."""
        tex = self.tex
        gt.normals = tex.normals(gt.medium, self.actor.faces)
        gt.hp = np.stack([tex.highpass(tex.texels(d)) for d in gt.displacement])
        gt.rel_map = tex.truth_map(self.actor, gt)
        return gt

    def hp(self, gt, V: np.ndarray, D: np.ndarray | None) -> np.ndarray:
        """(k,P) high-passed detail heights of meshes V (k,n,3) world, maps D (k,P)."""
        tex = self.tex
        return np.stack([tex.highpass(tex.heights(V[f], gt.medium[f], gt.normals[f], None if D is None else D[f]))
                         for f in range(len(V))])

    def score(self, gt, hp: np.ndarray, V: np.ndarray | None = None) -> dict:
        """rel err and r of detail heights hp (k,P) at the face texels; with meshes V (k,n,3)
        also the mean and max face vertex error (mm)."""
        face = self.tex.face
        x, y = hp[:, face].ravel(), gt.hp[:, face].ravel()
        out = {"rel": float(np.sqrt(np.sum((x - y) ** 2) / np.sum(y ** 2))),
               "r": float(np.corrcoef(x, y)[0, 1])}
        if V is not None:
            e = np.linalg.norm(V - gt.vertices, axis=-1)[:, np.asarray(self.actor.regions[FACE])]
            out.update(mean=float(e.mean()), max=float(e.max()))
        return out


# methods: (world vertices (k,n,3), fine maps at the texels (k,P) or None, clamped (k,) or None)
@dataclass
class Baselines:
    """What the baselines need from the training data and the biquadratic model."""

    model: object                      # the PdmModel whose deformation drives everything
    detailed: object                   # BaseSurface of the detailed neutral
    neutral_map: np.ndarray            # (P,) fine map of a neutral training frame
    train_aligned: np.ndarray          # (T,M,3) aligned training markers
    train_c: np.ndarray                # (T,n,3) float32 medium detail in base frames
    train_maps: np.ndarray             # (T,P) float32 relative fine maps

    @classmethod
    def build(cls, actor, clips, model, tex: DetailTexels) -> "Baselines":
        from service.methods.pdm.base_surface import BaseSurface

        base = model.evaluator.base
        detailed = BaseSurface.from_smooth(actor.vertices, actor.faces, actor.uv, actor.uv_faces,
                                           base.handles, base.rest_markers)
        markers = np.concatenate([c.markers for c in clips])
        pose, u_H, _ = model.evaluator.deformation(markers)
        V = np.concatenate([c.vertices for c in clips])
        c = np.empty(V.shape, np.float32)
        for t in range(len(V)):
            X = base.deform(u_H[t:t + 1])
            c[t] = np.einsum("fnij,fnj->fni", base.frames(X), pose[t:t + 1].remove(V[t:t + 1]) - X)[0]
        maps = np.concatenate([tex.texels(cl.displacement) for cl in clips]).astype(np.float32)
        neutral = next(cl for cl in clips if cl.name == NEUTRAL_CLIP)
        return cls(model, detailed, tex.texels(neutral.displacement[0]), pose.remove(markers), c, maps)

    def no_detail(self, markers):
        pose, u_H, _ = self.model.evaluator.deformation(markers)
        return pose.restore(self.detailed.deform(u_H)), None, None

    def static_neutral_map(self, markers):
        V, _, _ = self.no_detail(markers)
        return V, np.broadcast_to(self.neutral_map, (len(markers), len(self.neutral_map))), None

    def nearest(self, markers) -> tuple[np.ndarray, np.ndarray, None, np.ndarray]:
        """Also returns the chosen training frame (k,) (global index)."""
        base = self.model.evaluator.base
        pose, u_H, _ = self.model.evaluator.deformation(markers)
        a = pose.remove(markers)
        d2 = np.nansum((a[:, None] - self.train_aligned[None]) ** 2, axis=(2, 3))    # (k,T)
        t = np.argmin(d2, axis=1)
        X = base.deform(u_H)
        V = pose.restore(X + np.einsum("fnji,fnj->fni", base.frames(X), self.train_c[t]))
        return V, self.train_maps[t], None, t


@dataclass
class Scores:
    """Pooled accumulators of one method on one performance, over one vertex and texel set."""

    vertices: np.ndarray                                   # (n,) bool scored vertices
    texels: np.ndarray                                     # (P,) bool scored texels
    vertex_errors: list = field(default_factory=list)     # (k_v,) per frame, mm
    sums: np.ndarray = field(default_factory=lambda: np.zeros(6))   # n, Σx, Σy, Σxx, Σyy, Σxy

    def add(self, err: np.ndarray, hp: np.ndarray, hp_gt: np.ndarray) -> None:
        """One frame: vertex errors (n,), predicted and ground-truth high-passed heights (P,)."""
        self.vertex_errors.append(err[self.vertices].astype(np.float32))
        x, y = hp[self.texels], hp_gt[self.texels]
        self.sums += [len(x), x.sum(), y.sum(), x @ x, y @ y, x @ y]

    def result(self) -> dict:
        e = np.concatenate(self.vertex_errors)
        n, sx, sy, sxx, syy, sxy = self.sums
        cov, vx, vy = sxy - sx * sy / n, sxx - sx * sx / n, syy - sy * sy / n
        return {"medium_mean_mm": float(e.mean()), "medium_p95_mm": float(np.percentile(e, 95)),
                "fine_r": float(cov / np.sqrt(vx * vy)) if vx > 0 else float("nan"),
                "fine_rms_mm": float(np.sqrt(max(sxx - 2 * sxy + syy, 0.0) / n))}


def evaluate_performance(gt: Heldout, methods: dict, tex: DetailTexels, actor, keep_frames) -> dict:
    """Scores of every method on one performance; the figure data of frames ``keep_frames``.

    methods: name → callable(markers) → (V, d, clamped[, extra]).
    Returns {"scores": region → name → metrics, "clamped": name → mean fraction,
    "signal_rms_mm": region → GT high-passed RMS, "figure": {...}, "extra": name → extra}.
    """
    normals = tex.normals(gt.medium, actor.faces)
    gt_hp = np.stack([tex.highpass(tex.texels(d)) for d in gt.displacement])       # (k,P)
    signal = {r: float(np.sqrt(np.mean(gt_hp[:, tex.regions[r]] ** 2))) for r in SCORED_REGIONS}
    keep = [int(np.flatnonzero(gt.frames == f)[0]) for f in keep_frames]
    figure = {"gt_hp": {gt.frames[i]: gt_hp[i] for i in keep}, "hp": {}, "vertex_error": {}}
    scores = {r: {} for r in SCORED_REGIONS}
    clamped_mean, extra = {}, {}

    # the metric's floor: the ground truth's mesh and relative map through the same pipeline
    relative = tex.truth_map(actor, gt)
    methods = {GT_ROW: lambda m: (gt.vertices, relative, None), **methods}
    for name, method in methods.items():
        t0 = time.perf_counter()
        V, D, clamped, *more = method(gt.markers)
        if more:
            extra[name] = more[0]
        acc = {r: Scores(np.asarray(actor.regions[r]), tex.regions[r]) for r in SCORED_REGIONS}
        for f in range(len(gt.frames)):
            err = np.linalg.norm(V[f] - gt.vertices[f], axis=-1)
            hp = tex.highpass(tex.heights(V[f], gt.medium[f], normals[f], None if D is None else D[f]))
            for a in acc.values():
                a.add(err, hp, gt_hp[f])
            if f in keep:
                figure["hp"][(name, gt.frames[f])] = hp
                figure["vertex_error"][(name, gt.frames[f])] = err
        for r, a in acc.items():
            scores[r][name] = a.result()
        clamped_mean[name] = None if clamped is None else float(np.mean(clamped))
        print(f"    {gt.name} / {name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return {"scores": scores, "clamped": clamped_mean, "signal_rms_mm": signal, "figure": figure,
            "extra": extra}


def pdm_in_fresh_process(actor_dir: Path, order: str, model_dir: Path, marker_noise_mm: float | str = 0.0,
                         params: dict | None = None) -> dict:
    """:func:`train_pdm` run in a fresh process (its own peak memory); the training record."""
    return run_worker(__file__, "train-pdm", str(actor_dir), order, str(model_dir), str(marker_noise_mm),
                      json.dumps(params or {}))


def train_pdm_models(actor_dir: Path, orders, reuse: bool, models: Path = PDM_MODELS) -> dict[str, dict]:
    """Train (or with ``reuse`` keep) one PDM per order under ``models`` (``<order>/`` and its
    record ``<order>.train.json``), each in a fresh process; the training records."""
    stats = {}
    for order in orders:
        model_dir, record = models / order, models / f"{order}.train.json"
        if reuse and (model_dir / "manifest.json").is_file() and record.is_file():
            stats[order] = json.loads(record.read_text())
            print(f"  reusing {order} model", file=sys.stderr)
            continue
        print(f"  training {order} ...", file=sys.stderr)
        stats[order] = pdm_in_fresh_process(actor_dir, order, model_dir)
        record.write_text(json.dumps(stats[order]))
        print(f"  {order}: {stats[order]['train_s']:.1f} s", file=sys.stderr)
    return stats


def strong_frames(gt: Heldout, count: int, separation: int) -> list[int]:
    """Frame numbers of the ``count`` strongest expressions, greedily ≥ ``separation`` apart."""
    chosen: list[int] = []
    for i in np.argsort(-gt.strength, kind="stable"):
        f = int(gt.frames[i])
        if all(abs(f - c) >= separation for c in chosen):
            chosen.append(f)
        if len(chosen) == count:
            break
    return sorted(chosen)


def face_box(tex: DetailTexels, pad: int = 8) -> tuple[slice, slice]:
    """Rows and columns of the map around the face texels (``pad`` texels of margin)."""
    r, c = np.divmod(tex.index[tex.face], tex.H)
    return (slice(max(r.min() - pad, 0), min(r.max() + pad + 1, tex.H)),
            slice(max(c.min() - pad, 0), min(c.max() + pad + 1, tex.H)))


# --------------------------------------------------------------------------------------
# cache keys and the shape-space builds

def sha(data: bytes | str, n: int = 10) -> str:
    return hashlib.sha256(data.encode() if isinstance(data, str) else data).hexdigest()[:n]


def library_fingerprint() -> str:
    """sha256 (10 hex) of the shape-space library sources (another engineer edits them)."""
    h = hashlib.sha256()
    for f in sorted(SHAPE_SPACE_LIBRARY.glob("*.py")):
        h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()[:10]


def actor_files_key(actor_dir: Path, *files: str) -> str:
    """Key of an actor's files from its manifest's sha256 (level and seed included)."""
    manifest = json.loads((actor_dir / "manifest.json").read_text())
    parts = [f"l{manifest['level']}s{manifest['seed']}"] + [manifest["files"][f]["sha256"] for f in files]
    return f"l{manifest['level']}-" + sha("|".join(parts))


def actor_level(actor_dir: Path) -> int:
    return int(json.loads((actor_dir / "manifest.json").read_text())["level"])


def params_json(params) -> str:
    """Method parameters (a pydantic :class:`~service.methods.params.MethodParams`) as sorted JSON."""
    return json.dumps(params.model_dump(mode="json"), sort_keys=True)


def load_database(actor_dir: Path, actor):
    """The ``database`` performance as a Clip: with its maps (relative to its meshes) where
    the actor has them (levels 0–1), else float32 vertices only (the library converts them;
    at level 2 a float64 copy would cost 2.7 GB)."""
    from service.methods.inputs import Clip
    from service.samples.dataset import load_clip

    with np.load(actor_dir / "performances" / f"{DATABASE}.npz") as d:
        if "displacement" in d.files:
            return load_clip(actor_dir, DATABASE, actor)
        return Clip(DATABASE, d["vertices"], d["markers"].astype(np.float64), fps=float(d["fps"]))


def train_shape_space(actor_dir: Path, params: str, model_dir: Path) -> dict:
    """Build a shape-space model from the database (``params`` JSON overrides of
    ShapeSpaceParams); wall time and peak RSS of ``train`` (run it in a fresh process)."""
    from service.methods.shape_space import ShapeSpaceParams, train
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    clip = load_database(actor_dir, actor)
    p = ShapeSpaceParams(**json.loads(params))
    stages = {}
    load0 = os.getloadavg()[0]
    rss0 = reset_peak()
    t0 = time.perf_counter()

    def progress(fraction, stage):
        stages.setdefault(stage, time.perf_counter() - t0)
        print(f"    [shape-space {p.smoothing}] {fraction:4.0%} {stage} ({time.perf_counter() - t0:.0f} s)",
              file=sys.stderr)

    model = train(actor, [clip], p, progress)
    res = {"train_s": time.perf_counter() - t0, "peak_rss_mb": peak_mb(rss0),
           "load_average": [load0, os.getloadavg()[0]],
           "stages_s": stages, "frames": clip.frames, "vertices": actor.n_vertices,
           "metrics": {k: model.metrics[k] for k in ("database_frames", "patches", "regions", "detail_bytes")
                       if k in model.metrics},
           "params": json.loads(params), "library": library_fingerprint()}
    model.save(model_dir)
    return res


def register_input_rig(actor_dir: Path, out: Path) -> dict:
    """Register ``input_rig.npz`` to the neutral (no landmarks) into ``out``; time and
    residual stats (run it in a fresh process)."""
    from service.methods.shape_space.registration import register_rig

    with np.load(actor_dir / "input_rig.npz") as r, np.load(actor_dir / "neutral.npz") as n:
        rig_v, rig_f = r["vertices"].astype(np.float64), r["faces"].astype(np.int64)
        V, F = n["vertices"].astype(np.float64), n["faces"].astype(np.int64)
    rss0 = reset_peak()
    t0 = time.perf_counter()
    reg = register_rig(rig_v, rig_f, V, F)
    res = {"register_s": time.perf_counter() - t0, "peak_rss_mb": peak_mb(rss0),
           "stats": {k: float(v) for k, v in reg.stats.items()}, "rig_vertices": len(rig_v),
           "library": library_fingerprint()}
    out.write_bytes(reg.save())
    return res


def cached(record: Path, ready: bool, retrain: bool, build) -> dict:
    """The build record at ``record`` if the build is ``ready`` (and not ``retrain``), else
    ``build()``'s, written there; ``reused`` says which."""
    if ready and record.is_file() and not retrain:
        rec = json.loads(record.read_text())
        rec["reused"] = True
        return rec
    rec = build()
    record.write_text(json.dumps(rec))
    rec["reused"] = False
    return rec


def shape_space_paths(actor_dir: Path, params) -> tuple[Path, Path]:
    """The cached model directory of ``params`` on the actor's database and its build record."""
    key = f"{actor_files_key(actor_dir, 'neutral.npz', 'markers.json', f'performances/{DATABASE}.npz')}" \
          f"-{params.smoothing}-{sha(params_json(params))}"
    return SHAPE_SPACE_MODELS / f"shape_space-{key}", SHAPE_SPACE_MODELS / f"shape_space-{key}.train.json"


def shape_space_loadable(model_dir: Path) -> bool:
    """A model directory whose manifest has the library's current format (the store's format
    changes while the library is being worked on; an older model cannot be loaded)."""
    from service.methods.shape_space.store import FORMAT_VERSION

    try:
        return json.loads((model_dir / "manifest.json").read_text())["format_version"] == FORMAT_VERSION
    except (OSError, KeyError, ValueError):
        return False


def shape_space_cached(actor_dir: Path, params) -> bool:
    model_dir, record = shape_space_paths(actor_dir, params)
    return shape_space_loadable(model_dir) and record.is_file()


def shape_space_model(actor_dir: Path, params, retrain: bool) -> tuple[Path, dict]:
    """The model directory of ``params`` on the actor's database (built in a fresh process
    unless cached) and its build record."""
    model_dir, record = shape_space_paths(actor_dir, params)

    def build():
        print(f"  building shape-space model {model_dir.name} (fresh process) ...", file=sys.stderr)
        return run_worker(__file__, "train-shape-space", str(actor_dir), params_json(params), str(model_dir))

    SHAPE_SPACE_MODELS.mkdir(parents=True, exist_ok=True)
    rec = cached(record, shape_space_loadable(model_dir), retrain, build)
    print(f"  shape-space {params.smoothing}: {'reused' if rec['reused'] else 'built'}, "
          f"build {rec['train_s']:.0f} s", file=sys.stderr)
    return model_dir, rec


def rig_registration(actor_dir: Path, retrain: bool):
    """The actor's ``input_rig.npz`` registered to its neutral (in a fresh process unless
    cached): the RigRegistration and its build record."""
    from service.methods.shape_space.registration import RigRegistration

    key = actor_files_key(actor_dir, "neutral.npz", "input_rig.npz")
    path = SHAPE_SPACE_MODELS / f"rig_registration-{key}.npz"
    record = SHAPE_SPACE_MODELS / f"rig_registration-{key}.json"

    def build():
        print("  registering input_rig.npz to the neutral (fresh process) ...", file=sys.stderr)
        return run_worker(__file__, "register-rig", str(actor_dir), str(path))

    SHAPE_SPACE_MODELS.mkdir(parents=True, exist_ok=True)
    rec = cached(record, path.is_file(), retrain, build)
    return RigRegistration.load(path.read_bytes()), rec


def heldout_frames(actor_dir: Path, name: str, limit: int | None) -> Heldout:
    """``limit`` map frames of a held-out performance, evenly spaced between (not at) its ends
    (the performances start and end near the neutral)."""
    gt = load_heldout(actor_dir, name, None)
    if limit is None or limit >= len(gt.frames):
        return gt
    keep = np.unique(np.round(np.linspace(0, len(gt.frames) - 1, limit + 2)[1:-1]).astype(np.int64))
    return Heldout(name, *(getattr(gt, f.name)[keep] for f in dataclasses.fields(gt)[1:]))


def noise_arg(text: str) -> float | str:
    """``--marker-noise`` and ``--marker-filter``: a number (mm; frames) or "auto" (estimated
    from the input)."""
    return text if text == "auto" else float(text)


def train_pose_space(actor_dir: Path, params: str, model_dir: Path) -> dict:
    """Train a pose-space model (``params``: the JSON of a :class:`WpsdParams` or
    :class:`PsdParams`, told apart by ``method``) on the actor's training clips and save it into
    ``model_dir``; wall and CPU time and peak RSS of ``train`` (run it in a fresh process)."""
    from service.methods.pose_space import train
    from service.methods.pose_space.params import parse_params
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    clips = training_clips(actor_dir, actor)
    p = parse_params(json.loads(params))
    load0 = os.getloadavg()[0]
    rss0 = reset_peak()
    t0, c0 = time.perf_counter(), time.process_time()
    model = train(actor, clips, p)
    res = {"train_s": time.perf_counter() - t0, "train_cpu_s": time.process_time() - c0,
           "peak_rss_mb": peak_mb(rss0), "load_average": [load0, os.getloadavg()[0]],
           "frames": sum(c.frames for c in clips), "params": json.loads(params)}
    model.save(model_dir)
    return res


def pose_space_model(actor_dir: Path, params, retrain: bool,
                     models_dir: Path = GENERALIZATION_MODELS) -> tuple[Path, dict]:
    """The model directory of pose-space ``params`` (every field, so a changed default is
    another model) on the actor's training clips, built in a fresh process unless cached under
    ``models_dir``, and its build record."""
    from service.samples.dataset import performance_names

    files = ["neutral.npz", "markers.json"] + [f"performances/{n}.npz" for n in performance_names(actor_dir, "train_")]
    key = f"{actor_files_key(actor_dir, *files)}-{params.method}-{sha(params_json(params))}"
    model_dir, record = models_dir / f"pose_space-{key}", models_dir / f"pose_space-{key}.train.json"

    def build():
        print(f"  training pose-space model {model_dir.name} (fresh process) ...", file=sys.stderr)
        return run_worker(__file__, "train-pose-space", str(actor_dir), params_json(params), str(model_dir))

    models_dir.mkdir(parents=True, exist_ok=True)
    rec = cached(record, (model_dir / "manifest.json").is_file(), retrain, build)
    print(f"  pose-space {model_dir.name}: {'reused' if rec['reused'] else 'built'}, "
          f"training {rec['train_s']:.0f} s ({rec['train_cpu_s']:.0f} s CPU)", file=sys.stderr)
    return model_dir, rec


def generalization_pdm_models(actor_dir: Path, retrain: bool, marker_noise_mm: float | str = 0.0,
                              params: dict | None = None, orders=None,
                              models_dir: Path = GENERALIZATION_MODELS) -> dict:
    """Linear and biquadratic PDMs of the actor's training clips (fresh process each, cached
    under ``models_dir``, default :data:`GENERALIZATION_MODELS`), trained with
    ``marker_noise_mm`` and the other :class:`PdmParams` fields ``params``."""
    from service.methods.pdm.model import PdmModel
    from service.methods.pdm.params import PdmParams
    from service.samples.dataset import performance_names

    files = ["neutral.npz", "markers.json"] + [f"performances/{n}.npz" for n in performance_names(actor_dir, "train_")]
    # the defaults are part of the key: a changed default trains new models
    key = f"{actor_files_key(actor_dir, *files)}-d{sha(PdmParams().model_dump_json(), 6)}"
    models = {}
    for order in orders or PDM_ORDERS:
        noise = marker_noise_mm if isinstance(marker_noise_mm, str) else f"{marker_noise_mm:g}"
        model_dir = models_dir / (
            f"pdm_{order}-{key}" + (f"-noise{noise}" if marker_noise_mm else "")
            + (f"-p{hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:8]}" if params else ""))
        if retrain or not (model_dir / "manifest.json").is_file():
            print(f"  training PDM {order} (fresh process) ...", file=sys.stderr)
            pdm_in_fresh_process(actor_dir, order, model_dir, marker_noise_mm, params)
        models[order] = PdmModel.load(model_dir)
    return models


def variant_markers(actor_dir: Path, name: str, frames: np.ndarray, filter_frames: float | str = 0.0,
                    modes=None) -> np.ndarray:
    """The performance's markers at ``frames``; with ``filter_frames`` > 0 or "auto" the whole
    performance is first smoothed in time (:func:`~service.geometry.marker_filter.filter_performance`,
    as the synthesis job's ``marker_filter_frames`` does with the model's ``marker_modes``:
    ``modes``)."""
    from service.geometry.marker_filter import filter_performance

    with np.load(actor_dir / "performances" / f"{name}.npz") as d:
        markers = d["markers"].astype(np.float64)
    return (filter_performance(markers, filter_frames, modes=modes) if filter_frames else markers)[frames]


WORKERS = {
    "train-pdm": lambda actor, order, model, noise="0", params="{}": train_pdm(
        Path(actor), order, Path(model), noise if noise == "auto" else float(noise), params),
    "train-shape-space": lambda actor, params, model: train_shape_space(Path(actor), params, Path(model)),
    "register-rig": lambda actor, out: register_input_rig(Path(actor), Path(out)),
    "train-pose-space": lambda actor, params, model: train_pose_space(Path(actor), params, Path(model)),
}

# ---------------------------------------------------------------------------- servers
def source_tree(rev: str, work: Path) -> Path:
    """The ``service`` and ``models_store`` packages of commit ``rev``, unpacked once into
    ``work/rev-<rev>`` (a server of it runs with that directory first on its path)."""
    import re
    import tarfile

    where = work / f"rev-{re.sub(r'[^0-9A-Za-z_.-]', '_', rev)}"
    if not (where / "service" / "__init__.py").is_file():
        where.mkdir(parents=True, exist_ok=True)
        archive = where / "source.tar"
        with open(archive, "wb") as f:
            subprocess.run(["git", "archive", rev, "service", "models_store"], cwd=ROOT,
                           stdout=f, check=True)
        with tarfile.open(archive) as tar:
            tar.extractall(where, filter="data")
        archive.unlink()
    return where


def renamed_package(rev: str) -> str:
    """Unpack ``rev``'s ``service`` as the package ``service_<rev>`` (imports renamed) under
    ``benchmarks/out/realtime_ab/<rev>`` on ``sys.path``, and return its name: an older
    commit's code imported beside this tree's in one process, for paired A/B timings
    (``realtime_ab.py``, ``enhance_speed.py --against``; ``models_store`` is shared)."""
    import re
    import tarfile

    name = "service_" + re.sub(r"\W", "_", rev)
    where = OUT / "realtime_ab" / rev
    target = where / name
    if not (target / "__init__.py").is_file():
        where.mkdir(parents=True, exist_ok=True)
        archive = where / "service.tar"
        with open(archive, "wb") as f:
            subprocess.run(["git", "archive", rev, "service"], cwd=ROOT, stdout=f, check=True)
        with tarfile.open(archive) as tar:
            tar.extractall(where / "tmp", filter="data")
        (where / "tmp" / "service").rename(target)
        pattern = re.compile(r"\b(from|import) service(\.| )|\"service\.")
        for py in target.rglob("*.py"):
            text = py.read_text()
            py.write_text(pattern.sub(lambda m: (f"{m.group(1)} {name}{m.group(2)}" if m.group(1)
                                                 else f'"{name}.'), text))
    if str(where) not in sys.path:
        sys.path.insert(0, str(where))
    return name


REALTIME = OUT / "realtime"            # realtime.py's PDM model (shared with cold_start, realtime_ab)
REALTIME_PERFORMANCE = "heldout_in_range"
REALTIME_TRAIN_CLIP = "train_smile"    # the clip the server's model row names (never trained there)
REALTIME_FRAMES = 50                   # distinct frames cycled through
WARMUP = 3                             # untimed calls before a median
NPZ_TYPE = {"Content-Type": "application/x-npz"}


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, as reported beside every timing."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def ensure_realtime_model(actor_dir: Path) -> Path:
    """The benchmark's PDM model of ``actor_dir`` (default parameters), trained once per set
    of defaults (the directory is keyed by them: a changed default trains a new model)."""
    from service.methods.pdm.params import PdmParams

    model_dir = REALTIME / f"model-{actor_dir.name}-{sha(PdmParams().model_dump_json(), 8)}"
    if not (model_dir / "manifest.json").is_file():
        print(f"training the PDM of {actor_dir} into {model_dir} ...", file=sys.stderr, flush=True)
        code = ("import sys, json; sys.path.insert(0, %r); import harness; from pathlib import Path; "
                "print(json.dumps(harness.train_pdm(Path(%r), 'biquadratic', Path(%r))))"
                % (str(Path(__file__).resolve().parent), str(actor_dir), str(model_dir)))
        subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)
    return model_dir


def heldout_markers(actor_dir: Path) -> np.ndarray:
    """(FRAMES, M, 3) float32: the first frames of the held-out performance's markers, the
    frames the serving benchmarks send."""
    with np.load(actor_dir / "performances" / f"{REALTIME_PERFORMANCE}.npz") as d:
        return d["markers"][:REALTIME_FRAMES].astype(np.float32)


def register_model(base: str, work: Path, actor_dir: Path, model_dir: Path) -> str:
    """Upload the actor and one clip through the API, create a PDM model row, and mark it
    ready with the benchmark's trained directory (the same model as in-process); reused
    from ``work`` on later runs."""
    import httpx

    from models_store import registry
    from service.config import Settings
    from service.samples.uploads import sample_actor_uploads
    from service.store.container import get_store

    record = work / "model_id"
    with httpx.Client(base_url=base, timeout=600) as client:
        if record.is_file():
            model_id = record.read_text().strip()
            if client.get(f"/v1/models/{model_id}").json().get("status") == "ready":
                return model_id
        neutral, layout, clips = sample_actor_uploads(actor_dir, (REALTIME_TRAIN_CLIP,))
        canonical = json.loads(layout)
        body = {"markers": [{"name": n, "triangle": t, "barycentric": b} for n, t, b in
                            zip(canonical["names"], canonical["triangle"], canonical["barycentric"])]}
        actor_id = client.post("/v1/actors", json={"name": "realtime"}).json()["id"]
        client.put(f"/v1/actors/{actor_id}/neutral", content=neutral, headers=NPZ_TYPE).raise_for_status()
        client.put(f"/v1/actors/{actor_id}/markers", json=body).raise_for_status()
        clip = client.post(f"/v1/actors/{actor_id}/clips", content=clips[REALTIME_TRAIN_CLIP], headers=NPZ_TYPE,
                           params={"name": REALTIME_TRAIN_CLIP})
        clip.raise_for_status()
        accepted = client.post(f"/v1/actors/{actor_id}/models",
                               json={"kind": "pdm", "clips": [clip.json()["clip_id"]]})
        accepted.raise_for_status()
        model_id = accepted.json()["model_id"]
    store = get_store(Settings(data_dir=work / "data"))
    metrics = json.loads((model_dir / "manifest.json").read_text()).get("metrics", {})
    with store.session() as session:
        registry.mark_model_ready(session, store.blobs, model_id, model_dir, metrics=metrics)
    record.write_text(model_id)
    return model_id


def free_port() -> int:
    """A free TCP port on the loopback interface."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(work: Path, port: int, env: dict[str, str], repo: Path = ROOT
                 ) -> subprocess.Popen:
    """A ``facesynth serve`` of the checkout ``repo`` on ``port`` with its data in
    ``work/data`` (log: ``work/server.log``; one embedded worker unless ``env`` says
    otherwise), once ``/readyz`` answers 200 (RuntimeError after 120 s)."""
    import httpx

    full = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    full.update({"FACESYNTH_DATA_DIR": str(work / "data"), "FACESYNTH_PORT": str(port),
                 "FACESYNTH_GRPC_PORT": str(free_port()), "FACESYNTH_WORKERS": "1",
                 "PYTHONPATH": str(repo), **env})
    log = open(work / "server.log", "ab")
    server = subprocess.Popen([sys.executable, "-m", "service.cli", "serve"], cwd=repo, env=full,
                              stdout=log, stderr=log, stdin=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while True:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                return server
        except httpx.TransportError:
            pass
        if server.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"the server did not start; see {work / 'server.log'}")
        time.sleep(0.3)


def stop_server(server: subprocess.Popen, seconds: float = 60) -> None:
    """Terminate a server of :func:`start_server`; kill it if it is not gone in ``seconds``."""
    server.terminate()
    try:
        server.wait(seconds)
    except subprocess.TimeoutExpired:
        server.kill()
        server.wait()


if __name__ == "__main__":
    worker = WORKERS.get(sys.argv[1] if len(sys.argv) > 1 else "")
    code, n = (worker.__code__, len(sys.argv) - 2) if worker else (None, 0)
    if worker is None or not code.co_argcount - len(worker.__defaults__ or ()) <= n <= code.co_argcount:
        sys.exit("usage: harness.py train-pdm ACTOR_DIR ORDER MODEL_DIR [MARKER_NOISE_MM [PARAMS_JSON]] | train-shape-space ACTOR_DIR "
                 "PARAMS_JSON MODEL_DIR | register-rig ACTOR_DIR OUT_NPZ | train-pose-space ACTOR_DIR PARAMS_JSON "
                 "MODEL_DIR (the reports' workers)")
    print(json.dumps(worker(*sys.argv[2:])))

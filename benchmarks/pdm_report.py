"""PDM report (ma2008 §4–6): held-out accuracy against baselines, compression, speed, figures.

Models are trained on the sample actor's 8 ``train_*`` clips (all frames) and evaluated on
the map frames (every 5th) of ``heldout_in_range`` (expressions mixed from the trained
ones) and ``heldout_out_of_range`` (beyond the trained amplitudes).

Methods (rows), all driven by the same world markers through the biquadratic model's head
pose, handle displacements and deformation vectors (``PdmModel.deformation``):

1. *no detail*: the linear thin shell of the **detailed** neutral (the neutral's own
   vertex-level detail rides along, nothing changes with the expression), fine map 0;
2. *static neutral map*: (1) plus the fine map of a neutral training frame pasted on
   every frame (ma2008 Fig. 7 left: pores do not stretch, wrinkles do not form);
3. *nearest training frame*: the training frame whose aligned markers are nearest (sum
   of squared distances), its medium detail ``c = frames(X_t)·(V_t − X_t)`` in the base
   surface's tangent frames moved onto the held-out base surface (``X + framesᵀ c``), and
   its fine map — a lookup table of the training data, the non-parametric peer;
4–6. the PDM, ``linear``, ``biquadratic`` (eq. 1) and ``bicubic``; on the out-of-range
   performance also the biquadratic without the extrapolation clamp.

Metrics:

* **medium vertex error**, mm: ``|V − V_gt|`` at the face-region vertices against the
  ground-truth mesh (medium surface + wrinkles at vertex resolution), pooled over frames
  and vertices: mean and 95th percentile. The head pose is part of every method, so a
  pose error counts.
* **fine detail**: methods split detail between mesh and map differently (the PDM's fine
  band is a high-passed residual of its own medium result, the baselines paste maps made
  relative to other meshes), so maps are not compared directly. Instead each method's total
  detail *height* is measured against one reference fixed by the ground truth, at every
  fine texel: ``h = n·(P V − P V_gt,medium) + d`` with P the barycentric vertex→texel
  interpolation, n the unit normals of the ground truth's medium surface (vertex normals,
  area-weighted as in :mod:`service.samples.dataset`, interpolated and renormalized) and d
  the method's fine map; the ground truth's h is the actor's ``displacement`` map (all
  detail along the medium normal). Both are high-passed with the model's band split
  ``h − G_σ∗h`` (masked, normalized Gaussian, σ = ``highpass_sigma_texels``; the
  ``_highpass`` of training), so the comparison is of the band the fine PDM models (pores,
  fine wrinkles) and not of medium-scale offsets, which the vertex error already measures.
  Over the covered texels of face-region triangles: Pearson r (pooled over frames and
  texels) and RMS error, mm. A *ground truth (mesh + relative map)* row runs the GT mesh and
  :func:`~service.samples.dataset.vertex_detail_map`'s relative map through the same
  pipeline: the floor of the metric (interpolation order), ideally r = 1, RMS = 0.
* **clamped**: the mean fraction of fine texels whose d1/d2 hit the extrapolation limit.

Compression compares the model directory with the arrays it was trained from (vertices,
markers, displacement and albedo as float32) and with the training ``.npz`` files.

Speed and memory: each measurement runs in a **fresh subprocess** (as
``benchmarks/thin_shell.py``): it loads its inputs and imports everything, resets the
resident-set high-water mark (``echo 5 > /proc/self/clear_refs``) and reports
``VmHWM − VmRSS`` at the reset, the peak resident memory the measured step added (C
allocations included). Training: wall time and peak of ``train`` (clips already loaded);
synthesis: model load time, then one frame per call, median over frames after a warm-up,
with outputs ("mesh", "displacement") and with all outputs.

Run: ``python benchmarks/pdm_report.py [--actor DIR] [--quick] [--reuse]`` (``make bench``).
``--quick``: 6 held-out frames per performance, linear and biquadratic only. ``--reuse``:
keep models (and their training measurements) already in ``benchmarks/out/pdm/models``.
Writes the tables to stdout and ``benchmarks/out/pdm_report.md``, figures to
``benchmarks/out/pdm/``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "benchmarks" / "out"
FIGURES = OUT / "pdm"
MODELS = FIGURES / "models"

SEED, LEVEL = 1, 1
HELDOUT = ("heldout_in_range", "heldout_out_of_range")
ORDERS = ("linear", "biquadratic", "bicubic")
QUICK_ORDERS = ("linear", "biquadratic")
QUICK_FRAMES = 6                       # held-out map frames per performance with --quick
NEUTRAL_CLIP = "train_brow_raise"      # its frame 0 gives the static neutral map
SPEED_FRAMES = 20                      # synthesis timing: frames, one per call
WARMUP_FRAMES = 2
FIGURE_FRAMES = 3                      # strong in-range expressions in the figures
FIGURE_SEPARATION = 20                 # ... at least this many frames apart
TRAIN_BUDGET_S = 120.0
SYNTH_BUDGET_MS = 50.0
BASIC_OUTPUTS = ("mesh", "displacement")
ALL_OUTPUTS = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map")
PAPER_PCA_ENERGY = (76.84, 92.52, 98.46, 99.76, 100.0)    # ma2008 Table 1, %
FACE = "face"                          # actor region of the main metrics
SCORED_REGIONS = (FACE, "narrow_face") # ... and the marker-covered part of it (region 0)
GT_ROW = "ground truth (mesh + relative map)"


# --------------------------------------------------------------------------------------
# data

def ensure_actor(actor_dir: Path) -> None:
    """Build the level-1 sample actor (seed 1) into ``actor_dir`` unless it is there."""
    if (actor_dir / "manifest.json").is_file():
        return
    from service.samples.actor import build_sample_actor

    print(f"building the sample actor into {actor_dir} (a few minutes)", file=sys.stderr)
    build_sample_actor(actor_dir, seed=SEED, level=LEVEL)


def training_clips(actor_dir: Path, actor):
    from service.samples.dataset import load_clip, performance_names

    return [load_clip(actor_dir, name, actor) for name in performance_names(actor_dir, "train_")]


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


# --------------------------------------------------------------------------------------
# workers (fresh processes)

def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def _reset_peak() -> int:
    """Reset the high-water mark; the resident kB it is measured from."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return _status_kb("VmRSS")
    except OSError:
        return _status_kb("VmHWM")


def _peak_mb(rss0_kb: int) -> float:
    return (_status_kb("VmHWM") - rss0_kb) / 1024


def worker_train(actor_dir: Path, order: str, model_dir: Path) -> dict:
    """Train one order from the loaded clips; save it; wall time and peak RSS of ``train``."""
    from service.methods.pdm.model import PdmParams, train
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    clips = training_clips(actor_dir, actor)
    params = PdmParams(order=order)
    rss0 = _reset_peak()
    t0 = time.perf_counter()
    model = train(actor, clips, params,
                  lambda fr, stage: print(f"    [{order}] {fr:4.0%} {stage}", file=sys.stderr))
    res = {"order": order, "train_s": time.perf_counter() - t0, "peak_rss_mb": _peak_mb(rss0),
           "frames": sum(c.frames for c in clips)}
    model.save(model_dir)
    return res


def worker_synth(actor_dir: Path, model_dir: Path, mode: str) -> dict:
    """Load a model and synthesize one frame per call; times and peak RSS."""
    from service.methods.pdm.model import PdmModel

    with np.load(actor_dir / "performances" / f"{HELDOUT[0]}.npz") as d:
        markers = d["markers"][: WARMUP_FRAMES + SPEED_FRAMES].astype(np.float64)
    outputs = BASIC_OUTPUTS if mode == "basic" else ALL_OUTPUTS
    rss0 = _reset_peak()
    t0 = time.perf_counter()
    model = PdmModel.load(model_dir)
    res = {"mode": mode, "load_s": time.perf_counter() - t0, "load_rss_mb": _peak_mb(rss0),
           "outputs": list(outputs), "unavailable": {}}
    rss0 = _reset_peak()
    try:
        t0 = time.perf_counter()
        model.synthesize(markers[:1], outputs)
        res["first_ms"] = 1e3 * (time.perf_counter() - t0)
    except Exception as e:                                  # a module still being written
        if "normal_map" not in outputs:
            raise
        res["unavailable"]["normal_map"] = f"{type(e).__name__}: {e}"
        outputs = tuple(o for o in outputs if o != "normal_map")
        res["outputs"] = list(outputs)
        t0 = time.perf_counter()
        model.synthesize(markers[:1], outputs)
        res["first_ms"] = 1e3 * (time.perf_counter() - t0)
    for f in range(1, WARMUP_FRAMES):
        model.synthesize(markers[f:f + 1], outputs)
    times = []
    for f in range(WARMUP_FRAMES, len(markers)):
        t0 = time.perf_counter()
        model.synthesize(markers[f:f + 1], outputs)
        times.append(time.perf_counter() - t0)
    res["ms_frame"] = 1e3 * float(np.median(times))
    res["ms_frame_p90"] = 1e3 * float(np.percentile(times, 90))
    res["synth_rss_mb"] = _peak_mb(rss0)
    return res


def run_worker(*args: str) -> dict:
    """Run this script as a worker in a fresh process; its JSON result (last stdout line)."""
    proc = subprocess.run([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True,
                          check=False)
    if proc.returncode != 0:
        sys.exit(f"worker {' '.join(args)} failed (exit {proc.returncode})")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def train_models(actor_dir: Path, orders, reuse: bool) -> dict[str, dict]:
    """Train (or with ``reuse`` keep) one model per order under MODELS; training measurements."""
    stats = {}
    for order in orders:
        model_dir, record = MODELS / order, MODELS / f"{order}.train.json"
        if reuse and (model_dir / "manifest.json").is_file() and record.is_file():
            stats[order] = json.loads(record.read_text())
            print(f"  reusing {order} model", file=sys.stderr)
            continue
        print(f"  training {order} ...", file=sys.stderr)
        stats[order] = run_worker("--worker", "train", "--actor", str(actor_dir), "--order", order,
                                  "--model", str(model_dir))
        record.write_text(json.dumps(stats[order]))
        print(f"  {order}: {stats[order]['train_s']:.1f} s", file=sys.stderr)
    return stats


# --------------------------------------------------------------------------------------
# detail heights at the fine texels

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

    def image(self, values: np.ndarray, only_face: bool = True) -> np.ndarray:
        """(P,) texel values → (H,H) map, NaN off the covered (face) texels."""
        img = np.full(self.H * self.H, np.nan)
        keep = self.face if only_face else np.ones(len(self.index), bool)
        img[self.index[keep]] = values[keep]
        return img.reshape(self.H, self.H)


# --------------------------------------------------------------------------------------
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

        base = model.base
        detailed = BaseSurface.from_smooth(actor.vertices, actor.faces, actor.uv, actor.uv_faces,
                                           base.handles, base.rest_markers)
        markers = np.concatenate([c.markers for c in clips])
        pose, u_H, _ = model.deformation(markers)
        V = np.concatenate([c.vertices for c in clips])
        c = np.empty(V.shape, np.float32)
        for t in range(len(V)):
            X = base.deform(u_H[t:t + 1])
            c[t] = np.einsum("fnij,fnj->fni", base.frames(X), pose[t:t + 1].remove(V[t:t + 1]) - X)[0]
        maps = np.concatenate([tex.texels(cl.displacement) for cl in clips]).astype(np.float32)
        neutral = next(cl for cl in clips if cl.name == NEUTRAL_CLIP)
        return cls(model, detailed, tex.texels(neutral.displacement[0]), pose.remove(markers), c, maps)

    def no_detail(self, markers):
        pose, u_H, _ = self.model.deformation(markers)
        return pose.restore(self.detailed.deform(u_H)), None, None

    def static_neutral_map(self, markers):
        V, _, _ = self.no_detail(markers)
        return V, np.broadcast_to(self.neutral_map, (len(markers), len(self.neutral_map))), None

    def nearest(self, markers) -> tuple[np.ndarray, np.ndarray, None, np.ndarray]:
        """Also returns the chosen training frame (k,) (global index)."""
        base = self.model.base
        pose, u_H, _ = self.model.deformation(markers)
        a = pose.remove(markers)
        d2 = np.nansum((a[:, None] - self.train_aligned[None]) ** 2, axis=(2, 3))    # (k,T)
        t = np.argmin(d2, axis=1)
        X = base.deform(u_H)
        V = pose.restore(X + np.einsum("fnji,fnj->fni", base.frames(X), self.train_c[t]))
        return V, self.train_maps[t], None, t


def pdm_prediction(model, markers, tex: DetailTexels, clamp: bool = True):
    out = model.synthesize(markers, BASIC_OUTPUTS, clamp=clamp)
    return out["vertices"].astype(np.float64), tex.texels(out["displacement"]), out["clamped"]


# --------------------------------------------------------------------------------------
# metrics

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
    from service.samples.dataset import vertex_detail_map

    normals = tex.normals(gt.medium, actor.faces)
    gt_hp = np.stack([tex.highpass(tex.texels(d)) for d in gt.displacement])       # (k,P)
    signal = {r: float(np.sqrt(np.mean(gt_hp[:, tex.regions[r]] ** 2))) for r in SCORED_REGIONS}
    keep = [int(np.flatnonzero(gt.frames == f)[0]) for f in keep_frames]
    figure = {"gt_hp": {gt.frames[i]: gt_hp[i] for i in keep}, "hp": {}, "vertex_error": {}}
    scores = {r: {} for r in SCORED_REGIONS}
    clamped_mean, extra = {}, {}

    # the metric's floor: the ground truth's mesh and relative map through the same pipeline
    relative = tex.texels(gt.displacement - vertex_detail_map(actor, gt.vertices, gt.medium, tex.H))
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


def compression(clips, actor_dir: Path, orders) -> dict:
    """Bytes of the training arrays (float32), of the training npz files and of each model
    directory's files; files the manifest lists as ``derived`` (a cache loading could recompute)
    are kept apart."""
    arrays = {
        "vertices": sum(c.vertices.size for c in clips) * 4,
        "markers": sum(c.markers.size for c in clips) * 4,
        "displacement": sum(c.displacement.size for c in clips) * 4,
        "albedo": sum(c.albedo.size for c in clips) * 4,
    }
    npz = sum((actor_dir / "performances" / f"{c.name}.npz").stat().st_size for c in clips)
    models, derived = {}, {}
    for o in orders:
        cache = json.loads((MODELS / o / "manifest.json").read_text()).get("derived", {})
        sizes = {f.name: f.stat().st_size for f in (MODELS / o).iterdir() if f.is_file()}
        models[o] = {k: v for k, v in sizes.items() if k not in cache}
        derived[o] = {k: v for k, v in sizes.items() if k in cache}
    return {"arrays": arrays, "npz": npz, "models": models, "derived": derived}


# --------------------------------------------------------------------------------------
# report

def _mb(b: float) -> str:
    return f"{b / 2**20:,.1f}"


def _num(x, digits=2, pct=False) -> str:
    """Fixed point; values too small for ``digits`` decimals in two significant digits."""
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    if pct:
        return f"{100 * x:.{digits}f} %"
    return f"{x:.2g}" if 0 < abs(x) < 10 ** -digits else f"{x:.{digits}f}"


def _accuracy_rows(results: dict, region: str, clamped: bool) -> list[str]:
    rows = []
    for perf, r in results["accuracy"].items():
        for name, s in r["scores"][region].items():
            row = (f"| {perf} | {r['frames']} | {name} | {_num(s['medium_mean_mm'], 3)} | "
                   f"{_num(s['medium_p95_mm'], 3)} | {_num(s['fine_r'], 3)} | {_num(s['fine_rms_mm'], 4)} |")
            rows.append(row + (f" {_num(r['clamped'][name], 1, pct=True)} |" if clamped else ""))
    return rows


def report(results: dict, meta: dict) -> str:
    lines = [
        "# PDM report (ma2008 §4–6): held-out accuracy, compression, speed",
        "",
        f"Sample actor {meta['actor']} (level {LEVEL}, seed {SEED}): {meta['vertices']:,} vertices, "
        f"{meta['markers']} markers; trained on {meta['train_frames']} frames of "
        f"{meta['train_clips']} clips; {meta['cpus']} CPU cores, load average "
        f"{meta['load_before']} before / {meta['load_after']} after; NumPy {meta['numpy']}."
        + (" **--quick** run: subset of frames and orders." if meta["quick"] else ""),
        "",
        "## Accuracy on held-out performances",
        "",
        "Medium: |V − V_gt| over the face-region vertices (mean, 95th percentile). Fine: "
        f"high-passed detail heights (σ = {meta['sigma_texels']:.1f} texels = "
        f"{meta['sigma_mm']:.1f} mm) at the face texels vs the ground-truth displacement map: "
        "Pearson r and RMS error. Clamped: mean fraction of fine texels at the extrapolation "
        "limit. Definitions in the script's docstring.",
        "",
        "| performance | frames | method | medium mean mm | medium p95 mm | fine r | fine RMS mm | clamped |",
        "|---|---|---|---|---|---|---|---|",
        *_accuracy_rows(results, FACE, clamped=True),
        "",
    ]
    for perf, r in results["accuracy"].items():
        sig = r["signal_rms_mm"]
        lines.append(f"- {perf}: ground-truth high-passed detail RMS {sig[FACE]:.4f} mm over the face, "
                     f"{sig['narrow_face']:.4f} mm over the narrow face (the RMS error of a fine band of 0 "
                     f"on a perfect mesh); map frames {', '.join(map(str, r['frame_list']))}.")
    for perf, chosen in results.get("nearest", {}).items():
        lines.append(f"- nearest training frames, {perf} (held-out frame → clip:frame): {chosen}.")
    lines += [
        "",
        "The same on the **narrow face** only (rig region 0, the part covered by markers: without "
        "the forehead top, temples, ears and jaw sides):",
        "",
        "| performance | frames | method | medium mean mm | medium p95 mm | fine r | fine RMS mm |",
        "|---|---|---|---|---|---|---|",
        *_accuracy_rows(results, "narrow_face", clamped=False),
    ]

    lines += ["", "## PCA energy of the 5D deformation vectors (ma2008 Table 1)", "",
              "| eigenvectors | 1 | 2 | 3 | 4 | 5 |", "|---|---|---|---|---|---|",
              "| paper | " + " | ".join(f"{x:.2f} %" for x in PAPER_PCA_ENERGY) + " |",
              "| this actor | " + " | ".join(f"{100 * x:.2f} %" for x in results["pca_energy"]) + " |", ""]

    lines += ["## Training fit (training frames)", "",
              "| order | medium fit RMS mm (texels) | medium vertex RMS mm (face) | fine fit RMS mm (face) | "
              "fine signal RMS mm (face) | albedo fit RMS | axes replaced / worst angle |",
              "|---|---|---|---|---|---|---|"]
    fit_notes = []
    for order, m in results["fit"].items():
        ax = m["axis_smoothing"]
        fit_regions = ", ".join(f"{k} {v:.3f}" for k, v in m["medium_vertex_rms_mm"].items())
        fit_notes.append(f"- {order}: medium vertex RMS by region (mm): {fit_regions}; fine signal RMS by "
                         "region (mm): " + ", ".join(f"{k} {v:.3f}" for k, v in m["fine_signal_rms_mm"].items()))
        lines.append(f"| {order} | {m['medium_fit_rms_mm']:.4f} | {m['medium_vertex_rms_mm'][FACE]:.4f} | "
                     f"{m['fine_fit_rms_mm'][FACE]:.4f} | {m['fine_signal_rms_mm'][FACE]:.4f} | "
                     f"{_num(m['albedo_fit_rms'], 4)} | {ax['replaced']} / {ax['worst_angle_deg']:.1f}° "
                     f"(threshold {ax['threshold_deg']:g}°) |")

    lines += ["", "Medium vertex RMS: the medium result at the vertices vs the training meshes; fine "
              "signal: RMS of the high-passed residual the fine PDM is fitted to (it depends on the "
              "order through the medium result).", "", *fit_notes]
    comp = results["compression"]
    arrays = sum(comp["arrays"].values())
    lines += ["", "## Compression", "",
              "Training data: " + ", ".join(f"{k} {_mb(v)} MB" for k, v in comp["arrays"].items())
              + f" = **{_mb(arrays)} MB** as float32 arrays; the training .npz files: "
              f"**{_mb(comp['npz'])} MB**.", "",
              "| order | model MB | files (MB) | × smaller than arrays | × smaller than npz | "
              "derived cache MB (not counted) |",
              "|---|---|---|---|---|---|"]
    for order, files in comp["models"].items():
        size = sum(files.values())
        cache = ", ".join(f"{k} {_mb(v)}" for k, v in sorted(comp["derived"][order].items())) or "–"
        lines.append(f"| {order} | {_mb(size)} | " + ", ".join(f"{k} {_mb(v)}" for k, v in sorted(files.items()))
                     + f" | {arrays / size:.0f}× | {comp['npz'] / size:.0f}× | {cache} |")

    tr, sb, sa = results["train"], results["synth"]["basic"], results["synth"]["all"]
    bq = tr["biquadratic"]
    na = ", ".join(f"{k} n/a ({v})" for k, v in sa["unavailable"].items())
    lines += ["", f"## Speed and memory ({meta['cpus']} cores, wall clock, fresh process per measurement)", "",
              "| step | measured | budget | peak RSS added MB |", "|---|---|---|---|",
              f"| training, biquadratic ({bq['frames']} frames) | {bq['train_s']:.1f} s | ≤ {TRAIN_BUDGET_S:g} s: "
              f"**{'met' if bq['train_s'] <= TRAIN_BUDGET_S else 'MISSED'}** | {bq['peak_rss_mb']:.0f} |"]
    for order in tr:
        if order != "biquadratic":
            lines.append(f"| training, {order} | {tr[order]['train_s']:.1f} s | | {tr[order]['peak_rss_mb']:.0f} |")
    lines += [
        f"| model load (checksums, thin-shell basis, samplers) | {sb['load_s']:.1f} s | | {sb['load_rss_mb']:.0f} |",
        f"| synthesis, {' + '.join(sb['outputs'])}, 1 frame/call | {sb['ms_frame']:.0f} ms/frame "
        f"(p90 {sb['ms_frame_p90']:.0f}, first call {sb['first_ms']:.0f}) | ≤ {SYNTH_BUDGET_MS:g} ms: "
        f"**{'met' if sb['ms_frame'] <= SYNTH_BUDGET_MS else 'MISSED'}** | {sb['synth_rss_mb']:.0f} (beyond the loaded model) |",
        f"| synthesis, {' + '.join(sa['outputs'])}, 1 frame/call | {sa['ms_frame']:.0f} ms/frame "
        f"(p90 {sa['ms_frame_p90']:.0f}, first call {sa['first_ms']:.0f}) | | {sa['synth_rss_mb']:.0f} (beyond the loaded model) |",
        "",
        f"Synthesis: median over {SPEED_FRAMES} frames of {HELDOUT[0]} after {WARMUP_FRAMES} warm-up "
        "calls (the first call builds lazy caches, e.g. the normal mapper). Training peak: beyond the "
        "loaded clips.",
    ]
    if na:
        lines += ["", f"All outputs: {na}; timed without it."]
    lines += ["", f"Code: {meta['git']}."]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------
# figures

def _face_box(tex: DetailTexels, pad: int = 8) -> tuple[slice, slice]:
    r, c = np.divmod(tex.index[tex.face], tex.H)
    return (slice(max(r.min() - pad, 0), min(r.max() + pad + 1, tex.H)),
            slice(max(c.min() - pad, 0), min(c.max() + pad + 1, tex.H)))


def plot_detail_maps(fig_data, tex: DetailTexels, frames, path: Path, rows) -> None:
    """(a) high-passed detail heights in UV (face tile, row 0 = top of the map), one colour scale."""
    import matplotlib.pyplot as plt

    box = _face_box(tex)
    gt = [fig_data["gt_hp"][f] for f in frames]
    lim = float(np.percentile(np.abs(np.concatenate([g[tex.face] for g in gt])), 99.5))
    panels = [("ground truth", gt)] + [(name, [fig_data["hp"][(name, f)] for f in frames]) for name in rows]
    fig, axes = plt.subplots(len(panels), len(frames), figsize=(5 * len(frames) + 1, 5 * len(panels) + 0.6),
                             squeeze=False, layout="constrained")
    cmap = plt.get_cmap("RdBu_r").copy()
    cmap.set_bad("0.8")
    for i, (name, maps) in enumerate(panels):
        for j, (f, hp) in enumerate(zip(frames, maps)):
            im = axes[i, j].imshow(tex.image(hp)[box], cmap=cmap, vmin=-lim, vmax=lim,
                                   interpolation="antialiased")
            axes[i, j].set_title(f"{name}\nframe {f}", fontsize=10)
            axes[i, j].set_xticks([]), axes[i, j].set_yticks([])
    fig.colorbar(im, ax=axes, shrink=0.5, label="high-passed detail height h − G∗h, mm")
    fig.suptitle(f"Fine detail, face texels of the UV map (grey: not scored), {HELDOUT[0]}; "
                 f"colour limit ±{lim:.2f} mm = 99.5th percentile of |ground truth|", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


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


def plot_vertex_errors(fig_data, gt: Heldout, pose, actor, frames, path: Path, rows) -> None:
    """(b) per-vertex medium error on the (head-pose aligned) ground-truth mesh, seen from the front."""
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    from service.samples.render import shade

    cam = camera(actor)
    face_v = np.asarray(actor.regions[FACE])
    errs = [fig_data["vertex_error"][(rows[0], f)][face_v] for f in frames]
    vmax = float(np.ceil(np.percentile(np.concatenate(errs), 99) * 2) / 2)
    norm, cmap = Normalize(0, vmax), plt.get_cmap("inferno")
    fig, axes = plt.subplots(len(rows), len(frames), figsize=(4.5 * len(frames) + 1, 4.8 * len(rows) + 0.6),
                             squeeze=False, layout="constrained")
    for j, f in enumerate(frames):
        i_f = int(np.flatnonzero(gt.frames == f)[0])
        V = pose[i_f:i_f + 1].remove(gt.vertices[i_f:i_f + 1])[0]
        for i, name in enumerate(rows):
            err = fig_data["vertex_error"][(name, f)]
            colour = np.where(face_v[:, None], cmap(norm(err))[:, :3], 0.75)
            img = shade(cam, V, actor.faces, colour, light_dir=(0.0, 0.3, 1.0), ambient=0.55, background=1.0)
            axes[i, j].imshow(np.clip(img, 0, 1))
            axes[i, j].set_title(f"{name}, frame {f}\nmean {err[face_v].mean():.2f} mm over the face",
                                 fontsize=10)
            axes[i, j].set_xticks([]), axes[i, j].set_yticks([])
    fig.colorbar(ScalarMappable(norm, cmap), ax=axes, shrink=0.5, extend="max",
                 label="|V − V_gt|, mm (grey: outside the face region, not scored)")
    fig.suptitle(f"Medium-scale vertex error on the ground-truth mesh, {HELDOUT[0]}", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_accuracy(accuracy: dict, path: Path) -> None:
    """(c) the face-region accuracy table as grouped bars (the ground-truth floor left out)."""
    import matplotlib.pyplot as plt

    perfs = list(accuracy)
    names = [n for n in dict.fromkeys(n for p in perfs for n in accuracy[p]["scores"][FACE]) if n != GT_ROW]
    metrics = [("medium_mean_mm", "medium vertex error, mean (mm, lower is better)"),
               ("medium_p95_mm", "medium vertex error, 95th percentile (mm)"),
               ("fine_r", "fine detail: Pearson r (higher is better)"),
               ("fine_rms_mm", "fine detail: RMS error (mm, lower is better)")]
    fig, axes = plt.subplots(2, 2, figsize=(13, 9), layout="constrained")
    width = 0.8 / len(perfs)
    x = np.arange(len(names))
    colors = ["#4c72b0", "#dd8452"]
    for ax, (key, title) in zip(axes.ravel(), metrics):
        for k, perf in enumerate(perfs):
            vals = [accuracy[perf]["scores"][FACE].get(n, {}).get(key, np.nan) for n in names]
            pos = x + (k - (len(perfs) - 1) / 2) * width
            ax.bar(pos, vals, width, label=perf, color=colors[k % 2])
            for p_, v in zip(pos, vals):
                if np.isfinite(v):
                    ax.text(p_, v, f"{v:.3g}", ha="center", va="bottom", fontsize=6.5)
        ax.set_title(title, fontsize=10)
        ax.set_xticks(x, names, rotation=25, ha="right", fontsize=8)
        ax.set_ylim(0, 1.12 * ax.get_ylim()[1])
        ax.grid(axis="y", alpha=0.3)
    for k, perf in enumerate(perfs):
        axes[1, 1].axhline(accuracy[perf]["signal_rms_mm"][FACE], ls="--", lw=0.9, color=colors[k % 2],
                           label=f"ground-truth detail RMS (fine band 0), {perf}")
    handles, labels = axes[1, 1].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=2, fontsize=8)
    fig.suptitle("PDM vs baselines on held-out performances (face region)", fontsize=12)
    fig.savefig(path, dpi=100)
    plt.close(fig)


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


# --------------------------------------------------------------------------------------

def git_state() -> str:
    """Commit of the checkout and the library files with uncommitted changes (others edit in parallel)."""
    def git(*a):
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()

    dirty = [line[3:] for line in git("status", "--porcelain", "--", "service").splitlines()]
    return f"commit {git('rev-parse', '--short', 'HEAD')}" + (
        f", uncommitted changes in {', '.join(dirty)}" if dirty else ", service/ clean")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", type=Path, default=OUT / "actor-l1",
                        help="sample actor directory (built there, level 1 seed 1, if it has no manifest.json)")
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK_FRAMES} held-out frames per performance, linear and biquadratic only")
    parser.add_argument("--reuse", action="store_true",
                        help="reuse trained models (and their training measurements) in benchmarks/out/pdm/models")
    parser.add_argument("--worker", choices=("train", "synth-basic", "synth-all"), help=argparse.SUPPRESS)
    parser.add_argument("--order", help=argparse.SUPPRESS)
    parser.add_argument("--model", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    actor_dir = args.actor.resolve()
    if args.worker == "train":
        print(json.dumps(worker_train(actor_dir, args.order, args.model)))
        return
    if args.worker:
        print(json.dumps(worker_synth(actor_dir, args.model, args.worker.split("-")[1])))
        return

    from service.methods.pdm.model import PdmModel, mean_texel_size
    from service.samples.dataset import load_actor

    t_start = time.perf_counter()
    FIGURES.mkdir(parents=True, exist_ok=True)
    MODELS.mkdir(parents=True, exist_ok=True)
    ensure_actor(actor_dir)
    actor = load_actor(actor_dir)
    orders = QUICK_ORDERS if args.quick else ORDERS
    meta = {"actor": str(args.actor), "vertices": actor.n_vertices, "markers": actor.n_markers,
            "cpus": os.cpu_count(), "load_before": f"{os.getloadavg()[0]:.1f}", "numpy": np.__version__,
            "quick": args.quick, "git": git_state()}

    # ---- fresh-process measurements first, while this process is idle
    print("training (one fresh process per order)", file=sys.stderr)
    results: dict = {"train": train_models(actor_dir, orders, args.reuse)}
    print("synthesis speed (fresh processes)", file=sys.stderr)
    results["synth"] = {mode: run_worker("--worker", f"synth-{mode}", "--actor", str(actor_dir),
                                         "--model", str(MODELS / "biquadratic"))
                        for mode in ("basic", "all")}

    # ---- accuracy
    print("evaluation", file=sys.stderr)
    models = {o: PdmModel.load(MODELS / o) for o in orders}
    bq = models["biquadratic"]
    results["fit"] = {o: m.metrics for o, m in models.items()}
    results["pca_energy"] = bq.metrics["pca_energy"]
    sigma = bq.metrics["highpass_sigma_texels"]
    tex = DetailTexels.build(actor, bq.fine.resolution, sigma)
    clips = training_clips(actor_dir, actor)
    meta.update(train_frames=sum(c.frames for c in clips), train_clips=len(clips), sigma_texels=sigma,
                sigma_mm=sigma * mean_texel_size(actor, tex.H))
    if clips[0].displacement.shape[1] != tex.H:
        sys.exit(f"training maps are {clips[0].displacement.shape[1]}², the fine band {tex.H}²")
    results["compression"] = compression(clips, actor_dir, orders)
    base = Baselines.build(actor, clips, bq, tex)
    train_names = [f"{c.name}:{f}" for c in clips for f in range(c.frames)]
    del clips

    methods = {"no detail": base.no_detail, "static neutral map": base.static_neutral_map,
               "nearest training frame": base.nearest}
    methods.update({f"PDM {o}": (lambda m, model=model: pdm_prediction(model, m, tex))
                    for o, model in models.items()})
    limit = QUICK_FRAMES if args.quick else None
    results["accuracy"], figure_frames = {}, None
    for perf in HELDOUT:
        gt = load_heldout(actor_dir, perf, limit)
        perf_methods = dict(methods)
        if perf == "heldout_out_of_range":
            perf_methods["PDM biquadratic, no clamp"] = lambda m: pdm_prediction(bq, m, tex, clamp=False)
        keep = strong_frames(gt, FIGURE_FRAMES, FIGURE_SEPARATION) if perf == HELDOUT[0] else []
        r = evaluate_performance(gt, perf_methods, tex, actor, keep)
        r["frames"], r["frame_list"] = len(gt.frames), gt.frames.tolist()
        results["accuracy"][perf] = r
        if "nearest training frame" in r["extra"]:
            chosen = r["extra"]["nearest training frame"]
            results.setdefault("nearest", {})[perf] = ", ".join(
                f"{f}→{train_names[t]}" for f, t in zip(gt.frames, chosen))
        if perf == HELDOUT[0]:
            figure_frames, in_range = keep, gt

    # ---- figures
    print("figures", file=sys.stderr)
    fig_data = results["accuracy"][HELDOUT[0]]["figure"]
    plot_detail_maps(fig_data, tex, figure_frames, FIGURES / "a_detail_maps.png",
                     ["PDM biquadratic", "static neutral map"])
    pose, _, _ = bq.deformation(in_range.markers)
    plot_vertex_errors(fig_data, in_range, pose, actor, figure_frames, FIGURES / "b_vertex_error.png",
                       ["no detail", "PDM biquadratic"])
    plot_accuracy(results["accuracy"], FIGURES / "c_accuracy.png")
    f = figure_frames[-1]
    i = int(np.flatnonzero(in_range.frames == f)[0])
    sl = slice(i, i + 1)
    out = bq.synthesize(in_range.markers[sl], ("mesh", "mesh_detailed"))
    V_none, _, _ = base.no_detail(in_range.markers[sl])
    V_gt = pose[sl].remove(in_range.vertices[sl])[0]
    plot_grazing([("no detail (thin shell)", pose[sl].remove(V_none)[0]),
                  ("PDM biquadratic: vertices", pose[sl].remove(out["vertices"])[0]),
                  ("PDM biquadratic: vertices_detailed", pose[sl].remove(out["vertices_detailed"])[0]),
                  ("ground truth: vertices", V_gt)],
                 actor, zoom_centre(tex, fig_data["gt_hp"][f], V_gt), f"{HELDOUT[0]} frame {f}",
                 FIGURES / "d_grazing.png")

    meta["load_after"] = f"{os.getloadavg()[0]:.1f}"
    text = report(results, meta)
    text += f"\nFigures in benchmarks/out/pdm/ (a–d). Total run {time.perf_counter() - t_start:.0f} s.\n"
    print(text)
    (OUT / "pdm_report.md").write_text(text)


if __name__ == "__main__":
    main()

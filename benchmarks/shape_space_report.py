"""Shape-space report (bermano2014 §5–6): held-out enhancement vs the input and the PDM,
convex weights, retiming, speed and memory, figures.

The shape-space model is trained on the sample actor's long ``database`` performance (630
frames, ground-truth meshes and, at level 1, fine displacement and albedo maps, which the
model blends with its matched weights: :mod:`service.methods.shape_space.maps`). It enhances map frames (every 5th frame has maps;
``--frames`` of them, default ``DEFAULT_FRAMES``, evenly spaced but not at the ends, which
are near the neutral) of ``heldout_in_range`` (expressions mixed from the trained ones) and
``heldout_out_of_range`` (beyond them), given two ways:

* **rig**: the low-resolution rig meshes (``lowres``, the ICT topology) carried to the
  actor's neutral by :func:`~service.methods.shape_space.registration.register_rig` of
  ``input_rig.npz`` (no landmarks) and ``RigRegistration.propagate`` (§5.1);
* **markers**: the world markers; the model deforms its neutral to them with the linear
  thin shell (``input_kind="markers"``).

Rows per input, all against the ground truth ``vertices`` (medium surface + wrinkles at
vertex resolution), world pose:

1. *input alone*: the propagated rig mesh, or the thin shell of the markers (the
   ``input_vertices`` the model returns), no enhancement;
2. *PDM biquadratic* (ma2008, trained on the 8 ``train_*`` clips as in
   ``benchmarks/pdm_report.py``), with its extrapolation limit (``clamp``) and without.
   The PDM is driven by markers only: for the rig input it gets the marker positions
   sampled on the propagated rig mesh (what a rig can offer a marker-driven model);
3. *shape-space*: ``ShapeSpaceModel.enhance`` of the model with the given parameters (bold);
   if the model with the other ``smoothing`` is built (see speed) it is scored too, on the
   same input vertices.

Metrics (pooled over frames and vertices / texels):

* **vertex error**, mm: ``|V − V_gt|`` at the face-region vertices, mean and 95th
  percentile; and the same restricted to the vertex-frames where the ground truth has
  detail, ``|vertices − vertices_medium| > DETAIL_THRESHOLD_MM`` (about 2–3 % of the face:
  the whole-face mean is dominated by detail-free skin);
* **fine detail (mesh + map)**: the metric of ``pdm_report.py`` — detail heights
  ``h = n·(P V − P V_gt,medium) + d`` at the fine texels of the face (d the method's fine
  map: the PDM's fine band, shape-space's blended database maps ``fine_displacement``;
  the input has none), high-passed with the PDM's band split,
  against the ground truth's ``displacement`` map (all its detail, pores included):
  Pearson r and RMS error, mm;
* **fine detail (mesh)**: the same with d = 0 for every method and the ground truth's
  *mesh* heights ``n·(P V_gt − P V_gt,medium)`` as the reference: the detail band a
  vertex-resolution mesh can carry (wrinkles), where the shape-space method does its work.

The paper's Fig. 14 claim (shape-space shows fewer extrapolation artefacts than the PDM on
inputs far from the training set) is checked on ``heldout_out_of_range``: shape-space's
fine RMS error against the PDM's without clamp, both metrics, both inputs.

Convex weights (§5.3): the number of database frames with weight > ``WEIGHT_EPS`` per
region, mean and max over frames. Figure ``fig11_matching.png`` (paper Fig. 11): for the
strongest in-range frame (rig input), the input, the result and the ground truth, then per
region the top-weighted database frames with their weights, all under grazing light with
the head pose removed.

Retiming (§6.2, Fig. 7): a keyframe pair from the database (two frames of one window of
``ShapeSpaceModel.sequences()``, chosen as the pair whose ground-truth timing departs most
from linear) is retimed to the database's own length. Timing is the progress s(k) of
frame k along the keyframe difference, least squares over the face vertices after
aligning every frame rigidly on the back of the head (region ``head``); the ground truth
is the database frames between the keyframes. RMS timing error of the retimed result and
of linear interpolation, as progress (% of the transition) and in frames (the time at
which the ground truth reaches the same progress). Figure ``fig7_retiming.png``.

Speed and memory (as ``pdm_report.py``: each measurement in a **fresh subprocess**,
pinned to ``SPEED_CORES`` cores with the BLAS/OpenMP thread pools set to match; peak
resident memory the measured step added, ``VmHWM − VmRSS`` after resetting the high-water
mark): model build (``train``) for the chosen parameters and for the other
``smoothing`` (``"rest"`` / ``"per_frame"``), model load, and per-frame enhancement (one
frame per call, median after a warm-up) of vertex input (held-out ``vertices_medium``,
what the propagated rig gives at the actor's resolution) and of markers, against the
budgets (level 1 ≤ 0.5 s, level 2 ≤ 2 s) and the paper's ~30 s/frame at 500k vertices.
Level 2 needs a level-2 actor: ``--speed-actor DIR`` (``facesynth sample-actor --level 2
--no-tracking --out DIR``; ~179k vertices, 8 GB of performances); its model is trained on
its 630-frame database the same way.

Models (shape-space per parameter set, PDM, rig registration) are cached under
``benchmarks/out/shape_space/models/``, keyed by the actor files and the parameters, with
their build measurements; ``--retrain`` rebuilds them. The cache does not know about code
changes: the report prints the library fingerprint each model was built with.

Run: ``python benchmarks/shape_space_report.py [--actor DIR] [--frames K] [--params JSON]
[--speed-actor DIR] [--retrain]`` (``make bench``). Writes the report to stdout and
``benchmarks/out/shape_space/report.md``, figures to ``benchmarks/out/shape_space/``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import harness  # noqa: E402  (the reports' shared data loading, detail metric, workers, PDM baseline)
from harness import (  # noqa: E402  (the cached model builds, shared with generalization_report)
    DATABASE, SS_OUTPUTS, actor_files_key, actor_level, cached, heldout_frames, library_fingerprint,
    params_json, rig_registration, shape_space_cached, shape_space_model, shape_space_paths,
)

OUT = ROOT / "benchmarks" / "out" / "shape_space"
MODELS = harness.SHAPE_SPACE_MODELS

HELDOUT = harness.HELDOUT
INPUTS = ("rig", "markers")
FACE = harness.FACE
HEAD = "head"                          # rigid back of the head: alignment for the retiming
DEFAULT_FRAMES = 10                    # held-out map frames per performance (evenly spaced)
DETAIL_THRESHOLD_MM = 0.01             # ground truth "has detail": |vertices − vertices_medium| above
PDM_ORDER = "biquadratic"
INPUT_ROW, PDM_ROW, PDM_FREE_ROW, SS_ROW = ("input alone", "PDM biquadratic",
                                            "PDM biquadratic, no clamp", "shape-space")
# (the evaluated shape-space model is SS_ROW; a cached model with the other smoothing is scored
# too, as "shape-space, smoothing=…", on the same input vertices)
SPEED_CORES = 2
SPEED_FRAMES = 9                       # timed enhancement calls (one frame each) ...
WARMUP_FRAMES = 1                      # ... after this many
BUDGET_S = {1: 0.5, 2: 2.0}            # per-frame enhancement budget by actor level
PAPER_S_FRAME = ((500_000, 30.0), (850_000, 55.0))   # bermano2014 §7: i7, 12 GB, MOSEK
FIG11_TOP = 4                          # database frames per region in the matching figure
RETIME_MIN_SPAN = 8                    # keyframe pair at least this many frames apart
TILE = 300                             # rendered tiles, pixels


# --------------------------------------------------------------------------------------
# workers (fresh processes; the model builds' workers are harness's)

def worker_speed(actor_dir: Path, model_dir: Path) -> dict:
    """Load a model, enhance one frame per call (vertices, then markers); times and peak RSS."""
    from service.methods.shape_space import ShapeSpaceModel

    k = WARMUP_FRAMES + SPEED_FRAMES
    with np.load(actor_dir / "performances" / f"{HELDOUT[0]}.npz") as d:
        frames = np.linspace(0, len(d["markers"]) - 1, k).round().astype(np.int64)
        inputs = {"vertices": d["vertices_medium"][frames].astype(np.float64),
                  "markers": d["markers"][frames].astype(np.float64)}
    res = {"cores": sorted(os.sched_getaffinity(0)), "threads": os.environ.get("OMP_NUM_THREADS")}
    rss0 = harness.reset_peak()
    t0 = time.perf_counter()
    model = ShapeSpaceModel.load(model_dir)
    res.update(load_s=time.perf_counter() - t0, load_rss_mb=harness.peak_mb(rss0),
               n_vertices=model.n_vertices, database_frames=model.n_frames)
    for kind, X in inputs.items():
        rss0 = harness.reset_peak()
        times = []
        for f in range(k):
            t0 = time.perf_counter()
            model.enhance(X[f:f + 1], ("mesh",), input_kind=kind)
            times.append(time.perf_counter() - t0)
        res[kind] = {"first_s": times[0], "s_frame": float(np.median(times[WARMUP_FRAMES:])),
                     "s_frame_max": float(np.max(times[WARMUP_FRAMES:])), "rss_mb": harness.peak_mb(rss0)}
        print(f"    enhance {kind}: {res[kind]['s_frame']:.2f} s/frame", file=sys.stderr)
    return res


# --------------------------------------------------------------------------------------
# cached builds (the shape-space models and rig registration: harness)

def pdm_model(actor_dir: Path, retrain: bool) -> tuple[Path, dict]:
    from service.samples.dataset import performance_names

    files = ["neutral.npz", "markers.json"] + [f"performances/{n}.npz" for n in performance_names(actor_dir, "train_")]
    key = actor_files_key(actor_dir, *files)
    model_dir, record = MODELS / f"pdm_{PDM_ORDER}-{key}", MODELS / f"pdm_{PDM_ORDER}-{key}.train.json"

    def build():
        print(f"  training the PDM ({PDM_ORDER}, fresh process) ...", file=sys.stderr)
        return harness.pdm_in_fresh_process(actor_dir, PDM_ORDER, model_dir)

    rec = cached(record, (model_dir / "manifest.json").is_file(), retrain, build)
    return model_dir, rec


# --------------------------------------------------------------------------------------
# accuracy

@dataclass
class Accumulator:
    """Pooled errors of one (performance, input, method): vertex errors on the face and on
    the vertex-frames with ground-truth detail; Pearson sums of the two fine-detail metrics."""

    face: list = field(default_factory=list)
    detail: list = field(default_factory=list)
    sums: dict = field(default_factory=lambda: {"total": np.zeros(6), "mesh": np.zeros(6)})

    def add(self, err: np.ndarray, face: np.ndarray, has_detail: np.ndarray, hp: dict, hp_gt: dict,
            texels: np.ndarray) -> None:
        self.face.append(err[face].astype(np.float32))
        self.detail.append(err[has_detail].astype(np.float32))
        for k in self.sums:
            x, y = hp[k][texels], hp_gt[k][texels]
            self.sums[k] += [len(x), x.sum(), y.sum(), x @ x, y @ y, x @ y]

    def result(self) -> dict:
        out = {}
        for name, errs in (("face", self.face), ("detail", self.detail)):
            e = np.concatenate(errs)
            out[f"{name}_mean_mm"] = float(e.mean()) if len(e) else float("nan")
            out[f"{name}_p95_mm"] = float(np.percentile(e, 95)) if len(e) else float("nan")
        out["detail_count"] = int(sum(len(e) for e in self.detail))
        for k, (n, sx, sy, sxx, syy, sxy) in self.sums.items():
            cov, vx, vy = sxy - sx * sy / n, sxx - sx * sx / n, syy - sy * sy / n
            out[f"{k}_r"] = float(cov / np.sqrt(vx * vy)) if vx > 0 and vy > 0 else float("nan")
            out[f"{k}_rms_mm"] = float(np.sqrt(max(sxx - 2 * sxy + syy, 0.0) / n))
        return out


def evaluate(actor, actor_dir: Path, model, bq, reg, tex, limit: int | None, extra: dict | None = None) -> dict:
    """Every row of the accuracy table; convex-weight counts; the figure frames' data.
    ``extra``: row name → further shape-space model (e.g. the other smoothing), scored too."""
    extra = extra or {}
    face = np.asarray(actor.regions[FACE])
    results = {}
    for perf in HELDOUT:
        gt = heldout_frames(actor_dir, perf, limit)
        with np.load(actor_dir / "performances" / f"{perf}.npz") as d:
            lowres = d["lowres"][gt.frames].astype(np.float64)
        normals = tex.normals(gt.medium, actor.faces)
        hp_gt = [{"total": tex.highpass(tex.texels(gt.displacement[f])),
                  "mesh": tex.highpass(tex.heights(gt.vertices[f], gt.medium[f], normals[f], None))}
                 for f in range(len(gt.frames))]
        has_detail = (np.linalg.norm(gt.vertices - gt.medium, axis=-1) > DETAIL_THRESHOLD_MM) & face
        perf_res = {"frames": gt.frames.tolist(), "detail_fraction": float(has_detail[:, face].mean()),
                    "signal_rms_mm": {k: float(np.sqrt(np.mean(np.stack([h[k] for h in hp_gt])[:, tex.face] ** 2)))
                                      for k in ("total", "mesh")},
                    "inputs": {}}
        for inp in INPUTS:
            t0 = time.perf_counter()
            if inp == "rig":
                V_in = reg.propagate(lowres)
                ss = model.enhance(V_in, SS_OUTPUTS, input_kind="vertices")
                markers = actor.marker_positions(V_in)
            else:
                ss = model.enhance(gt.markers, SS_OUTPUTS, input_kind="markers")
                V_in = ss["input_vertices"].astype(np.float64)
                markers = gt.markers
            D_ss = (np.stack([tex.texels(m) for m in ss["fine_displacement"]])
                    if "fine_displacement" in ss else None)
            t_ss = time.perf_counter() - t0
            V_pdm, D_pdm, clamped = harness.pdm_prediction(bq, markers, tex, clamp=True)
            V_free, D_free, _ = harness.pdm_prediction(bq, markers, tex, clamp=False)
            rows = {INPUT_ROW: (V_in, None), PDM_ROW: (V_pdm, D_pdm), PDM_FREE_ROW: (V_free, D_free),
                    SS_ROW: (ss["vertices"].astype(np.float64), D_ss)}
            for name, other in extra.items():
                rows[name] = (other.enhance(V_in, ("mesh",), input_kind="vertices")["vertices"].astype(np.float64),
                              None)
            acc = {name: Accumulator() for name in rows}
            for f in range(len(gt.frames)):
                for name, (V, D) in rows.items():
                    err = np.linalg.norm(V[f] - gt.vertices[f], axis=-1)
                    h_mesh = tex.heights(V[f], gt.medium[f], normals[f], None)
                    hp = {"mesh": tex.highpass(h_mesh),
                          "total": tex.highpass(h_mesh if D is None else h_mesh + D[f])}
                    acc[name].add(err, face, has_detail[f], hp, hp_gt[f], tex.face)
            nz = ss["nonzero"]
            perf_res["inputs"][inp] = {
                "scores": {name: a.result() for name, a in acc.items()},
                "pdm_clamped": float(np.mean(clamped)),
                "nonzero": {str(r): {"mean": float(nz[:, i].mean()), "max": int(nz[:, i].max())}
                            for i, r in enumerate(ss["region_names"])},
                "match_error": {str(r): float(ss["match_error"][:, i].mean()) for i, r in enumerate(ss["region_names"])},
                "enhance_s_frame": t_ss / len(gt.frames),
                "_ss": ss, "_input": V_in, "_pdm_free": V_free,
            }
            print(f"    {perf} / {inp}: shape-space {t_ss / len(gt.frames):.1f} s/frame, "
                  f"all rows {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        perf_res["_gt"] = gt
        results[perf] = perf_res
    return results


# --------------------------------------------------------------------------------------
# retiming (§6.2, Fig. 7)

def head_aligned(actor, V: np.ndarray) -> np.ndarray:
    """Frames (k,n,3) rigidly aligned to the neutral on the back of the head (region ``head``)."""
    from service.geometry.rigid import rigid_align

    head = np.asarray(actor.regions[HEAD])
    out = np.empty(V.shape, np.float64)
    for f, X in enumerate(V):
        out[f] = rigid_align(X[head], actor.vertices[head]).apply(X)
    return out


def progress_of(frames: np.ndarray, key0: np.ndarray, key1: np.ndarray) -> np.ndarray:
    """Least-squares progress s (k,) of frames (k,p,3) along key1 − key0: min ‖x − key0 − s Δ‖²."""
    d = key1 - key0
    return np.einsum("fpd,pd->f", frames - key0, d) / np.einsum("pd,pd->", d, d)


def choose_keyframes(model, actor, A: np.ndarray) -> tuple[int, int, int]:
    """The keyframe pair: positions (i, j) in one window ``w`` of ``model.sequences()`` whose
    ground-truth timing departs most from linear, among pairs ≥ RETIME_MIN_SPAN database
    frames apart that move the face by at least the median pair's motion, along a path that
    is monotone and stays near the keyframe line. A: head-aligned face vertices (N,p,3) of the
    model's database frames."""
    X = A.reshape(len(A), -1)
    X = X - X.mean(axis=0)
    lam, U = np.linalg.eigh((X @ X.T).astype(np.float64))     # PCA through the (N,N) Gram matrix
    top = np.argsort(lam)[::-1][:40]
    Y = U[:, top] * np.sqrt(np.maximum(lam[top], 0.0))      # PCA coordinates (distances ≈ kept)
    del X
    gap = max(2, int(np.ceil(RETIME_MIN_SPAN / model.params.frame_stride)))
    cands = []
    for w, seq in enumerate(model.sequences()):
        for i in range(len(seq)):
            for j in range(i + gap, len(seq)):
                path = Y[seq[i:j + 1]] - Y[seq[i]]
                d = path[-1]
                dd = d @ d
                if dd <= 0:
                    continue
                s = path @ d / dd
                resid = np.sqrt(np.mean(np.sum((path - s[:, None] * d) ** 2, axis=1)) / dd)
                lin = np.linspace(0, 1, len(s))
                cands.append((w, i, j, np.sqrt(dd), np.sqrt(np.mean((s - lin) ** 2)),
                              np.min(np.diff(s)), resid))
    if not cands:
        raise RuntimeError("no database window is long enough for a keyframe pair")
    motion = np.median([c[3] for c in cands])
    ok = [c for c in cands if c[3] >= motion and c[5] > -0.01 and c[6] < 0.25]
    return max(ok or cands, key=lambda c: c[4])[:3]


def retiming(model, actor, database: np.ndarray) -> dict:
    """Retime a database keyframe pair to the database's own length; timing curves and errors."""
    stride = model.params.frame_stride
    face = np.asarray(actor.regions[FACE])
    A = head_aligned(actor, database[::stride])[:, face].astype(np.float32)     # (N,p,3) model frames
    w, i, j = choose_keyframes(model, actor, A)
    seq = model.sequences()[w]
    span = seq[i:j + 1]                                     # model frame indices
    a, b, m = int(span[0]) * stride, int(span[-1]) * stride, j - i + 1
    keys = database[[a, b]].astype(np.float64)
    t0 = time.perf_counter()
    res = model.retime(keys, m)
    t_retime = time.perf_counter() - t0
    ext = model.retime(keys, m, extend=True)
    G = A[span].astype(np.float64)                          # ground truth, head-aligned face
    ka, kb = G[0], G[-1]
    s_gt = progress_of(G, ka, kb)
    aligned = {"retimed": head_aligned(actor, res["vertices"])[:, face],
               "retimed, extended": head_aligned(actor, ext["vertices"])[:, face]}
    s_lin = np.linspace(0.0, 1.0, m)
    lin_frames = keys[0] + s_lin[:, None, None] * (keys[1] - keys[0])
    aligned["linear"] = head_aligned(actor, lin_frames)[:, face]
    s = {name: progress_of(X, ka, kb) for name, X in aligned.items()}
    k = np.arange(m, dtype=np.float64)
    # time (frames) at which the ground truth reaches a progress: its running maximum inverted
    mono = np.maximum.accumulate(s_gt) + k * 1e-9

    def frame_error(x):
        return float(np.sqrt(np.mean((np.interp(x, mono, k) - k) ** 2)) * stride)

    def mm_error(X):
        return float(np.sqrt(np.mean(np.sum((X - G) ** 2, axis=-1))))

    v = int(np.argmax(np.linalg.norm(kb - ka, axis=1)))     # the vertex of Fig. 7: largest motion
    unit = (kb[v] - ka[v]) / np.linalg.norm(kb[v] - ka[v])
    curves = {"database": (G[:, v] - ka[v]) @ unit}
    curves.update({name: (X[:, v] - ka[v]) @ unit for name, X in aligned.items()})
    return {
        "window": w, "window_frames": [int(seq[0]) * stride, int(seq[-1]) * stride], "a": a, "b": b,
        "length": m, "stride": stride,
        "keyframe_motion_rms_mm": float(np.sqrt(np.mean(np.sum((kb - ka) ** 2, axis=1)))),
        "retime_s": t_retime,
        "s_gt": s_gt, "s_retimed": s["retimed"], "s_extended": s["retimed, extended"], "s_linear": s["linear"],
        "progress_rms": {n: float(np.sqrt(np.mean((s[n] - s_gt) ** 2))) for n in ("retimed", "linear")},
        "frames_rms": {n: frame_error(s[n]) for n in ("retimed", "linear")},
        "mm_rms": {n: mm_error(aligned[n]) for n in ("retimed", "linear")},
        "region_progress": res["region_progress"], "region_names": [str(r) for r in res["region_names"]],
        "region_sequences": res["region_sequences"].tolist(), "region_spans": res["region_spans"].tolist(),
        "vertex": v, "vertex_curves": curves,
    }


def plot_retiming(rt: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    k = np.arange(rt["length"]) * rt["stride"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 5), layout="constrained")
    ax = axes[0]
    ax.plot(k, rt["s_gt"], "o-", color="#1f3b99", lw=2, label="database (ground truth)")
    ax.plot(k, rt["s_linear"], "s--", color="#d62728",
            label=f"linear interpolation: RMS {100 * rt['progress_rms']['linear']:.1f} %, "
                  f"{rt['frames_rms']['linear']:.2f} frames")
    ax.plot(k, rt["s_retimed"], "^-", color="#17becf",
            label=f"retimed: RMS {100 * rt['progress_rms']['retimed']:.1f} %, {rt['frames_rms']['retimed']:.2f} frames")
    ax.plot(k, rt["s_extended"], "v:", color="#9467bd", label="retimed, extended to the full motion")
    for r, name in enumerate(rt["region_names"]):
        ax.plot(k, rt["region_progress"][r], lw=0.8, alpha=0.6, color="0.5",
                label="retimed, per-region progress" if r == 0 else None)
    ax.set_xlabel(f"frame after keyframe 0 (database frames {rt['a']}–{rt['b']})")
    ax.set_ylabel("progress s along keyframe 1 − keyframe 0 (face, head-aligned)")
    ax.set_title("Timing of the transition", fontsize=11)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax = axes[1]
    styles = {"database": ("o-", "#1f3b99"), "linear": ("s--", "#d62728"), "retimed": ("^-", "#17becf"),
              "retimed, extended": ("v:", "#9467bd")}
    for name, y in rt["vertex_curves"].items():
        ax.plot(k, y, styles[name][0], color=styles[name][1], label=name)
    ax.set_xlabel("frame after keyframe 0")
    ax.set_ylabel("displacement along its keyframe motion, mm")
    ax.set_title(f"Vertex {rt['vertex']} (largest keyframe motion), as paper Fig. 7", fontsize=11)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(f"Retiming (bermano2014 §6.2) of database frames {rt['a']} → {rt['b']} "
                 f"({rt['length']} frames, window {rt['window']} = frames {rt['window_frames'][0]}–"
                 f"{rt['window_frames'][1]}), keyframe motion RMS {rt['keyframe_motion_rms_mm']:.2f} mm", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------------------
# figures

def render_tiles(actor, items: list[tuple[str, np.ndarray]], cam, cols: int, path: Path) -> None:
    """Grey meshes (n,3) under grazing light, labelled, in a grid of ``cols`` columns (None: blank)."""
    from PIL import Image, ImageDraw, ImageFont

    from service.samples.gallery import GRAZING_LIGHT
    from service.samples.render import shade, to_srgb8, write_png

    grey = np.full((actor.n_vertices, 3), 0.6)
    font = ImageFont.load_default(size=14)
    tiles = []
    for label, V in items:
        if V is None:
            img = Image.new("RGB", (cam.width, cam.height), (255, 255, 255))
        else:
            img = Image.fromarray(to_srgb8(shade(cam, V, actor.faces, grey, light_dir=GRAZING_LIGHT, ambient=0.05)))
        ImageDraw.Draw(img).multiline_text((6, 5), label, fill=(255, 255, 255) if V is not None else (0, 0, 0),
                                           font=font)
        tiles.append(np.asarray(img))
    while len(tiles) % cols:
        tiles.append(np.full_like(tiles[0], 255))
    rows = [np.concatenate(tiles[i:i + cols], axis=1) for i in range(0, len(tiles), cols)]
    write_png(path, np.concatenate(rows, axis=0))


def plot_matching(actor, perf_res: dict, database: np.ndarray, stride: int, path: Path) -> dict:
    """Paper Fig. 11: input, result, ground truth; per region the top-weighted database frames."""
    gt = perf_res["_gt"]
    i = int(np.argmax(gt.strength))
    inp = perf_res["inputs"]["rig"]
    ss = inp["_ss"]
    W = ss["weights"][i]                                      # (R,N)
    cam = harness.camera(actor, zoom=1.4, size=TILE)
    show = lambda V: head_aligned(actor, V[None].astype(np.float64))[0]       # noqa: E731
    items = [(f"input: rig, propagated\n{gt.name} frame {gt.frames[i]}", show(inp["_input"][i])),
             ("shape-space result", show(ss["vertices"][i])),
             ("ground truth", show(gt.vertices[i])),
             ("Shape-space matching\n(bermano2014 Fig. 11)\n\nrows below: regions\ncolumns: database frames\n"
              "by convex weight w\n\ngrazing light,\nhead pose removed", None)]
    chosen = {}
    for r, name in enumerate(ss["region_names"]):
        top = np.argsort(-W[r])[:FIG11_TOP]
        top = top[W[r][top] > 0]
        chosen[str(name)] = [(int(t) * stride, float(W[r][t])) for t in top]
        for rank, t in enumerate(top):
            items.append((f"region {name} #{rank + 1} (of {int(ss['nonzero'][i, r])} non-zero)\n"
                          f"database frame {int(t) * stride}, w = {W[r][t]:.3f}", show(database[int(t) * stride])))
        items += [("", None)] * (FIG11_TOP - len(top))
    render_tiles(actor, items, cam, FIG11_TOP, path)
    return {"performance": gt.name, "frame": int(gt.frames[i]), "top": chosen}


def plot_out_of_range(actor, perf_res: dict, path: Path) -> dict:
    """Paper Fig. 14 analogue: the out-of-range frame with the most ground-truth detail (marker
    input): input, PDM without clamp (mesh), shape-space, ground truth; whole face and a 3×
    close-up where the ground truth's vertex detail is largest."""
    gt = perf_res["_gt"]
    detail = np.linalg.norm(gt.vertices - gt.medium, axis=-1) * np.asarray(actor.regions["narrow_face"])
    i = int(np.argmax(detail.sum(axis=1)))
    inp = perf_res["inputs"]["markers"]
    show = lambda V: head_aligned(actor, V[None].astype(np.float64))[0]       # noqa: E731
    V_gt = show(gt.vertices[i])
    meshes = [("input alone (markers, thin shell)", show(inp["_input"][i])),
              (f"{PDM_FREE_ROW} (mesh)", show(inp["_pdm_free"][i])),
              (SS_ROW, show(inp["_ss"]["vertices"][i])), ("ground truth", V_gt)]
    harness.plot_grazing(meshes, actor, V_gt[int(np.argmax(detail[i]))], f"{gt.name} frame {gt.frames[i]}", path)
    return {"performance": gt.name, "frame": int(gt.frames[i])}


# --------------------------------------------------------------------------------------
# report

def _num(x, digits=3) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.2g}" if 0 < abs(x) < 10 ** -digits else f"{x:.{digits}f}"


def report(acc: dict, rt: dict, speed: dict, builds: dict, meta: dict, figures: dict) -> str:
    L = [
        "# Shape-space report (bermano2014 §5–6): held-out enhancement, convex weights, retiming, speed",
        "",
        f"Actor {meta['actor']} (level {meta['level']}): {meta['vertices']:,} vertices, {meta['markers']} "
        f"markers; shape-space database: `{DATABASE}`, {meta['database_frames']} frames; PDM "
        f"({PDM_ORDER}) trained on the {meta['pdm_clips']} `train_*` clips; {meta['cpus']} CPU cores, "
        f"load average {meta['load_before']} before / {meta['load_after']} after; NumPy {meta['numpy']}. "
        f"Shape-space parameters: `{meta['params']}`. Library fingerprint (sha256 of "
        f"service/methods/shape_space/*.py) now {meta['library']}; the evaluated model was built with "
        f"{builds['main']['library']}.",
        "",
        "## Accuracy on held-out performances (face region)",
        "",
        f"Vertex error |V − V_gt| over the face (mean, p95) and over the vertex-frames where the ground "
        f"truth has detail (|vertices − vertices_medium| > {DETAIL_THRESHOLD_MM} mm). Fine detail: "
        f"high-passed heights at the face texels (σ = {meta['sigma_texels']:.1f} texels = "
        f"{meta['sigma_mm']:.1f} mm, the PDM's band split), Pearson r and RMS error: *mesh + map* "
        "against the ground-truth displacement map (pores included; the PDM's map is its fine band, "
        "shape-space's the blended database maps, the input has none), *mesh* "
        "against the ground-truth mesh's own detail (wrinkles at vertex resolution). Definitions in "
        "the script's docstring. The rig input's own fine error is mostly faceting: the ICT rig's "
        "flat triangles, interpolated onto the actor's vertices, differ from the smooth ground truth "
        "in the high-passed band.",
        "",
        "| performance | input | method | face mean mm | face p95 mm | detail mean mm | detail p95 mm | "
        "fine r (mesh+map) | fine RMS mm (mesh+map) | fine r (mesh) | fine RMS mm (mesh) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for perf, pr in acc.items():
        for inp, ir in pr["inputs"].items():
            for name, s in ir["scores"].items():
                shown = f"**{name}, smoothing={meta['smoothing']}**" if name == SS_ROW else name
                L.append(f"| {perf} | {inp} | {shown} | {_num(s['face_mean_mm'])} | {_num(s['face_p95_mm'])} | "
                         f"{_num(s['detail_mean_mm'])} | {_num(s['detail_p95_mm'])} | {_num(s['total_r'])} | "
                         f"{_num(s['total_rms_mm'], 4)} | {_num(s['mesh_r'])} | {_num(s['mesh_rms_mm'], 4)} |")
    L.append("")
    for perf, pr in acc.items():
        sig = pr["signal_rms_mm"]
        clamp = ", ".join(f"{inp} {100 * ir['pdm_clamped']:.1f} %" for inp, ir in pr["inputs"].items())
        L.append(f"- {perf}: {len(pr['frames'])} map frames ({', '.join(map(str, pr['frames']))}); ground truth "
                 f"has detail at {100 * pr['detail_fraction']:.2f} % of the face vertex-frames; high-passed "
                 f"ground-truth detail RMS {sig['total']:.4f} mm (map), {sig['mesh']:.4f} mm (mesh) — the RMS "
                 f"error of a method with no detail on a perfect medium surface; PDM fine texels at the "
                 f"extrapolation limit: {clamp}.")
    L += ["", "### Paper Fig. 14 claim: out-of-range, shape-space vs PDM without extrapolation limit", "",
          "| input | fine metric | shape-space RMS mm | PDM no clamp RMS mm | PDM (clamp) RMS mm | shape-space lower than PDM no clamp |",
          "|---|---|---|---|---|---|"]
    oor = acc.get("heldout_out_of_range")
    claims = []
    if oor:
        for inp, ir in oor["inputs"].items():
            sc = ir["scores"]
            for metric, key in (("mesh + map", "total_rms_mm"), ("mesh", "mesh_rms_mm")):
                ok = sc[SS_ROW][key] < sc[PDM_FREE_ROW][key]
                claims.append(ok)
                L.append(f"| {inp} | {metric} | {sc[SS_ROW][key]:.4f} | {sc[PDM_FREE_ROW][key]:.4f} | "
                         f"{sc[PDM_ROW][key]:.4f} | **{'yes' if ok else 'NO'}** |")
    L += ["", f"Claim holds in {sum(claims)} of {len(claims)} comparisons."]
    if oor:
        for inp, ir in oor["inputs"].items():
            sc = ir["scores"]
            if sc[SS_ROW]["mesh_rms_mm"] >= sc[PDM_FREE_ROW]["mesh_rms_mm"]:
                L.append(f"Where it fails ({inp} input): the input's own low frequencies are off by "
                         f"{sc[INPUT_ROW]['face_mean_mm']:.3f} mm (face mean; PDM {sc[PDM_FREE_ROW]['face_mean_mm']:.3f} mm) "
                         "and shape-space keeps them by design (it transfers detail onto the input's low band; "
                         "bermano2014 §7 assumes that band correct), so its high-passed heights inherit the "
                         "input's error in the 2 mm band; the PDM's medium band corrects part of it.")
    L.append("")

    L += ["## Convex weights (§5.3): non-zero database frames per region", "",
          "Weights above the library's `WEIGHT_EPS`, per enhanced frame: mean / max over the evaluated "
          "frames; in brackets the mean `match_error` (Ω_r-weighted RMS distance between the input's compressed shape and its convex projection, rad / dimensionless).", "",
          "| performance | input | " + " | ".join(next(iter(next(iter(acc.values()))["inputs"].values()))["nonzero"]) + " |",
          "|---|---|" + "---|" * len(next(iter(next(iter(acc.values()))["inputs"].values()))["nonzero"])]
    for perf, pr in acc.items():
        for inp, ir in pr["inputs"].items():
            L.append(f"| {perf} | {inp} | " + " | ".join(
                f"{v['mean']:.1f} / {v['max']} ({_num(ir['match_error'][r], 3)})" for r, v in ir["nonzero"].items()) + " |")
    f11 = figures["fig11"]
    L += ["", f"Figure `fig11_matching.png` (paper Fig. 11): {f11['performance']} frame {f11['frame']} (rig "
          "input); top database frames per region (frame: weight): "
          + "; ".join(f"{r} " + ", ".join(f"{t}: {w:.3f}" for t, w in top) for r, top in f11["top"].items()) + ".",
          f"Figure `fig14_out_of_range.png` (paper Fig. 14 analogue): {figures['fig14']['performance']} frame "
          f"{figures['fig14']['frame']} (the evaluated frame with the most ground-truth vertex detail), marker "
          "input: the input, the PDM without clamp (mesh), shape-space, the ground truth; whole face and a 3× "
          "close-up where the ground truth's vertex detail is largest.", ""]

    L += ["## Retiming (§6.2, paper Fig. 7)", "",
          f"Keyframes: database frames {rt['a']} and {rt['b']} (window {rt['window']} of `sequences()`, frames "
          f"{rt['window_frames'][0]}–{rt['window_frames'][1]}; keyframe motion RMS {rt['keyframe_motion_rms_mm']:.2f} mm "
          f"over the face), retimed to {rt['length']} frames (the database's own length); "
          f"`retime` took {rt['retime_s']:.2f} s. Regions matched sequences {rt['region_sequences']} at spans "
          + ", ".join(f"{s[0]:.2f}–{s[1]:.2f}" for s in rt["region_spans"]) + ".", "",
          "| timing | RMS progress error (% of the transition) | RMS timing error (frames; ground-truth curve inverted, so unstable where the database holds still) | RMS vertex error vs database (mm, face) |",
          "|---|---|---|---|"]
    for name in ("retimed", "linear"):
        L.append(f"| {name} | {100 * rt['progress_rms'][name]:.2f} | {rt['frames_rms'][name]:.2f} | {rt['mm_rms'][name]:.3f} |")
    L += ["", "Figure `fig7_retiming.png`: progress curves (left) and the vertex of largest keyframe motion "
          "(right): database, linear interpolation, retimed, retimed with the subsequence extended to the "
          "full database motion.", ""]

    L += [f"## Speed and memory ({SPEED_CORES} cores pinned, fresh process per measurement, wall clock)", ""]
    if max(float(meta["load_before"]), float(meta["load_after"])) > SPEED_CORES:
        L += [f"**The machine was shared** (load average {meta['load_before']} before / {meta['load_after']} "
              f"after on {meta['cpus']} cores): every time below is inflated by the other processes' share "
              "of the cores; builds may also have run concurrently with each other.", ""]
    L += ["| level | vertices | step | measured | budget | ratio to budget | peak RSS added MB |",
          "|---|---|---|---|---|---|---|"]
    for level, sp in speed.items():
        for variant, b in sp.get("builds", {}).items():
            st = b["stages_s"]
            names = list(st)
            stages = ", ".join(f"{n} {st[m] - st[n]:.0f} s" for n, m in zip(names, names[1:]))
            L.append(f"| {level} | {b['vertices']:,} | model build, smoothing={variant} "
                     f"({b['metrics']['database_frames']} frames; {stages}) | "
                     f"{b['train_s']:.0f} s{' (cached model, time of its build)' if b['reused'] else ''}"
                     + (" (load average {:.1f} → {:.1f})".format(*b["load_average"]) if "load_average" in b else "")
                     + " | | | "
                     f"{b['peak_rss_mb']:,.0f} |")
        for variant in ("per_frame", "rest"):
            if sp.get("builds") and variant not in sp["builds"]:
                L.append(f"| {level} | – | model build, smoothing={variant} | not built (--no-compare and not "
                         "cached) | | | – |")
        if sp.get("missing"):
            L.append(f"| {level} | – | enhancement | not measured: {sp['missing']} | ≤ {BUDGET_S[level]:g} s/frame | – | – |")
            continue
        n = sp["speed"]["n_vertices"]
        s = sp["speed"]
        L.append(f"| {level} | {n:,} | model load | {s['load_s']:.1f} s | | | {s['load_rss_mb']:,.0f} |")
        budget = BUDGET_S[level]
        for kind in ("vertices", "markers"):
            k = s[kind]
            L.append(f"| {level} | {n:,} | enhance, {kind} input, smoothing={sp['variant']} | "
                     f"{k['s_frame']:.2f} s/frame (max {k['s_frame_max']:.2f}, first {k['first_s']:.2f}) | "
                     f"≤ {budget:g} s: **{'met' if k['s_frame'] <= budget else 'MISSED'}** | "
                     f"{k['s_frame'] / budget:.2f}× | {k['rss_mb']:,.0f} (beyond the loaded model) |")
        for variant, s2 in sp.get("other_speed", {}).items():
            k = s2["vertices"]
            L.append(f"| {level} | {n:,} | enhance, vertices input, smoothing={variant} | {k['s_frame']:.2f} s/frame | "
                     f"≤ {budget:g} s: **{'met' if k['s_frame'] <= budget else 'MISSED'}** | "
                     f"{k['s_frame'] / budget:.2f}× | {k['rss_mb']:,.0f} |")
    paper = "; ".join(f"{s:g} s/frame at {v:,} vertices ({v / s:,.0f} vertices/s)" for v, s in PAPER_S_FRAME)
    L += ["", f"Paper (§7, i7 desktop, 12 GB, MOSEK, four regions in parallel): {paper}."]
    for level, sp in speed.items():
        if not sp.get("missing"):
            s = sp["speed"]
            L.append(f"- level {level}: {s['n_vertices'] / s['vertices_s_frame']:,.0f} vertices/s (vertex input); "
                     f"{s['database_frames']} database frames.")
    L += ["", f"Enhancement: one frame per call, median of {SPEED_FRAMES} frames of {HELDOUT[0]} after "
          f"{WARMUP_FRAMES} warm-up call(s), outputs (\"mesh\",). Vertex input: the held-out "
          "`vertices_medium` (the propagated rig's stand-in at the actor's resolution; the same cost). "
          "Build peak: beyond the loaded database. Marker input: the first call also builds the model's "
          "thin-shell basis (\"first\" column). Accuracy-run enhancement (all cores, several frames "
          "per call, the marker runs including that first call): " + ", ".join(f"{perf}/{inp} {ir['enhance_s_frame']:.2f} s/frame"
                                    for perf, pr in acc.items() for inp, ir in pr["inputs"].items()) + ".",
          "", f"Rig registration (`register_rig`, no landmarks): {builds['registration']['register_s']:.0f} s, "
          "residuals " + ", ".join(f"{k} {v:.3g}" for k, v in builds["registration"]["stats"].items()) + ". "
          f"PDM training: {builds['pdm']['train_s']:.0f} s.", ""]
    return "\n".join(L) + "\n"


# --------------------------------------------------------------------------------------

def speed_section(actor_dir: Path, params, other, retrain: bool, compare: bool) -> dict:
    """Builds (both smoothings; the other one only if cached unless ``compare``) and
    2-core enhancement timings on one actor."""
    level = actor_level(actor_dir)
    main_dir, main_rec = shape_space_model(actor_dir, params, retrain)
    out = {"variant": params.smoothing, "builds": {params.smoothing: main_rec}, "model_dir": main_dir,
           "other_speed": {}}
    print(f"  level {level}: enhancement speed ({SPEED_CORES} cores, fresh process) ...", file=sys.stderr)
    s = harness.run_worker(__file__, "--worker", "speed", "--actor", str(actor_dir), "--model", str(main_dir), cores=SPEED_CORES)
    s["vertices_s_frame"] = s["vertices"]["s_frame"]
    out["speed"] = s
    if compare or shape_space_cached(actor_dir, other):
        other_dir, out["builds"][other.smoothing] = shape_space_model(actor_dir, other, retrain)
        out["other_speed"][other.smoothing] = harness.run_worker(__file__, "--worker", "speed", "--actor", str(actor_dir),
                                                         "--model", str(other_dir), cores=SPEED_CORES)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--actor", type=Path, default=ROOT / "benchmarks" / "out" / "actor-l1",
                        help="sample actor directory (built there, level 1 seed 1, if it has no manifest.json)")
    parser.add_argument("--out", type=Path, default=OUT, help="report and figures directory")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                        help=f"held-out map frames per performance, evenly spaced (default {DEFAULT_FRAMES}; 0: all)")
    parser.add_argument("--params", default="{}", help="ShapeSpaceParams overrides as JSON, e.g. "
                        "'{\"smoothing\": \"per_frame\", \"frame_stride\": 2}'")
    parser.add_argument("--speed-actor", type=Path,
                        help="a level-2 sample actor for the level-2 speed line (not built here: facesynth "
                        "sample-actor --level 2 --no-tracking --out DIR; its model build needs ~4x the "
                        "level-1 time and memory)")
    parser.add_argument("--retrain", action="store_true", help="rebuild cached models and registration")
    parser.add_argument("--no-compare", action="store_true",
                        help="do not build the model with the other smoothing (report it only if cached)")
    parser.add_argument("--no-speed", action="store_true",
                        help="skip the speed section (builds only the evaluated model; for quick runs)")
    parser.add_argument("--worker", choices=("speed",), help=argparse.SUPPRESS)
    parser.add_argument("--model", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    actor_dir = args.actor.resolve()
    if args.worker == "speed":
        print(json.dumps(worker_speed(actor_dir, args.model)))
        return

    from service.methods.pdm.model import PdmModel, mean_texel_size
    from service.methods.shape_space import ShapeSpaceModel, ShapeSpaceParams
    from service.samples.dataset import load_actor, performance_names

    t_start = time.perf_counter()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    MODELS.mkdir(parents=True, exist_ok=True)
    try:
        params = ShapeSpaceParams(**json.loads(args.params))
    except (TypeError, ValueError) as error:
        sys.exit(f"--params: {error}")
    other = params.model_copy(update={"smoothing": "rest" if params.smoothing == "per_frame" else "per_frame"})
    harness.ensure_actor(actor_dir)
    actor = load_actor(actor_dir)
    meta = {"actor": str(args.actor), "level": actor_level(actor_dir), "vertices": actor.n_vertices,
            "markers": actor.n_markers, "cpus": os.cpu_count(), "load_before": f"{os.getloadavg()[0]:.1f}",
            "numpy": np.__version__, "params": params_json(params), "smoothing": params.smoothing, "library": library_fingerprint(),
            "pdm_clips": len(performance_names(actor_dir, "train_"))}

    # ---- fresh-process builds and measurements first
    print("builds and speed (fresh processes)", file=sys.stderr)
    if args.no_speed:
        model_dir, rec = shape_space_model(actor_dir, params, args.retrain)
        speed = {meta["level"]: {"missing": "--no-speed", "builds": {params.smoothing: rec}, "model_dir": model_dir}}
    else:
        speed = {meta["level"]: speed_section(actor_dir, params, other, args.retrain, not args.no_compare)}
    if args.speed_actor and not args.no_speed:
        sa = args.speed_actor.resolve()
        if not (sa / "manifest.json").is_file():
            sys.exit(f"--speed-actor {sa}: no manifest.json (build it with facesynth sample-actor --level 2)")
        speed[actor_level(sa)] = speed_section(sa, params, other, args.retrain, not args.no_compare)
    for level in BUDGET_S:
        speed.setdefault(level, {"missing": "no level-2 actor (pass --speed-actor DIR)" if level == 2
                                 else "no level-1 actor"})
    speed = dict(sorted(speed.items()))
    pdm_dir, pdm_rec = pdm_model(actor_dir, args.retrain)
    reg, reg_rec = rig_registration(actor_dir, args.retrain)
    builds = {"main": speed[meta["level"]]["builds"][params.smoothing], "pdm": pdm_rec, "registration": reg_rec}

    # ---- accuracy
    print("evaluation", file=sys.stderr)
    model = ShapeSpaceModel.load(speed[meta["level"]]["model_dir"])
    bq = PdmModel.load(pdm_dir)
    sigma = bq.metrics["highpass_sigma_texels"]
    tex = harness.DetailTexels.build(actor, bq.data.fine.resolution, sigma)
    meta.update(database_frames=model.n_frames, sigma_texels=sigma, sigma_mm=sigma * mean_texel_size(actor, tex.H))
    extra = {}
    if shape_space_cached(actor_dir, other):
        extra[f"{SS_ROW}, smoothing={other.smoothing}"] = ShapeSpaceModel.load(shape_space_paths(actor_dir, other)[0])
    acc = evaluate(actor, actor_dir, model, bq, reg, tex, args.frames or None, extra)
    del extra

    # ---- retiming and figures
    print("retiming and figures", file=sys.stderr)
    with np.load(actor_dir / "performances" / f"{DATABASE}.npz") as d:
        database = d["vertices"]
    rt = retiming(model, actor, database)
    plot_retiming(rt, out / "fig7_retiming.png")
    figures = {"fig11": plot_matching(actor, acc[HELDOUT[0]], database, params.frame_stride, out / "fig11_matching.png"),
               "fig14": plot_out_of_range(actor, acc["heldout_out_of_range"], out / "fig14_out_of_range.png")}

    meta["load_after"] = f"{os.getloadavg()[0]:.1f}"
    text = report(acc, rt, speed, builds, meta, figures)
    text += f"\nFigures in {out.relative_to(ROOT) if out.is_relative_to(ROOT) else out}/. " \
            f"Total run {time.perf_counter() - t_start:.0f} s.\n"
    print(text)
    (out / "report.md").write_text(text)


if __name__ == "__main__":
    main()

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
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import (  # noqa: E402  (the reports' shared harness, beside this file)
    BASIC_OUTPUTS, FACE, FIGURE_SEPARATION, GT_ROW, HELDOUT, LEVEL, OUT, PDM_MODELS, QUICK_FRAMES,
    SEED, Baselines, DetailTexels, Heldout, evaluate_performance, camera, ensure_actor, face_box, git_state,
    load_heldout, pdm_prediction, peak_mb, plot_grazing, reset_peak, run_worker, strong_frames,
    train_pdm_models, training_clips, zoom_centre,
)
FIGURES = OUT / "pdm"
MODELS = PDM_MODELS

ORDERS = ("linear", "biquadratic", "bicubic")
QUICK_ORDERS = ("linear", "biquadratic")
SPEED_FRAMES = 20                      # synthesis timing: frames, one per call
WARMUP_FRAMES = 2
FIGURE_FRAMES = 3                      # strong in-range expressions in the figures
TRAIN_BUDGET_S = 120.0
SYNTH_BUDGET_MS = 50.0
ALL_OUTPUTS = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map")
PAPER_PCA_ENERGY = (76.84, 92.52, 98.46, 99.76, 100.0)    # ma2008 Table 1, %


# --------------------------------------------------------------------------------------
# data

# --------------------------------------------------------------------------------------
# workers (fresh processes)

def worker_synth(actor_dir: Path, model_dir: Path, mode: str) -> dict:
    """Load a model and synthesize one frame per call; times and peak RSS."""
    from service.methods.pdm.model import PdmModel

    with np.load(actor_dir / "performances" / f"{HELDOUT[0]}.npz") as d:
        markers = d["markers"][: WARMUP_FRAMES + SPEED_FRAMES].astype(np.float64)
    outputs = BASIC_OUTPUTS if mode == "basic" else ALL_OUTPUTS
    rss0 = reset_peak()
    t0 = time.perf_counter()
    model = PdmModel.load(model_dir)
    res = {"mode": mode, "load_s": time.perf_counter() - t0, "load_rss_mb": peak_mb(rss0),
           "outputs": list(outputs), "unavailable": {}}
    rss0 = reset_peak()
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
    res["synth_rss_mb"] = peak_mb(rss0)
    return res



# --------------------------------------------------------------------------------------
# metrics

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

def plot_detail_maps(fig_data, tex: DetailTexels, frames, path: Path, rows) -> None:
    """(a) high-passed detail heights in UV (face tile, row 0 = top of the map), one colour scale."""
    import matplotlib.pyplot as plt

    box = face_box(tex)
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


# --------------------------------------------------------------------------------------

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", type=Path, default=OUT / "actor-l1",
                        help="sample actor directory (built there, level 1 seed 1, if it has no manifest.json)")
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK_FRAMES} held-out frames per performance, linear and biquadratic only")
    parser.add_argument("--reuse", action="store_true",
                        help="reuse trained models (and their training measurements) in benchmarks/out/pdm/models")
    parser.add_argument("--worker", choices=("synth-basic", "synth-all"), help=argparse.SUPPRESS)
    parser.add_argument("--model", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    actor_dir = args.actor.resolve()
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
    results: dict = {"train": train_pdm_models(actor_dir, orders, args.reuse)}
    print("synthesis speed (fresh processes)", file=sys.stderr)
    results["synth"] = {mode: run_worker(__file__, "--worker", f"synth-{mode}", "--actor", str(actor_dir),
                                         "--model", str(MODELS / "biquadratic"))
                        for mode in ("basic", "all")}

    # ---- accuracy
    print("evaluation", file=sys.stderr)
    models = {o: PdmModel.load(MODELS / o) for o in orders}
    bq = models["biquadratic"]
    results["fit"] = {o: m.metrics for o, m in models.items()}
    results["pca_energy"] = bq.metrics["pca_energy"]
    sigma = bq.metrics["highpass_sigma_texels"]
    tex = DetailTexels.build(actor, bq.data.fine.resolution, sigma)
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
    pose, _, _ = bq.evaluator.deformation(in_range.markers)
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

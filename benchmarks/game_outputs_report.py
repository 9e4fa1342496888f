"""Game-engine outputs report: stress-driven expression-map blending and the bone rig.

Part 1, stress blend (Digital Ira course 2014, "Real-Time Rendering"), per actor family
(default ``benchmarks/out/actor-{a,b}-l0``, built if missing; ``--actor FAMILY=DIR``): a
``stress_blend`` model is built from the family's training clips (their neutral and peak
frames are the scans) and evaluated on the map frames of ``heldout_in_range``,
``heldout_combinations`` and ``heldout_amplified`` with the fine-detail metric of ``benchmarks/pdm_report.py``
(imported: high-passed detail heights ``n·(P V − P V_gt,medium) + d`` against the ground
truth's, Pearson r and RMS over the face texels; *relative error* = RMS / RMS of the ground
truth's high band), next to the biquadratic PDM trained by that report's own worker. Rows:

* *stress blend (tracked mesh)*: input the held-out ground-truth mesh (what a tracker
  delivers; the PDM only sees markers, so this row has more input), output its blended map;
* *stress blend (PDM mesh)*: input the PDM's medium mesh synthesized from the markers, so
  the same information as the PDM row; the map is blended from that mesh's stress;
* *engine: masks × weights*: the tracked-mesh row's per-region wrinkle weights replayed as
  an engine would (``M_0 + Σ_k (Σ_r mask_r ω_rk)(M_k − M_0)``);
* *static neutral map*: the neutral scan's map on the tracked mesh (no blending);
* *pose space WPSD (markers)*: bickel2008's default WPSD (the model pose_space_report.py
  saved for the actor, else trained here) from the markers; *shape space (markers)* with
  ``--shape-space``: bermano2014 on the family's database (shape_space_report's cached build).

The PDM is trained here with its defaults and the fine band at the actor's map size.

A frame equal to a scan must blend to that scan: measured on every scan (max |Δ| of the
displacement and albedo maps over covered texels), after a save/load round trip.

Part 2, bone rig (Le & Deng 2012 SSDR, the course's "Game Rig") against ``py-dem-bones``
(its ``solve_skinning``, the Dem Bones SSDR solver) on the same animation and bone count:
the level-0 sample actor's ``heldout_in_range`` performance (154 frames × 11,248 vertices,
rest pose frame 0; level 0 because py-dem-bones needed 5–8 min for 10 iterations of it on
this shared 2-core machine, level 1 would take about 4× as long), 70 bones (the course's rig), 4
influences, 10 iterations each (py-dem-bones' default is 30: its 30 took longer than this
run could wait on the shared machine; facesynth's default is 30). Each solve runs in a fresh
process: wall time and peak RSS added by the solve (``VmHWM``, as pdm_report). Then the
inputs py-dem-bones fails on (each in its own process, so a crash is recorded, not
suffered): empty arrays, NaN frames, a static animation, more bones than vertices, through
py-dem-bones' ``solve_skinning`` and facesynth's ``decompose`` (InvalidInput → 422).

Run: ``python benchmarks/game_outputs_report.py [--reuse] [--quick]`` (``make bench``).
Writes ``benchmarks/out/game_outputs_report.md`` and figures in ``benchmarks/out/game_outputs/``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import harness  # noqa: E402  (the reports' shared data, metric and workers)

OUT = ROOT / "benchmarks" / "out"
FIGURES = OUT / "game_outputs"
#: the actor families of part 1 (``--actor a=DIR``), the actor of part 2
FAMILIES = {"a": harness.actor_dir("a", 0), "b": harness.actor_dir("b", 0)}
ACTOR_L0 = FAMILIES["a"]
#: held-out performances of part 1 (as generalization_report.py: in range, combinations
#: no training clip shows, every expression 25–40 % beyond its peak)
PERFORMANCES = ("heldout_in_range", "heldout_combinations", "heldout_amplified")
WPSD_ROW, SS_ROW = "pose space WPSD (markers)", "shape space (markers)"
RIG_PERFORMANCE = "heldout_in_range"
RIG_BONES, RIG_INFLUENCES, RIG_ITERATIONS = 70, 4, 10
CRASH_TIMEOUT_S = 300
FIGURE_FRAMES = 3


# --------------------------------------------------------------------------------------
# bone-rig workers (fresh processes)

def _animation(actor_dir: Path, name: str):
    with np.load(actor_dir / "performances" / f"{name}.npz") as d:
        A = d["vertices"].astype(np.float64)
    with np.load(actor_dir / "neutral.npz") as d:
        F = d["faces"].astype(np.int64)
    return A, F


def _errors(recon: np.ndarray, A: np.ndarray) -> dict:
    e = np.linalg.norm(recon - A, axis=-1)
    return {"rms_mm": float(np.sqrt(np.mean(e ** 2))), "max_mm": float(e.max()),
            "p99_mm": float(np.percentile(e, 99))}


def worker_rig(which: str, actor_dir: Path, out_dir: Path) -> dict:
    """Solve the rig with facesynth or py-dem-bones; errors, time, peak memory."""
    A, F = _animation(actor_dir, RIG_PERFORMANCE)
    rss0 = harness.reset_peak()
    t0 = time.perf_counter()
    if which == "facesynth":
        from service.methods.bone_rig.decomposition import decompose
        from service.methods.bone_rig.params import BoneRigParams

        rig = decompose(A, A[0], F, BoneRigParams(bones=RIG_BONES, max_influences=RIG_INFLUENCES,
                                                  iterations=RIG_ITERATIONS), fps=30.0)
        seconds, peak = time.perf_counter() - t0, harness.peak_mb(rss0)
        recon = rig.reconstruct()
        out_dir.mkdir(parents=True, exist_ok=True)
        rig.save_npz(out_dir / "rig.npz")
        rig.write_glb(out_dir / "rig.glb")
        res = {"bones": rig.bones, "iterations": rig.metrics["iterations"],
               "history": rig.metrics["rms_history_mm"],
               "glb_bytes": (out_dir / "rig.glb").stat().st_size}
    else:
        import py_dem_bones as pdb

        r = pdb.solve_skinning(A[0], A, RIG_BONES, faces=F, max_influences=RIG_INFLUENCES,
                               iterations=RIG_ITERATIONS)
        seconds, peak = time.perf_counter() - t0, harness.peak_mb(rss0)
        W, T = np.asarray(r.weights), np.asarray(r.transforms)
        recon = (np.einsum("bv,fbij,vj->fvi", W, T[:, :, :3, :3], A[0])
                 + np.einsum("bv,fbi->fvi", W, T[:, :, :3, 3]))
        nnz = (W > 0).sum(axis=0)
        res = {"bones": int(W.shape[0]), "iterations": RIG_ITERATIONS,
               "max_influences_used": int(nnz.max()), "weight_sum_err": float(np.abs(W.sum(axis=0) - 1).max()),
               "min_weight": float(W.min())}
    res.update(which=which, seconds=seconds, peak_rss_mb=peak, frames=len(A), vertices=A.shape[1],
               **_errors(recon, A))
    return res


CRASH_CASES = {
    # name: (rest, frames, bones) from a small animation A (6 frames × 400 vertices)
    "empty (0 frames)": lambda A: (A[0], A[:0], 4),
    "empty (0 vertices)": lambda A: (A[0, :0], A[:, :0], 4),
    "NaN frame (frame 3, one vertex)": lambda A: (A[0], _with_nan(A), 4),
    "NaN rest pose vertex": lambda A: (_nan_rest(A[0]), A, 4),
    "static animation (no motion)": lambda A: (A[0], np.repeat(A[:1], 6, axis=0), 4),
    "bones > vertices (50 bones, 5 vertices)": lambda A: (A[0, :5], A[:, :5], 50),
}


def _with_nan(A):
    A = A.copy()
    A[min(3, len(A) - 1), 7, 1] = np.nan
    return A


def _nan_rest(P):
    P = P.copy()
    P[7, 1] = np.nan
    return P


def worker_crash(which: str, case: str, actor_dir: Path) -> dict:
    """One bad input through one solver: what happens (exception, result, time)."""
    A, F = _animation(actor_dir, RIG_PERFORMANCE)
    A = A[:6, :400]
    F = F[(F < 400).all(axis=1)]
    rest, frames, bones = CRASH_CASES[case](A)
    t0 = time.perf_counter()
    try:
        if which == "facesynth":
            from service.methods.bone_rig.decomposition import decompose
            from service.methods.bone_rig.params import BoneRigParams

            rig = decompose(frames, rest, None, BoneRigParams(bones=bones, iterations=3))
            outcome = f"returned a rig (rms {rig.metrics['rms_mm']:.3g} mm, finite: {bool(np.isfinite(rig.R).all())})"
        elif which == "dem":
            import py_dem_bones as pdb

            faces = F if rest.shape[0] == 400 else F[(F < max(len(rest), 1)).all(axis=1)]
            r = pdb.solve_skinning(rest, frames, bones, faces=faces, iterations=3)
            W = np.asarray(r.weights)
            outcome = (f"returned weights {W.shape}, "
                       f"{'finite' if np.isfinite(W).all() and np.isfinite(r.transforms).all() else 'NON-FINITE'}")
    except Exception as e:                                   # the outcome is what is measured
        outcome = f"{type(e).__name__}: {str(e)[:160]}"
    return {"which": which, "case": case, "outcome": outcome, "seconds": time.perf_counter() - t0}


def run_worker(*args: str, timeout: float | None = None) -> dict:
    """This script as a worker in a fresh process; its JSON result, or how it died."""
    try:
        proc = subprocess.run([sys.executable, __file__, *args], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, check=False, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"outcome": f"no answer within {timeout:.0f} s (killed)"}
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1][:160]
        how = f"killed by signal {-proc.returncode}" if proc.returncode < 0 else f"exit {proc.returncode}"
        return {"outcome": f"process {how}: {tail}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------
# stress blend

def stress_blend_model(actor, clips, reuse: bool, family: str):
    from service.methods.stress_blend.model import StressBlendModel, train
    from service.methods.stress_blend.params import StressBlendParams

    path = FIGURES / "models" / family / "stress_blend"
    if reuse and (path / "manifest.json").is_file():
        rec = json.loads((path.parent / "stress_blend.train.json").read_text())
        return StressBlendModel.load(path), rec
    t0 = time.perf_counter()
    model = train(actor, clips, StressBlendParams())
    rec = {"train_s": time.perf_counter() - t0}
    model.save(path)
    rec["size_mb"] = sum(f.stat().st_size for f in path.iterdir()) / 1e6
    (path.parent / "stress_blend.train.json").write_text(json.dumps(rec))
    return model, rec


def scan_reproduction(model, clips) -> dict:
    """Max |blend − scan map| over covered texels, each scan fed as a frame (after a reload)."""
    by_name = {c.name: c for c in clips}
    dmax = amax = 0.0
    wmin = 1.0
    dmask = model.disp_band.mask()
    amask = model.albedo_band.mask()
    for k, name in enumerate(model.scan_names):
        clip, f = name.rsplit(":", 1)
        c, f = by_name[clip], int(f)
        out = model.synthesize(c.vertices[f], ("displacement", "albedo", "blend_weights"))
        dmax = max(dmax, float(np.abs(out["displacement"][0] - c.displacement[f])[dmask].max()))
        amax = max(amax, float(np.abs(out["albedo"][0] - c.albedo[f])[amask].max()))
        wmin = min(wmin, float(out["blend_weights"][0][:, k].min()))
    return {"scans": len(model.scan_names), "disp_max_abs_mm": dmax, "albedo_max_abs": amax,
            "min_own_weight": wmin}


def stress_methods(model, pdm, gt, tex, store: dict, others: dict):
    """name → callable(markers) → (V, maps at the texels, None), as pdm_report's evaluation wants;
    ``others``: further marker-driven rows (name → callable)."""
    def tracked(_markers):
        out = model.synthesize(gt.vertices, ("displacement", "wrinkle_weights"))
        store["tracked"] = out
        return gt.vertices, tex.texels(out["displacement"]), None

    def engine(_markers):
        ww = store["tracked"]["wrinkle_weights"]
        return gt.vertices, tex.texels(model.engine_maps(ww)), None

    def on_pdm(markers):
        V = pdm.synthesize(markers, ("mesh",))["vertices"].astype(np.float64)
        return V, tex.texels(model.synthesize(V, ("displacement",))["displacement"]), None

    def neutral(_markers):
        d = tex.texels(model.displacement[0])
        return gt.vertices, np.broadcast_to(d, (len(gt.frames), len(d))), None

    return {"PDM biquadratic": lambda m: harness.pdm_prediction(pdm, m, tex), **others,
            "stress blend (tracked mesh)": tracked,
            "engine: masks × weights (tracked mesh)": engine,
            "stress blend (PDM mesh)": on_pdm,
            "static neutral map": neutral}


def map_scores(model, gt, tex, actor, store: dict) -> dict:
    """The maps alone: each row's displacement map against the ground truth's map relative
    to the same (ground-truth) mesh, ``displacement − vertex_detail_map`` (what the scans'
    maps hold), face texels, no high-pass: Pearson r and RMS / RMS(truth)."""
    truth = tex.truth_map(actor, gt)
    rows = {"stress blend (tracked mesh)": tex.texels(store["tracked"]["displacement"]),
            "engine: masks × weights (tracked mesh)": tex.texels(model.engine_maps(store["tracked"]["wrinkle_weights"])),
            "static neutral map": np.broadcast_to(tex.texels(model.displacement[0]), truth.shape)}
    y = truth[:, tex.face].astype(np.float64).ravel()
    out = {}
    for name, d in rows.items():
        x = np.asarray(d)[:, tex.face].astype(np.float64).ravel()
        out[name] = {"r": float(np.corrcoef(x, y)[0, 1]),
                     "relative_rms": float(np.sqrt(np.mean((x - y) ** 2)) / np.sqrt(np.mean(y ** 2)))}
    store["truth_relative"] = truth
    return out


def albedo_errors(model, pdm, actor_dir: Path, name: str, frames: np.ndarray, V: np.ndarray,
                  markers: np.ndarray, face_mask: np.ndarray) -> dict:
    """Relative RMS error of the albedo maps against the ground truth (face texels)."""
    with np.load(actor_dir / "performances" / f"{name}.npz") as d:
        slot = {int(f): i for i, f in enumerate(d["map_frames"])}
        gt = d["albedo"][[slot[int(f)] for f in frames]].astype(np.float64)
    sb = model.synthesize(V, ("albedo",))["albedo"]
    pd = pdm.synthesize(markers, ("albedo",))["albedo"]
    neutral = np.broadcast_to(model.albedo[0], gt.shape)
    mean = gt[:, face_mask].mean(axis=0)

    def rel(x):
        return float(np.sqrt(np.mean((x[:, face_mask] - gt[:, face_mask]) ** 2))
                     / np.sqrt(np.mean((gt[:, face_mask] - mean) ** 2)))
    return {"stress blend (tracked mesh)": rel(sb), "PDM biquadratic": rel(pd), "static neutral map": rel(neutral)}


def engine_vs_blend(model, V: np.ndarray) -> dict:
    """How well masks × region weights reproduce the full per-texel blend (relative RMS)."""
    out = model.synthesize(V, ("displacement", "albedo", "wrinkle_weights"))
    res = {}
    for kind in ("displacement", "albedo"):
        full = out[kind]
        eng = model.engine_maps(out["wrinkle_weights"], kind)
        band = model.disp_band if kind == "displacement" else model.albedo_band
        m = band.mask()
        base = model.displacement[0] if kind == "displacement" else model.albedo[0]
        delta = full[:, m] - base[m]
        res[kind] = float(np.sqrt(np.mean((eng[:, m] - full[:, m]) ** 2)) / np.sqrt(np.mean(delta ** 2)))
    res["weights_per_frame"] = int(np.prod(out["wrinkle_weights"].shape[1:]))
    return res


def synth_speed(model, V: np.ndarray) -> dict:
    model.synthesize(V[:1], ("displacement", "albedo", "normal_map", "wrinkle_weights"))
    out = {}
    for name, outs in (("displacement + wrinkle_weights", ("displacement", "wrinkle_weights")),
                       ("all maps", ("displacement", "albedo", "normal_map", "wrinkle_weights"))):
        ts = []
        for f in range(1, min(len(V), 9)):
            t0 = time.perf_counter()
            model.synthesize(V[f:f + 1], outs)
            ts.append(time.perf_counter() - t0)
        out[name] = 1e3 * float(np.median(ts))
    return out


# --------------------------------------------------------------------------------------
# figures

def plot_blended_maps(model, gt, frames, store, pdm_maps, path: Path, tex) -> None:
    """Displacement maps (face box) for a few held-out frames: truth, blend, engine, PDM."""
    import matplotlib.pyplot as plt

    box = harness.face_box(tex)
    H = tex.H
    tracked = store["tracked"]
    truth = [tex.image(store["truth_relative"][i], only_face=False) for i in frames]
    rows = [("ground truth (all detail)", [gt.displacement[i] for i in frames]),
            ("ground truth rel. to mesh", [np.nan_to_num(t) for t in truth]),
            ("stress blend (rel. to mesh)", [tracked["displacement"][i] for i in frames]),
            ("engine masks × weights", list(model.engine_maps(tracked["wrinkle_weights"][frames]))),
            ("PDM biquadratic fine map", [pdm_maps[i] for i in frames])]
    fig, axes = plt.subplots(len(rows), len(frames), figsize=(4.2 * len(frames), 4.2 * len(rows)),
                             squeeze=False, layout="constrained")
    for r, (name, maps) in enumerate(rows):
        lim = float(np.percentile(np.abs(np.concatenate([m[box].ravel() for m in maps])), 99.5))
        for j, (f, m) in enumerate(zip(frames, maps)):
            axes[r, j].imshow(m.reshape(H, H)[box], cmap="RdBu_r", vmin=-lim, vmax=lim)
            axes[r, j].set_title(f"{name}\nframe {gt.frames[f]} (±{lim:.2f} mm)", fontsize=9)
            axes[r, j].set_xticks([]), axes[r, j].set_yticks([])
    fig.suptitle(f"Blended displacement maps, {gt.name} (UV, face region)")
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_albedo(model, tracked_albedo, gt_albedo, frames, path: Path, title: str = "") -> None:
    """Target (ground-truth) albedo, the scans' albedo warped into the frame by the stress
    blend, and |warped − target| (luminance, ×10 scale bar in the title), for a few frames."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(frames), figsize=(4 * len(frames), 12), squeeze=False, layout="constrained")
    m = model.albedo_band.mask()
    for j, i in enumerate(frames):
        diff = np.abs(np.asarray(tracked_albedo[j], np.float64) - gt_albedo[j]).mean(axis=-1)
        lim = max(float(np.percentile(diff[m], 99.5)), 1e-6)
        for r, (name, img) in enumerate((("target (ground truth)", gt_albedo[j]),
                                         ("stress blend (scans warped to the frame)", tracked_albedo[j]))):
            axes[r, j].imshow(np.clip(img, 0, 1) ** (1 / 2.2))
            axes[r, j].set_title(f"{name} albedo, frame {i}", fontsize=9)
            axes[r, j].axis("off")
        im = axes[2, j].imshow(np.where(m, diff, np.nan), cmap="magma", vmin=0, vmax=lim)
        axes[2, j].set_title(f"|warped − target| (mean over RGB), frame {i}\nmean {diff[m].mean():.4f}, "
                             f"p99.5 {lim:.3f}", fontsize=9)
        axes[2, j].axis("off")
        fig.colorbar(im, ax=axes[2, j], shrink=0.7)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_masks_weights(model, path: Path) -> None:
    import matplotlib.pyplot as plt

    masks = model.texel_masks()
    R = len(masks)
    fig, axes = plt.subplots(1, 2, figsize=(12, 6), layout="constrained")
    rgb = np.zeros(masks.shape[1:] + (3,))
    colors = plt.get_cmap("tab10")(np.arange(R) % 10)[:, :3]
    for r in range(R):
        rgb += masks[r][..., None] * colors[r]
    axes[0].imshow(rgb)
    axes[0].set_title(f"{R} wrinkle-region masks (colour per region, soft edges)")
    axes[0].axis("off")
    W = model.importance
    axes[1].imshow(np.log10(np.maximum(W, 1e-4)), aspect="auto", cmap="magma", interpolation="nearest")
    axes[1].set_yticks(range(len(W)), model.scan_names[1:], fontsize=8)
    axes[1].set_title("log10 importance δ_ik per expression (vertices on x)")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_bone_weights(actor_dir: Path, rig_path: Path, path: Path) -> None:
    """The rig's bone weights in UV space: hue = dominant bone, brightness = its weight."""
    import matplotlib.pyplot as plt
    from service.geometry.uv_raster import rasterize_uv
    from service.methods.bone_rig.rig import BoneRig
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    rig = BoneRig.load_npz(rig_path)
    H = 512
    raster = rasterize_uv(actor.uv, actor.uv_faces, H, H)
    rng = np.random.default_rng(0)
    colors = rng.uniform(0.2, 1.0, size=(rig.bones, 3))
    vcol = np.einsum("vk,vkc->vc", rig.weight, colors[rig.index])           # weight-blended bone colours
    img = raster.interpolate(vcol, actor.faces)
    second = raster.interpolate(rig.weight[:, 1], actor.faces)
    img[~raster.mask] = 1.0
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.5), layout="constrained")
    axes[0].imshow(np.clip(img, 0, 1))
    axes[0].set_title(f"{rig.bones} bones: weight-blended bone colours (UV)")
    axes[1].imshow(np.where(raster.mask, second, np.nan), cmap="viridis", vmin=0, vmax=0.5)
    axes[1].set_title("second-largest weight per texel (blend zones)")
    for a in axes:
        a.axis("off")
    fig.savefig(path, dpi=80)
    plt.close(fig)


# --------------------------------------------------------------------------------------
# report

def _f(x, d=3):
    return "–" if x is None else f"{x:.{d}f}"


def report(res: dict, meta: dict) -> str:
    L = ["# Game-engine outputs: stress-blended expression maps and the bone rig", "",
         f"Machine: {meta['cpus']} CPUs shared (load {meta['load']}), NumPy {np.__version__}. "
         f"Code: {meta['git']}.", ""]
    for fam, sb in (res.get("stress") or {}).items():
        L += [f"## 1{fam}. Stress blend, family {fam} ({sb['actor']})", "",
              f"Scans: {', '.join(sb['scans'])}. Training {sb['train']['train_s']:.0f} s, model "
              f"{sb['train']['size_mb']:.0f} MB. Map {sb['H']}², high-pass σ = {sb['sigma']:.1f} texels "
              "(the PDM's).", "",
              "**A frame equal to a scan blends to that scan**: each of the "
              f"{sb['repro']['scans']} scans fed as a frame (model reloaded from disk): max |Δ| "
              f"displacement {sb['repro']['disp_max_abs_mm']:.3g} mm, albedo {sb['repro']['albedo_max_abs']:.3g}; "
              f"smallest own weight {sb['repro']['min_own_weight']:.6g}.", ""]
        for perf, r in sb["accuracy"].items():
            sig = r["signal_rms_mm"][harness.FACE]
            L += [f"### {perf} ({r['frames']} map frames), face texels; GT high-band RMS {sig:.3f} mm", "",
                  "| method | input | fine r | fine RMS mm | relative error | medium mean mm |",
                  "|---|---|---:|---:|---:|---:|"]
            for name, s in r["scores"][harness.FACE].items():
                inp = ("markers" if name.startswith("PDM") or name in (WPSD_ROW, SS_ROW)
                       else "markers (PDM mesh)" if "PDM mesh" in name
                       else "GT mesh + GT map" if name == harness.GT_ROW else "tracked mesh")
                L.append(f"| {name} | {inp} | {s['fine_r']:.3f} | {s['fine_rms_mm']:.3f} | "
                         f"{s['fine_rms_mm'] / sig:.3f} | {s['medium_mean_mm']:.3f} |")
            L += ["", "The maps alone (each against the ground truth's map relative to the same mesh, "
                  "face texels, no high-pass):", "", "| method | map r | map relative RMS |", "|---|---:|---:|"]
            for name, m in r["maps"].items():
                L.append(f"| {name} | {m['r']:.3f} | {m['relative_rms']:.3f} |")
            a = sb["albedo"].get(perf)
            if a:
                L += ["", "Albedo, relative RMS error vs ground truth (face texels, / GT std): " +
                      ", ".join(f"{k} {v:.3f}" for k, v in a.items()) + "."]
            L.append("")
        e = sb["engine"]
        L += ["### Engine form: masks × per-region weights vs the full per-texel blend", "",
              f"{sb['regions']} masks; {e['weights_per_frame']} weights per frame (regions × expressions). "
              f"Relative RMS of (engine − full blend) / (full blend − neutral map) over "
              f"{PERFORMANCES[0]} map frames: displacement {e['displacement']:.3f}, albedo {e['albedo']:.3f}.", "",
              "Synthesis speed, ms/frame (median, one frame per call): " +
              ", ".join(f"{k} {v:.0f}" for k, v in sb["speed"].items()) + ".", "",
              f"Figures: a_blended_maps_{fam}.png, b_warped_vs_target_{fam}.png (target albedo, the "
              f"scans' albedo warped into the frame by the blend, |warped − target|), "
              f"d_wrinkle_masks_{fam}.png.", ""]
    rg = res.get("rig")
    if rg:
        f, d = rg["facesynth"], rg["dem"]
        L += ["## 2. Bone rig vs py-dem-bones (level-0 sample actor)", "",
              f"Animation: {RIG_PERFORMANCE}, {f.get('frames', '?')} frames × {f.get('vertices', '?')} "
              f"vertices, rest = frame 0; {RIG_BONES} bones, ≤ {RIG_INFLUENCES} influences, "
              f"{RIG_ITERATIONS} iterations each; fresh process per solver.", "",
              "| solver | bones | RMS mm | p99 mm | max mm | time s | peak RSS MB |", "|---|---:|---:|---:|---:|---:|---:|"]
        for name, r in (("facesynth bone_rig", f), ("py-dem-bones", d)):
            if "rms_mm" in r:
                L.append(f"| {name} | {r['bones']} | {r['rms_mm']:.4f} | {r['p99_mm']:.3f} | {r['max_mm']:.3f} | "
                         f"{r['seconds']:.0f} | {r['peak_rss_mb']:.0f} |")
            else:
                L.append(f"| {name} | – | {r.get('outcome')} | | | | |")
        if "rms_mm" in f and "rms_mm" in d:
            L += ["", f"Ratio facesynth / py-dem-bones: RMS {f['rms_mm'] / d['rms_mm']:.3f}, max "
                  f"{f['max_mm'] / d['max_mm']:.3f}, time {f['seconds'] / d['seconds']:.2f}."]
        if "history" in f:
            L += ["", "facesynth RMS per iteration (mm): " + ", ".join(f"{x:.3f}" for x in f["history"]) + ".",
                  f"glTF: {f['glb_bytes'] / 1e6:.1f} MB .glb (mesh, {f['bones']} joints, inverse bind "
                  "matrices, JOINTS_0/WEIGHTS_0, one translation + rotation channel per joint)."]
        if "max_influences_used" in d:
            L += [f"py-dem-bones result: at most {d['max_influences_used']} non-zero weights per vertex, "
                  f"|Σw − 1| ≤ {d['weight_sum_err']:.2g}, min weight {d['min_weight']:.3g}."]
        L += ["", "### Bad inputs (6 frames × 400 vertices, each case in its own process)", "",
              "| input | py-dem-bones `solve_skinning` | facesynth `decompose` |", "|---|---|---|"]
        for case, r in rg["crash"].items():
            L.append(f"| {case} | {r['dem']['outcome']} | {r['facesynth']['outcome']} |")
        L.append("")
    L += [f"Figures in benchmarks/out/game_outputs/. Total run {meta['total_s']:.0f} s."]
    return "\n".join(L) + "\n"


def _save_part(path: Path, key: str, value) -> None:
    """Update one part of the results file (the other part may have been written meanwhile)."""
    res = json.loads(path.read_text()) if path.is_file() else {}
    res[key] = value
    path.write_text(json.dumps(res, indent=1))


def pose_space_model(actor, clips, actor_dir: Path, reuse: bool, family: str):
    """The default WPSD (bickel2008) of the family: the one pose_space_report.py saved for this
    actor if there is one, else trained here (and cached)."""
    from service.methods.pose_space import PoseSpaceModel, WpsdParams, train

    for saved in (OUT / f"pose_space_{family}" / "models" / actor_dir.name / "WPSD",
                  OUT / "pose_space" / "models" / actor_dir.name / "WPSD",
                  FIGURES / "models" / family / "wpsd"):
        if (saved / "manifest.json").is_file() and (reuse or saved.parent.name != family):
            m = PoseSpaceModel.load(saved)
            if m.params == WpsdParams(marker_regression=None) and m.data.n_vertices == actor.n_vertices:
                return m
    model = train(actor, clips, WpsdParams(marker_regression=None))
    model.save(FIGURES / "models" / family / "wpsd")
    return model


def pdm_model(actor, clips, H: int, reuse: bool, family: str):
    """The biquadratic PDM (defaults, fine band at the actor's map size), cached."""
    from service.methods.pdm.model import PdmModel, PdmParams, train

    path = FIGURES / "models" / family / "pdm"
    if reuse and (path / "manifest.json").is_file():
        return PdmModel.load(path)
    model = train(actor, clips, PdmParams(fine_resolution=H))
    model.save(path)
    return PdmModel.load(path)


def stress_family(family: str, actor_dir: Path, args) -> dict:
    """Part 1 on one actor family: accuracy rows, scan reproduction, engine form, figures."""
    from service.methods.stress_blend.model import StressBlendModel
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    clips = harness.training_clips(actor_dir, actor)
    H = json.loads((actor_dir / "manifest.json").read_text())["map_resolution"]
    print(f"[{family}] PDM", file=sys.stderr)
    pdm = pdm_model(actor, clips, H, args.reuse, family)
    print(f"[{family}] pose space (WPSD)", file=sys.stderr)
    wpsd = pose_space_model(actor, clips, actor_dir, args.reuse, family)
    print(f"[{family}] stress blend", file=sys.stderr)
    model, train_rec = stress_blend_model(actor, clips, args.reuse, family)
    model = StressBlendModel.load(FIGURES / "models" / family / "stress_blend")
    repro = scan_reproduction(model, clips)
    del clips
    sigma = pdm.metrics["highpass_sigma_texels"]
    tex = harness.DetailTexels.build(actor, pdm.data.fine.resolution, sigma)
    if model.disp_band.resolution != tex.H:
        sys.exit(f"stress-blend maps are {model.disp_band.resolution}², the PDM's fine band {tex.H}²")
    others = {WPSD_ROW: lambda m: _pose_space_prediction(wpsd, m, tex)}
    if args.shape_space:
        others[SS_ROW] = _shape_space_method(actor_dir, tex)
    sb = {"actor": str(actor_dir), "scans": model.scan_names, "train": train_rec, "repro": repro, "H": tex.H,
          "sigma": sigma, "regions": int(model.masks.shape[1]), "accuracy": {}, "albedo": {}}
    limit = harness.QUICK_FRAMES if args.quick else None
    amask_face = None
    for perf in PERFORMANCES:
        if not (actor_dir / "performances" / f"{perf}.npz").is_file():
            continue
        print(f"[{family}]   {perf}", file=sys.stderr)
        gt = harness.load_heldout(actor_dir, perf, limit)
        store: dict = {}
        keep = harness.strong_frames(gt, FIGURE_FRAMES, harness.FIGURE_SEPARATION) if perf == PERFORMANCES[0] else []
        r = harness.evaluate_performance(gt, stress_methods(model, pdm, gt, tex, store, others), tex, actor, keep)
        r.pop("figure"), r.pop("extra")
        r["frames"] = len(gt.frames)
        r["maps"] = map_scores(model, gt, tex, actor, store)
        sb["accuracy"][perf] = r
        if amask_face is None:
            from service.geometry.uv_raster import rasterize_uv
            Ha = model.albedo_band.resolution
            ra = rasterize_uv(actor.uv, actor.uv_faces, Ha, Ha)
            amask_face = ra.mask & np.asarray(actor.regions[harness.FACE])[actor.faces[np.maximum(ra.triangle, 0), 0]]
        sb["albedo"][perf] = albedo_errors(model, pdm, actor_dir, perf, gt.frames, gt.vertices,
                                           gt.markers, amask_face)
        if perf == PERFORMANCES[0]:
            sb["engine"] = engine_vs_blend(model, gt.vertices)
            sb["speed"] = synth_speed(model, gt.vertices)
            idx = [int(np.flatnonzero(gt.frames == f)[0]) for f in keep]
            pdm_maps = pdm.synthesize(gt.markers[idx], ("displacement",))["displacement"]
            plot_blended_maps(model, gt, idx, store, {i: m for i, m in zip(idx, pdm_maps)},
                              FIGURES / f"a_blended_maps_{family}.png", tex)
            with np.load(actor_dir / "performances" / f"{perf}.npz") as d:
                slot = {int(f): i for i, f in enumerate(d["map_frames"])}
                gta = d["albedo"][[slot[f] for f in keep]].astype(np.float32)
            plot_albedo(model, model.synthesize(gt.vertices[idx], ("albedo",))["albedo"], gta, keep,
                        FIGURES / f"b_warped_vs_target_{family}.png",
                        f"family {family} ({actor_dir.name}), {perf}: target vs warped albedo")
    plot_masks_weights(model, FIGURES / f"d_wrinkle_masks_{family}.png")
    return sb


def _pose_space_prediction(model, markers, tex):
    out = model.synthesize(markers, ("mesh", "displacement"))
    return out["vertices"].astype(np.float64), tex.texels(out["displacement"]), out["clamped"]


def _shape_space_method(actor_dir: Path, tex):
    """bermano2014 on the family's database, marker input (the harness's cached build)."""
    from service.methods.shape_space import ShapeSpaceModel, ShapeSpaceParams

    ss_dir, _ = harness.shape_space_model(actor_dir, ShapeSpaceParams(), False)
    shape = ShapeSpaceModel.load(ss_dir)

    def run(markers):
        out = shape.enhance(markers, harness.SS_OUTPUTS, input_kind="markers")
        D = (np.stack([tex.texels(m) for m in out["fine_displacement"]])
             if "fine_displacement" in out else None)
        return out["vertices"].astype(np.float64), D, None
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reuse", action="store_true", help="reuse models and rig results in benchmarks/out")
    parser.add_argument("--quick", action="store_true", help="6 held-out frames per performance")
    parser.add_argument("--part", choices=("all", "stress", "rig"), default="all")
    parser.add_argument("--actor", action="append", metavar="FAMILY=DIR",
                        help="actor family of part 1 (default a, b: benchmarks/out/actor-{a,b}-l0, built if missing)")
    parser.add_argument("--shape-space", action="store_true",
                        help="also the shape-space row (builds bermano2014 on each family's database "
                             "through shape_space_report's cache: long)")
    parser.add_argument("--worker", choices=("rig", "crash"), help=argparse.SUPPRESS)
    parser.add_argument("--which", help=argparse.SUPPRESS)
    parser.add_argument("--case", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker == "rig":
        print(json.dumps(worker_rig(args.which, ACTOR_L0, FIGURES / "rig")))
        return
    if args.worker == "crash":
        print(json.dumps(worker_crash(args.which, args.case, ACTOR_L0)))
        return
    t_start = time.perf_counter()
    FIGURES.mkdir(parents=True, exist_ok=True)
    meta = {"cpus": os.cpu_count(), "load": f"{os.getloadavg()[0]:.1f}", "git": harness.git_state()}
    results_path = FIGURES / "results.json"
    res = json.loads(results_path.read_text()) if (args.reuse and results_path.is_file()) else {}

    if args.part in ("all", "rig"):
        print("bone rig (fresh processes)", file=sys.stderr)
        rig = res.get("rig") if args.reuse and "rig" in res else {}
        for which in ("facesynth", "dem"):
            if which not in rig or "rms_mm" not in rig[which]:
                t0 = time.perf_counter()
                rig[which] = run_worker("--worker", "rig", "--which", which)
                print(f"  {which}: {time.perf_counter() - t0:.0f} s {rig[which].get('rms_mm')}", file=sys.stderr)
        rig["crash"] = {case: {w: run_worker("--worker", "crash", "--which", w, "--case", case,
                                             timeout=CRASH_TIMEOUT_S)
                               for w in ("dem", "facesynth")}
                        for case in CRASH_CASES}
        res["rig"] = rig
        _save_part(results_path, "rig", rig)
        if (FIGURES / "rig" / "rig.npz").is_file():
            plot_bone_weights(ACTOR_L0, FIGURES / "rig" / "rig.npz", FIGURES / "c_bone_weights.png")

    if args.part in ("all", "stress"):
        families = dict(FAMILIES)
        for spec in args.actor or []:
            fam, _, d = spec.partition("=")
            families[fam] = Path(d)
        stress = res.get("stress", {}) if args.reuse else {}
        stress = {k: v for k, v in stress.items() if isinstance(v, dict) and "accuracy" in v}
        for fam, actor_dir in families.items():
            if not (actor_dir / "manifest.json").is_file():
                print(f"family {fam}: {actor_dir} has no manifest.json, skipped", file=sys.stderr)
                continue
            stress[fam] = stress_family(fam, actor_dir.resolve(), args)
            _save_part(results_path, "stress", stress)
        res["stress"] = stress
    res = json.loads(results_path.read_text()) if results_path.is_file() else res

    meta["total_s"] = time.perf_counter() - t_start
    text = report(res, meta)
    print(text)
    (OUT / "game_outputs_report.md").write_text(text)


if __name__ == "__main__":
    main()

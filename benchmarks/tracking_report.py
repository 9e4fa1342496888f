"""Performance-flow tracking report (fyffe et al., Digital Ira course 2014, §4–7).

Data: :func:`service.samples.tracking.build_tracking_sample` of each actor directory given
(default: families a and b at level 0, ``benchmarks/out/actor-{a,b}-l0``, built if
missing): the whole held-out in-range performance and ``--rest-frames`` of rest after it,
rendered through 3 cameras (frontal first) with light and exposure changes and camera
noise, the neutral plus ``--scans``
training-clip peaks as static scans re-meshed as range scans (cached in
``benchmarks/out/tracking/``).

Methods (one :func:`~service.methods.tracking.track.track` call each, same solver):

* *sequential*: frame-to-frame propagation from frame 0 (registered to the neutral);
* *neutral anchors*: the flow graph with the neutral scan as the only static candidate;
* *flow graph*: the full method (all scans), in 3 views and in 1 view (monocular).

Metrics: per-frame mean vertex error (mm) over the face vertices (region 0) against the
ground truth, plotted over time; start / end (means of the first and last 10 frames) and
their ratio (drift); the temporal variance of contrast-normalized texture in UV space
(Fig. 15's metric: view 0 projected onto the tracked mesh at 128² texels, each texel's
intensity normalized by its local mean and deviation over σ = 3 texels, variance over time,
mean over texels seen in every frame); static-to-dynamic edges selected vs candidates;
registration error of the static scans (Fig. 11 by-product); the blended albedo maps
(§7.3) against the ground-truth maps at the performance's map frames (mean |error| over face
texels and channels), vs the blend by the correspondence strength alone (the paper's
weights, without :mod:`~service.methods.tracking.maps`' surface-stress similarity), the neutral's
map alone, and two oracles (the best single scan per frame; the best scan per texel);
stage timings and time per frame; flows per second (the method's flow + NCC vs OpenCV's DIS
medium preset alone). Figures: ``error_over_time_<fam>.png``, ``graph_<fam>.png``.

Measured (level 0, 256² images, neutral + 5 scans, 2 cores, commit d7aa43d's report, load
1.0-4.1): the whole held-out performance, which starts and ends on the neutral (a 154, b 146
frames), plus :data:`REST_FRAMES` frames of rest, so the start and end windows (10 frames
each) see the same expression and end/start measures drift alone:

=====================  =====  =======  =====  =====  =========  ===========  ===========
method                 views  mean mm  start  end    end/start  slope/100fr  texture var
=====================  =====  =======  =====  =====  =========  ===========  ===========
a sequential           3      1.024    0.316  0.941  2.97       +0.313       0.0927
a neutral anchors      3      0.544    0.241  0.229  0.95       +0.069       0.0945
a flow graph           3      0.444    0.194  0.191  0.98       +0.056       0.0881
a flow graph, mono     1      1.461    0.533  1.291  2.42       +0.279       0.0824
b sequential           3      0.803    0.303  0.740  2.44       +0.318       0.0803
b neutral anchors      3      0.676    0.313  0.217  0.70       +0.072       0.0832
b flow graph           3      0.613    0.298  0.313  1.05       +0.127       0.0840
b flow graph, mono     1      2.305    4.262  0.860  0.20       −0.600       0.0828
=====================  =====  =======  =====  =====  =========  ===========  ===========

(no tracking: a 4.94, b 7.01 mm; ground-truth texture variance a 0.1017, b 0.0959: the metric
follows the light swing and does not separate the methods.) The full graph has the lowest
mean error on both families and no drift (back at its start error once the face is at rest
again), where sequential propagation ends 2.4-3× its start. Monocular: family b's error is
the head's depth along the view axis (camera at 622 mm, f = 579 px at 256²; on the first 30
frames 0.6-5.3 mm, of which 0.34-0.86 mm is left once each frame is rigidly aligned to the
truth).

Until session 15 the report tracked the first 120 frames (commit 75fecc0, load 4.5-6.8):
a flow graph 0.401 mean, 0.187 start, 0.491 end, ratio 2.63; b 0.642 / 0.283 / 0.400 / 1.41;
sequential a 3.63, b 2.48. Family a's cut ended on a strong expression (amplitude 1.71 mm
over the last ten frames against 0.45 over the first), so its end/start measured the
expression, not drift: against the early frames of like amplitude the end was 1.07× (a)
and 1.19× (b), and taking all eight training peaks as scans instead of five left it at 2.54
(d7aa43d's parent, load 1.0-4.0). The whole take with a rest compares like with like.

Monocular depth (session 14; 256², 1 view, mean face error mm; 3-view error in brackets,
unchanged by it: a 0.387 / 0.404, b 0.481 / 0.628 at 40 / 120 frames): the opt-in
``TrackingParams(monocular_depth=True)`` reads the head's distance from the size of the
face part no static pose moves (:func:`service.methods.tracking.solve.update_rigid`).
a 40 frames 0.700 → 0.717, 120 frames 1.273 → 1.503; b 40 frames 3.177 → 1.803, 120
frames 2.480 → 2.291. It stays off: family a's performance has expressions the scans do not
show that change that part's size (see the docstring). Measured with one ``track()`` call
per cell on the report's samples (load 2-4.5).

Speed (512², 30 frames, neutral + 5 scans, graph method, one process, 1 BLAS thread; CPU
seconds per frame, all threads; load 5-7 on 2 cores throughout). Before: commit 8974d4e;
after: this file's commit. Family a has 11 248 vertices (the issue's ≈10k), b 21 092:

======  =====  ==================  ==================  ===============  ================
family  views  CPU s/fr before     CPU s/fr after      mean mm before   mean mm after
======  =====  ==================  ==================  ===============  ================
a       1      2.35                1.09                0.682            0.682
b       1      3.41                1.72                2.554            2.379
a       3      5.62                2.35                0.324            0.328
b       3      7.14                2.96                0.249            0.249
======  =====  ==================  ==================  ===============  ================

Wall time was 1.6-2.4× the CPU time in every run: the main thread's run-queue wait
(``/proc/self/schedstat``) accounts for all of it (a, 1 view, after: wall 78.5 s = 29.8 s
running + 48.2 s waiting for a core + 0.5 s else), so the gap is the other work on the
two cores, not I/O, sleeping or subprocesses. What cut the CPU: the temporal flows were
computed twice (keyframe concatenation, then the spans: 58 of 197 flows); DIS at patch
stride 4 instead of 2 (0.115 against 0.221 s per 512² flow at the same end-point error);
the visibility z-buffer at 256 px (0.042 against 0.119 s per pose and view); the CG's
matrix as BSR blocks in vertex-major order (0.65 against 1.10 s per 100 iterations for 8
poses). Flows per second at 512² (CPU, 1 view): flow + NCC 4.5 → 8.9 (a), 4.6 → 10.1 (b);
OpenCV DIS medium alone 38.5 / 35.6. The NCC confidence is 0.019 s of a flow's 0.11 s; the
remaining flow cost is DIS at finest scale 0 (finest scale 1: 0.051 s, but 20-40 % larger
end-point error).

Where family a's end error comes from (256², 120 frames, 3 views, full graph; mean 0.404,
start 0.191, end 0.504, ratio 2.63, as before this session's speed changes: 0.401 / 0.187 /
0.491 / 2.63). No scan resembles the last frames: for every frame 110-119 the nearest scan
(rigidly aligned, mean distance) is the neutral, at the frame's own expression amplitude
(1.1-2.4 mm). 87 % of the end-minus-start error increase is in the lower centre and left
of the face (4 × 3 grid in view 0), where the truth moves 2-4 mm, and the end error equals
the error of earlier frames of like amplitude (frames 15, 60, 90: amplitude 1.9-2.3 mm,
error 0.51-0.53 mm). Anchors are selected there (frame 110: pucker; 119: all six scans). The
per-vertex end error correlates with the registration error of the smile (r = 0.82),
pucker (0.71) and chin-raise (0.69) scans (registered 0.75 / 1.53 / 0.64 mm off, mostly
tangentially), but holding every static pose at its ground truth only moves the end error
from 0.504 to 0.468 mm (mean 0.404 → 0.380, ratio 2.63 → 2.25): the registration is a
small part; the performance's end expression, outside the scans, is the rest.

Run: ``python benchmarks/tracking_report.py [ACTOR_DIR ...] [--size 256] [--frames N] [--rest-frames 10]
[--scans 5] [--no-monocular] [--speed-size 512 --speed-frames 30] [--speed-only] [--out DIR]``.
Writes ``benchmarks/out/tracking/report.md`` (or ``DIR/report.md``; and stdout).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")      # tiny BLAS calls: threads only thrash
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

import harness  # noqa: E402  (the sample actors every report shares)

OUT = ROOT / "benchmarks" / "out" / "tracking"
#: frames of rest after the performance (its last pose, the neutral, held): the take starts
#: and ends at rest, so the drift columns compare the same expression at both ends
REST_FRAMES = 10


def texture_variance(sample, vertices: np.ndarray, res: int = 128, sigma: float = 3.0) -> float:
    """Fig. 15: mean temporal variance of contrast-normalized view-0 texture in UV space."""
    from service.geometry import optical_flow as of
    from service.geometry.uv_raster import interpolation_matrix, rasterize_uv

    raster = rasterize_uv(sample.uv, sample.uv_faces, res, res)
    M = interpolation_matrix(raster, sample.faces, len(sample.artist_vertices))
    face_tex = (M @ (sample.region == 0).astype(float)) > 0.99
    cam = sample.cameras[0]
    stack, seen = [], np.ones(res * res, bool)
    for t in range(len(vertices)):
        P = M @ vertices[t].astype(np.float64)
        xy = cam.project(P)[:, :2] - 0.5
        img = sample.frame_images[t, 0].astype(np.float32)
        val = of.sample(img, xy, border=0.0).reshape(res, res)
        mean = cv2.GaussianBlur(val, (0, 0), sigma)
        std = np.sqrt(np.maximum(cv2.GaussianBlur(val * val, (0, 0), sigma) - mean ** 2, 1e-6))
        stack.append(((val - mean) / (std + 2.0)).ravel())
        seen &= of.sample(img, xy, border=0.0) > 0
    sel = seen & face_tex & raster.mask.ravel()
    return float(np.var(np.stack(stack)[:, sel], axis=0).mean())


def expression_amplitude(truth: np.ndarray, neutral: np.ndarray, face: np.ndarray) -> np.ndarray:
    """(T,) mean distance, mm, of each ground-truth frame (T,n,3) from the neutral (n,3) over
    the ``face`` vertices once the head motion is taken out (each frame rigidly aligned onto
    the neutral's face, :func:`~service.geometry.rigid.rigid_align_frames`)."""
    from service.geometry.rigid import rigid_align_frames

    R, t = rigid_align_frames(truth[:, face], neutral[face])
    aligned = np.einsum("tij,tnj->tni", R, truth[:, face]) + t[:, None]
    return np.linalg.norm(aligned - neutral[face], axis=2).mean(axis=1)


def drift(err: np.ndarray, amplitude: np.ndarray, window: int = 10) -> tuple[float, float]:
    """Drift with the expression's amplitude factored out of the error.

    err (T,) per-frame mean vertex error, mm; amplitude (T,) the ground truth's expression
    (:func:`expression_amplitude`), mm. The tracking error of any method grows with
    how far the face is from the neutral, so the plain end/start ratio of a performance that
    starts neutral and ends on a strong expression measures the expression, not drift. Two
    amplitude-free measures:

    * matched ratio: each of the last ``window`` frames paired with the frame of the first
      half whose amplitude is nearest; mean error of the last frames over that of their
      partners (1 = no growth over time at equal expression);
    * time slope: least squares ``err ≈ a + b·amplitude + c·t``; ``100·c`` in mm per 100
      frames (0 = no growth over time).
    """
    T = len(err)
    early = np.arange(T // 2)
    late = np.arange(T - window, T)
    partner = early[np.abs(amplitude[late, None] - amplitude[None, early]).argmin(axis=1)]
    ratio = float(err[late].mean() / err[partner].mean())
    A = np.column_stack([np.ones(T), amplitude, np.arange(T)])
    coef = np.linalg.lstsq(A, err, rcond=None)[0]
    return ratio, float(100.0 * coef[2])


def plot_errors(path: Path, curves: dict, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for name, err in curves.items():
        ax.plot(err, label=f"{name} (mean {np.mean(err):.2f})")
    ax.set_xlabel("frame")
    ax.set_ylabel("mean vertex error, mm (face)")
    ax.set_title(title)
    ax.set_ylim(bottom=0)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_graph(path: Path, graph, names, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    S = len(names)
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True,
                                 gridspec_kw={"height_ratios": [1.2, 1]})
    T = graph.frames
    ax.plot([0, T - 1], [-1, -1], color="red", lw=3, label="temporal edges (all neighbours)")
    colours = plt.cm.tab10(np.arange(S) % 10)
    for s, t in graph.static_edges:
        ax.plot([t, t], [-1, s], color=colours[s], lw=1.2)
        ax.plot(t, s, "o", color=colours[s], ms=5)
    ax.set_yticks(range(-1, S))
    ax.set_yticklabels(["frames"] + [str(n).replace("train_", "") for n in names])
    ax.set_title(f"{title}: {len(graph.static_edges)} static edges of {graph.candidates} candidates")
    ax.legend(loc="upper right", fontsize=8)
    for s in range(S):                         # the per-scan maximum region confidence (Fig. 5)
        tab = graph.table[s]
        ok = np.isfinite(tab).any(axis=0)
        row = np.full(tab.shape[1], np.nan)
        row[ok] = np.nanmax(tab[:, ok], axis=0)
        if ok.any():
            bx.plot(np.flatnonzero(ok), row[ok], ".-", color=colours[s], ms=3, lw=0.8)
    bx.set_ylabel("best region confidence")
    bx.set_xlabel("frame")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def flow_speed(sample, params, n: int = 12) -> tuple[float, float, float]:
    """Flows per second (CPU time, one thread): the method's flow + NCC confidence, one
    tracking edge per view (both directions + forward-backward consistency, per flow), and
    OpenCV DIS at the same preset alone, alternating so load changes hit all three alike."""
    from service.geometry.optical_flow import dis_flow
    from service.methods.tracking.graph import edge_flows, flow_with_confidence

    n = min(n, len(sample.frame_images) - 1)
    pairs = [(sample.frame_images[t, 0], sample.frame_images[t + 1, 0]) for t in range(n)]
    cpu = {"ours": 0.0, "edge": 0.0, "dis": 0.0}
    for a, b in pairs:
        t0 = time.process_time()
        flow_with_confidence(a, b, params)
        cpu["ours"] += time.process_time() - t0
        t0 = time.process_time()
        edge_flows(a[None], b[None], ("frame", 0), ("frame", 1), params)
        cpu["edge"] += time.process_time() - t0
        t0 = time.process_time()
        dis_flow(a, b, params.dis_preset)
        cpu["dis"] += time.process_time() - t0
    return n / cpu["ours"], 2 * n / cpu["edge"], n / cpu["dis"]


def run_queue_wait() -> float:
    """Seconds this process's main thread has spent ready to run but waiting for a core
    (Linux ``/proc/self/schedstat``, second field; NaN elsewhere)."""
    try:
        return int(Path("/proc/self/schedstat").read_text().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return float("nan")


def speed_rows(actor: Path, args, lines: list, summary: dict) -> None:
    """Time per frame end to end (graph method) at ``--speed-size`` for 1 and 3 views."""
    from service.methods.tracking.params import TrackingParams
    from service.methods.tracking.track import TrackingInput, track
    from service.samples.tracking import TrackingSample, build_tracking_sample

    fam, size, T = actor.name, args.speed_size, args.speed_frames
    cache = OUT / f"sample_{fam}_{size}_{T}_{args.scans}.npz"
    if cache.exists():
        sample = TrackingSample.load(cache)
    else:
        manifest = json.loads((actor / "manifest.json").read_text())
        training = sorted(k for k, v in manifest["performances"].items() if v["kind"] == "training")
        sample = build_tracking_sample(actor, size=size, frames=T, views=3,
                                       scans=tuple(training[:args.scans]), out=cache)
    params = TrackingParams()
    ours, edge, dis = flow_speed(sample, params)
    rows = []
    for views in (1, 3):
        inp = TrackingInput.from_sample(sample, views=views)
        load = os.getloadavg()[0]
        w0, c0, q0 = time.perf_counter(), time.process_time(), run_queue_wait()
        result = track(inp, params)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        queued = run_queue_wait() - q0
        face = sample.region == 0
        err = np.linalg.norm(result.vertices - sample.frame_truth, axis=2)[:, face].mean()
        stages = ", ".join(f"{k} {v:.0f} / {result.cpu_timings.get(k, float('nan')):.0f}"
                           for k, v in result.timings.items())
        rows.append(f"| {fam} | {size}² | {views} | {T} | {len(sample.artist_vertices)} | {wall / T:.2f} | "
                    f"{cpu / T:.2f} | {queued / T:.2f} | {err:.3f} | {stages} | {load:.1f} |")
        summary[f"{fam}/speed/{size}/{views}"] = {"wall_s_per_frame": wall / T, "cpu_s_per_frame": cpu / T,
                                                  "run_queue_s_per_frame": queued / T,
                                                  "mean_mm": float(err), "timings": result.timings,
                                                  "cpu_timings": result.cpu_timings, "load": load}
        print("speed", views, wall / T, cpu / T, queued / T, flush=True)
    lines += [f"### Speed at {size}² ({T} frames, graph method, 1 BLAS thread, one process)", "",
              f"Flows per second at {size}² (CPU time, 1 view): flow + NCC {ours:.1f}; a tracking edge's "
              f"flows (both directions + consistency) {edge:.1f}; OpenCV DIS {params.dis_preset} preset "
              f"alone {dis:.1f}.", "",
              "| family | images | views | frames | vertices | wall s / frame | CPU s / frame | "
              "run-queue wait s / frame | mean mm | stages (wall / CPU s) | load |",
              "|---|---|---|---|---|---|---|---|---|---|---|", *rows, "",
              "The run-queue wait is the time the main thread was ready but waited for a core "
              "(``/proc/self/schedstat``): wall ≈ main-thread CPU + wait when other work shares "
              "the cores; CPU counts OpenCV's worker threads too.", ""]


def run_family(actor: Path, args, lines: list, summary: dict) -> None:
    from service.methods.tracking.maps import blend_maps, scan_weights
    from service.methods.tracking.params import TrackingParams
    from service.methods.tracking.track import TrackingInput, build_graph, track
    from service.samples.tracking import TrackingSample, build_tracking_sample

    fam = actor.name
    cache = OUT / f"sample_{fam}_{args.size}_{args.frames or 'all'}_{args.rest_frames}_{args.scans}.npz"
    t0 = time.perf_counter()
    if cache.exists():
        sample = TrackingSample.load(cache)
    else:
        manifest = json.loads((actor / "manifest.json").read_text())
        training = sorted(k for k, v in manifest["performances"].items() if v["kind"] == "training")
        sample = build_tracking_sample(actor, size=args.size, frames=args.frames, views=3,
                                       scans=tuple(training[:args.scans]),
                                       rest_frames=args.rest_frames, out=cache)
    build_s = time.perf_counter() - t0
    face = sample.region == 0
    T = len(sample.frame_images)
    params = TrackingParams()
    n = len(sample.artist_vertices)
    lines += [f"## {fam}: {T} frames, {args.size}² images, {len(sample.scan_names)} static scans "
              f"({', '.join(str(x) for x in sample.scan_names)}), {n} vertices", "",
              f"sample built/loaded in {build_s:.0f} s; raw scans "
              f"{', '.join(str(len(v)) for v in sample.scan_vertices)} vertices (re-meshed)", ""]
    runs = [r for r in [("sequential", "sequential", 3), ("neutral anchors", "neutral", 3),
                        ("flow graph", "graph", 3), ("flow graph, monocular", "graph", 1)]
            if r[0] != "flow graph, monocular" or not args.no_monocular]
    curves, rows, results = {}, [], {}
    graphs = {}
    amplitude = expression_amplitude(sample.frame_truth, sample.artist_vertices, face)
    for label, method, views in runs:
        inp = TrackingInput.from_sample(sample, views=views)
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        graph = graphs.get(method) if method != "sequential" else None
        result = track(inp, params, method=method, graph=graph)
        wall = time.perf_counter() - t0
        if method != "sequential":
            graphs[method] = result.graph
        err = np.linalg.norm(result.vertices - sample.frame_truth, axis=2)[:, face].mean(axis=1)
        curves[label] = err
        results[label] = result
        start, end = float(err[:10].mean()), float(err[-10:].mean())
        matched, slope = drift(err, amplitude)
        tv = texture_variance(sample, result.vertices)
        edges = f"{len(result.graph.static_edges)} / {result.graph.candidates}" if result.graph else "1 / –"
        rows.append(f"| {label} | {views} | {err.mean():.3f} | {start:.3f} | {end:.3f} | "
                    f"{end / start:.2f} | {matched:.2f} | {slope:+.3f} | {tv:.4f} | {edges} | {len(result.keyframes)} | "
                    f"{wall:.0f} | {wall / T:.2f} | {load:.1f} |")
        summary[f"{fam}/{label}"] = {"mean": float(err.mean()), "start": start, "end": end,
                                     "matched_drift": matched, "time_slope_mm_per_100": slope,
                                     "texture_variance": tv, "wall_s": wall,
                                     "timings": result.timings, "keyframes": result.keyframes,
                                     "edges": result.graph.static_edges if result.graph else []}
        print(label, views, f"mean {err.mean():.3f} start {start:.3f} end {end:.3f}", result.timings,
              flush=True)
    truth_tv = texture_variance(sample, sample.frame_truth)
    np.savez(OUT / f"curves_{fam}.npz", amplitude=amplitude,
             **{label.replace(" ", "_").replace(",", ""): e for label, e in curves.items()})
    lines += ["| method | views | mean error mm | start (10 fr) | end (10 fr) | end/start | "
              "end / amplitude-matched early | time slope mm/100 fr | texture variance (Fig. 15) | static edges / candidates | keyframes | wall s | s per frame | load |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|", *rows,
              f"| ground truth mesh | – | 0 | | | | | | {truth_tv:.4f} | | | | | |",
              f"| no tracking (the neutral) | – | "
              f"{np.linalg.norm(sample.frame_truth - sample.artist_vertices, axis=2)[:, face].mean():.3f}"
              " | | | | | | | | | | | |", ""]
    plot_errors(OUT / f"error_over_time_{fam}.png", curves, f"{fam}: per-frame vertex error")
    full = results["flow graph"]
    plot_graph(OUT / f"graph_{fam}.png", full.graph, list(sample.scan_names), f"{fam} flow graph")
    timing = ", ".join(f"{k} {v:.0f} s" for k, v in full.timings.items())
    lines += [f"Stages of the full method (3 views): {timing}.", ""]
    # static scans registered to the artist topology (Fig. 11)
    reg = []
    for s in range(1, len(sample.scan_names)):
        if np.isfinite(full.scan_vertices[s]).all():
            e = np.linalg.norm(full.scan_vertices[s] - sample.scan_truth[s], axis=1)[face].mean()
            moved = np.linalg.norm(sample.scan_truth[s] - sample.artist_vertices, axis=1)[face].mean()
            reg.append(f"{sample.scan_names[s]} {e:.2f} mm (neutral is {moved:.2f} mm off)")
        else:
            reg.append(f"{sample.scan_names[s]} not in the graph")
    lines += ["Static scans registered to the artist mesh (face vertices, vs truth): " + "; ".join(reg) + ".", ""]
    # per-frame weights and blended albedo maps (§7.3) against the truth maps
    t0 = time.perf_counter()
    inp = TrackingInput.from_sample(sample, views=3)
    W = scan_weights(inp, full, sample.uv, sample.uv_faces, params)
    weights_s = time.perf_counter() - t0
    W_conf = scan_weights(inp, full, sample.uv, sample.uv_faces, params, stress=False)   # §7.3 alone
    frames = sample.truth_map_frames
    A = sample.scan_albedo.astype(np.float32)
    truth = sample.truth_albedo.astype(np.float32)
    from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
    h = truth.shape[1]
    raster = rasterize_uv(sample.uv, sample.uv_faces, h, h)
    fmask = (interpolation_matrix(raster, sample.faces, n) @ face.astype(float)).reshape(h, h) > 0.99

    def map_error(maps):                   # mean |error| over face texels, channels, map frames
        return float(np.abs(maps - truth)[:, fmask].mean())

    e_blend = map_error(blend_maps(W[frames], sample.faces, sample.uv, sample.uv_faces, A))
    e_conf = map_error(blend_maps(W_conf[frames], sample.faces, sample.uv, sample.uv_faces, A))
    e_neutral = map_error(A[0][None])
    texel = np.abs(A[None] - truth[:, None])[:, :, fmask].mean(axis=3)             # (k,S,texels)
    e_frame_best = float(texel.mean(axis=2).min(axis=1).mean())
    e_texel_best = float(texel.min(axis=1).mean())
    dominant = np.bincount(W.argmax(axis=2)[:, face].ravel(), minlength=len(sample.scan_names))
    lines += [f"Blended albedo maps (§7.3) at the {len(frames)} ground-truth map frames, mean |error| "
              f"over face texels (weights in {weights_s:.0f} s):", "",
              "| maps | mean abs error |", "|---|---|",
              f"| blended: correspondence strength × surface-stress similarity (maps.py) | {e_blend:.5f} |",
              f"| blended: correspondence strength alone (§7.3) | {e_conf:.5f} |",
              f"| the neutral's map alone | {e_neutral:.5f} |",
              f"| best single scan per frame (oracle) | {e_frame_best:.5f} |",
              f"| best scan per texel (oracle) | {e_texel_best:.5f} |", "",
              "Share of face vertex-frames whose largest weight is each scan: "
              + ", ".join(f"{sample.scan_names[s]} {dominant[s] / dominant.sum():.0%}"
                          for s in range(len(dominant))) + ".", ""]
    ours, edge, dis = flow_speed(sample, params)
    lines += [f"Flows per second at {args.size}² (1 view, CPU time): the method's flow + NCC "
              f"confidence {ours:.1f}, a tracking edge's flows {edge:.1f}, OpenCV DIS "
              f"{params.dis_preset} preset alone {dis:.1f}.", ""]
    summary[f"{fam}/maps"] = {"blended": e_blend, "confidence_only": e_conf, "neutral": e_neutral,
                              "best_scan_per_frame": e_frame_best, "best_scan_per_texel": e_texel_best}


def _commit() -> str:
    import subprocess
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    global OUT
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("actors", nargs="*", default=[])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--frames", type=int, default=None,
                    help="the first N frames of the performance (default: all, 154 in a, 146 in b)")
    ap.add_argument("--rest-frames", type=int, default=REST_FRAMES,
                    help=f"frames of rest appended, the last pose held (default {REST_FRAMES})")
    ap.add_argument("--scans", type=int, default=5, help="training clips used as static scans")
    ap.add_argument("--no-monocular", action="store_true", help="skip the 1-view run (quick)")
    ap.add_argument("--speed-size", type=int, default=0, help="images of the speed rows, e.g. 512 (0: none)")
    ap.add_argument("--speed-frames", type=int, default=30, help="frames of the speed rows")
    ap.add_argument("--speed-only", action="store_true", help="only the speed rows")
    ap.add_argument("--out", type=Path, default=OUT, help=f"output directory (default {OUT})")
    args = ap.parse_args()
    OUT = args.out
    OUT.mkdir(parents=True, exist_ok=True)
    lines = ["# Performance-flow tracking report (fyffe, Digital Ira course 2014)", "",
             f"{args.frames or 'all'} frames of held-out_in_range + {args.rest_frames} of rest, "
             f"{args.size}² images, "
             f"neutral + {args.scans} scans; errors over the face vertices (region 0). Commit "
             f"{_commit()}, load average at the start {os.getloadavg()[0]:.1f}.", ""]
    summary: dict = {}
    actors = [Path(a) for a in args.actors] or [harness.sample_actor(f, 0) for f in ("a", "b")]
    for actor in actors:                   # the report is rewritten after every family
        if not args.speed_only:
            run_family(actor, args, lines, summary)
        if args.speed_size and actor is actors[0]:
            speed_rows(actor, args, lines, summary)
        (OUT / "report.md").write_text("\n".join(lines))
        (OUT / "report.json").write_text(json.dumps(summary, indent=1, default=float))
    print("\n".join(lines))


if __name__ == "__main__":
    main()

"""Pose-space detail report (bickel2008 §6.1-6.2): Fig. 4 study, held-out accuracy against the
thin shell, the nearest training frame and the PDM, transfer to a second identity, speed.

Usage: ``python benchmarks/pose_space_report.py ACTOR_DIR [ACTOR_DIR ...] [--target DIR]
[--quick] [--frames N] [--reuse] [--no-fig4] [--no-shape-space]``. Every actor directory has
the sample actor's layout (``neutral.npz``,
``markers.json``, ``performances/train_*.npz`` and ``heldout_*.npz`` with map frames), so any
actor family written that way can be reported. Output: ``benchmarks/out/pose_space/``
(``report.md``, ``report.json``, figures, models under ``models/``).

Per actor:

* **Fig. 4 study** — a 100-frame training sequence (100 frames evenly spaced over the
  ``train_*`` clips), the L2 (RMS) vertex error over the face region and the 100 frames, mm,
  against the basis size P = 1…20, for: *global blend shapes* (the P basis poses' meshes
  with convex weights matching the frame's features, §6.1: "our feature distance metric ...
  to find a convex combination of blend shapes"), *locally controlled blend shapes* (the
  basis meshes interpolated per vertex with the locally supported metric (3), §6.1), PSD and
  WPSD, each with exact interpolation of the P poses and least squares over the 100 frames.
  Basis poses by the greedy selection of §5.2 (λ = 0), per method and fit; the blend shapes
  use the WPSD sequences. The thin shell (P = 0) is the reference line. PSD and WPSD with
  their defaults: PSD eq. 2 as printed, WPSD with the local linear polynomial term
  (``service/methods/pose_space/polynomial.py``); one more series, WPSD (LSq) without it
  (eq. 5 as printed), shows what the term changes.
* **held-out accuracy** — the held-out performances *in range* (``heldout_in_range``),
  *combinations* (``heldout_combinations``: combinations no training clip shows) and *out of
  range* (``heldout_amplified``: every training expression 25–40 % beyond its peak) at their
  map frames, with clean markers, noisy markers and occluded markers: the actor's stored
  ``_noisy`` (σ = 0.3 mm per coordinate) and ``_occluded`` (NaN bursts) variants, as
  ``generalization_report.py``, or where an actor has none, our own (σ 0.3 mm / 10 % of the
  markers of every frame NaN, seeded). Methods: *thin shell* (no
  detail: the detailed neutral deformed to the markers), *nearest training frame* (its
  correction and fine map on the held-out shell), *PDM* (biquadratic, defaults; fine band at the training maps' size), *PSD* and
  *WPSD* (defaults: least squares, P = 12, smoothing by validation). Metrics exactly as
  ``benchmarks/pdm_report.py`` (its ``DetailTexels``, ``Scores``): vertex error |V − V_gt|
  over the face region (mean and max here), and the fine detail as high-passed detail
  heights at the face texels (Pearson r; relative error = RMS error / RMS of the ground
  truth's high-passed heights). Also the mean per-frame confidence of the pose-space models.
* **transfer** (``--target``) — the WPSD model transferred (§5.4) to a second identity with
  40 landmark pairs (farthest-point samples of the source's face vertices; both identities
  come from one rig, so vertex i corresponds — only these 40 pairs are given, the dense
  correspondence is computed), driven by the target's own markers, scored against the
  target's ground truth beside the target's thin shell and a WPSD trained on the target.
* **speed** (2 cores) — per-frame synthesis at the actor's level with P = 6 and P = 20, and
  of WPSD with the recommended marker regression (``--speed-models "WPSD,WPSD +
  regression"``: what the regression's sparse product adds; its entries counted in the
  storage columns)
  (``mesh``: large scale + fine scale + tangent frames; and with the displacement map),
  against scipy's ``RBFInterpolator`` doing the same interpolation in the same run (for PSD
  one interpolator over all 3n values; for WPSD one per vertex, timed on a vertex sample and
  scaled to n), training time, and stored floats/ints per vertex. CPU times are of every
  thread. The report runs with ``facesynth serve``'s BLAS threads (cores ÷ synthesis slots:
  1 on 2 cores, ``service/app/threads.py``; an ``OPENBLAS_NUM_THREADS`` in the environment
  is kept; the compiled per-frame kernels run on ``NUMBA_NUM_THREADS`` threads, sized with
  them). ``OPENBLAS_NUM_THREADS=2 NUMBA_NUM_THREADS=2`` in the environment measures one
  synthesis slot with both cores (the latency setting, ``FACESYNTH_MAX_CONCURRENT_SYNTHESES=1
  FACESYNTH_BLAS_THREADS=2``), written to ``report_speed_2x2threads.md``.
  (Before the compiled kernels the thin-shell basis product was an OpenBLAS GEMM, whose
  idle second thread spin-waited and billed its cycles to the synthesis: level 2, P = 6,
  mesh CPU 52-54 ms with 1 thread against 93 ms with 2, session 13.)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
OUT = ROOT / "benchmarks" / "out" / "pose_space"

from service.app.threads import apply_blas_threads  # noqa: E402

#: BLAS threads, set before NumPy loads: ``facesynth serve``'s sizing (cores ÷ synthesis
#: slots, 1 on 2 cores; an OPENBLAS_NUM_THREADS already set is kept), so the speed rows
#: measure a synthesis as the service runs it (module docstring: speed)
BLAS_THREADS = apply_blas_threads(None, None)

import numpy as np  # noqa: E402

import harness as pr  # noqa: E402  (the reports' shared data, metric and baselines)
from service.methods.pose_space.params import RECOMMENDED_MARKER_REGRESSION  # noqa: E402

#: WPSD as bickel2008 prints it (the rows named "WPSD" here; the service's default adds the
#: marker regression, issue 17: the "WPSD + regression" rows)
AS_PRINTED = {"marker_regression": None}

FIG4_FRAMES = 100
FIG4_MAX_P = 20
NOISE_MM = 0.3
OCCLUDED_FRACTION = 0.1
SEED = 7
SPEED_FRAMES = 20
SPEED_WARMUP = 2
#: held-out ranges and marker conditions: the sample actors' performances and their stored
#: marker variants (as benchmarks/generalization_report.py: σ 0.3 mm noise, NaN bursts)
RANGES = {"in range": "heldout_in_range", "combinations": "heldout_combinations",
          "out of range": "heldout_amplified"}
CONDITIONS = {"clean": "", "noisy": "_noisy", "occluded": "_occluded"}
WPSD_NO_POLY = "WPSD (LSq, eq. 5 as printed: no polynomial)"
SS_MARKERS = "shape space (markers)"


# --------------------------------------------------------------------------------------
# data

def heldout_names(actor_dir: Path) -> list[str]:
    """The actor's held-out performances of :data:`RANGES` (clean markers)."""
    return [p for p in RANGES.values() if (actor_dir / "performances" / f"{p}.npz").is_file()]


def perturb(markers: np.ndarray, condition: str, rng) -> np.ndarray:
    """Markers (k,M,3) under a condition: clean, noisy (σ 0.3 mm) or occluded (10 % NaN)."""
    m = markers.copy()
    if condition == "noisy":
        m += rng.normal(0.0, NOISE_MM, m.shape)
    elif condition == "occluded":
        k, M = m.shape[:2]
        for f in range(k):
            m[f, rng.choice(M, int(round(OCCLUDED_FRACTION * M)), replace=False)] = np.nan
    return m


def cached_model(path: Path, reuse: bool, build, load):
    """(model, training seconds): loaded from ``path`` with ``reuse``, else built and saved."""
    record = path.with_suffix(".train.json")
    if reuse and (path / "manifest.json").is_file() and record.is_file():
        return load(path), json.loads(record.read_text())["train_s"]
    t0 = time.perf_counter()
    model = build()
    seconds = time.perf_counter() - t0
    model.save(path)
    record.write_text(json.dumps({"train_s": seconds}))
    return model, seconds


# --------------------------------------------------------------------------------------
# Fig. 4

def fig4_study(actor, clips, max_p: int) -> dict:
    """L2 error over a 100-frame training sequence vs basis size (module docstring)."""
    from service.methods.pdm.base_surface import head_alignment, stability_weights
    from service.methods.pose_space import rbf
    from service.methods.pose_space.corrections import corrections, large_scale_surface
    from service.methods.pose_space.feature_graph import automatic_graph
    from service.methods.pose_space.model import (
        _even_sample, _phi, _poly, _targets, node_operator, select_basis, support)
    from service.methods.pose_space.params import PsdParams, WpsdParams
    from service.methods.pose_space.weighting import edge_weights
    from service.methods.shape_space.simplex_qp import simplex_least_squares

    markers = np.concatenate([c.markers for c in clips])
    V = np.concatenate([c.vertices for c in clips])
    pick = np.unique(np.linspace(0, len(markers) - 1, FIG4_FRAMES).round().astype(np.int64))
    markers, V = markers[pick], V[pick]
    T, n = len(markers), actor.n_vertices
    rest = actor.marker_positions()
    pose = head_alignment(markers, rest)
    pose = head_alignment(markers, rest, stability_weights(pose.remove(markers), rest))
    base = large_scale_surface(actor)
    u_H = base.handle_displacements(pose.remove(markers))
    aligned = pose.remove(V)
    C = corrections(base, u_H, aligned)                                       # (T,n,3)
    U = (aligned - actor.vertices).astype(np.float32)                         # blend-shape targets
    shell_sq = np.einsum("tvc,tvc->v", C[:, actor.regions[pr.FACE]], C[:, actor.regions[pr.FACE]], dtype=np.float64)
    graph = automatic_graph(actor.marker_uv(), rest)
    nodes = node_operator(actor.faces, actor.marker_triangle, actor.marker_barycentric, n)
    node_rest = nodes @ actor.vertices
    F = graph.features(node_rest + np.einsum("nm,fmd->fnd", np.asarray(nodes @ base.basis.astype(np.float64)), u_H))
    wp = WpsdParams(basis_size=max_p, smoothing=0.0, marker_regression=None)
    alpha = edge_weights(actor.vertices, node_rest, graph)
    first = int(np.argmin(np.linalg.norm(F, axis=1)))
    sample = _even_sample(n, wp.selection_vertices)
    sup = support(alpha, graph.n_edges, wp)                                   # WPSD's polynomial
    seq = {}
    for fit in ("exact", "least_squares"):
        p = wp.model_copy(update={"fit": fit})
        seq[("wpsd", fit)], _ = select_basis(F, _targets(C, sample, True), alpha[sample], p, 0.0, first,
                                             _poly(F, sup, sample))
        if fit == "least_squares":
            seq[("wpsd0", fit)], _ = select_basis(F, _targets(C, sample, True), alpha[sample], p, 0.0, first)
        K = np.zeros((T, T))
        for v0 in range(0, n, 4096):
            Cv = C[:, v0:v0 + 4096].reshape(T, -1).astype(np.float64)
            K += Cv @ Cv.T
        pp = PsdParams(basis_size=max_p, smoothing=0.0, fit=fit)
        seq[("psd", fit)], _ = select_basis(F, rbf.gram_factor(K)[None], None, pp, 0.0, first)
    face = np.flatnonzero(actor.regions[pr.FACE])
    count = T * len(face)
    sq = {k: np.zeros(max_p) for k in ("global blend shapes", "local blend shapes", "local blend shapes (LSq)",
                                       "PSD", "PSD (LSq)", "WPSD", "WPSD (LSq)", WPSD_NO_POLY)}
    # PSD: one system for all face vertices
    Cf = _targets(C, face, False)
    for fit, name in (("exact", "PSD"), ("least_squares", "PSD (LSq)")):
        sel = seq[("psd", fit)]
        Phi = _phi(F, F[sel], None)
        for P in range(1, len(sel) + 1):
            W = rbf.fit_basis(Phi[:, :, :P], Cf, sel[:P], 0.0, fit == "exact")
            sq[name][P - 1] = rbf.residual_sq(Phi[:, :, :P], Cf, W).sum()
    # WPSD and local blend shapes: per-vertex systems, vertex chunks
    for v0 in range(0, len(face), 2048):
        vs = face[v0:v0 + 2048]
        Dc, Du = _targets(C, vs, True), _targets(U, vs, True)
        for fit, name, bs in (("exact", "WPSD", "local blend shapes"),
                              ("least_squares", "WPSD (LSq)", "local blend shapes (LSq)")):
            sel = seq[("wpsd", fit)]
            Phi = _phi(F, F[sel], alpha[vs])
            Q = _poly(F, sup, vs)
            for P in range(1, len(sel) + 1):
                W = rbf.fit_basis(Phi[:, :, :P], Dc, sel[:P], 0.0, fit == "exact", Q)
                sq[name][P - 1] += rbf.residual_sq(rbf.columns(Phi[:, :, :P], Q), Dc, W).sum()
                W = rbf.fit_basis(Phi[:, :, :P], Du, sel[:P], 0.0, fit == "exact")   # blend shapes
                sq[bs][P - 1] += rbf.residual_sq(Phi[:, :, :P], Du, W).sum()
        sel = seq[("wpsd0", "least_squares")]
        Phi = _phi(F, F[sel], alpha[vs])
        for P in range(1, len(sel) + 1):
            W = rbf.fit_basis(Phi[:, :, :P], Dc, sel[:P], 0.0, False)
            sq[WPSD_NO_POLY][P - 1] += rbf.residual_sq(Phi[:, :, :P], Dc, W).sum()
    # global blend shapes: convex weights matching the features, the basis meshes blended
    sel = seq[("wpsd", "least_squares")]
    Uf = U[:, face].astype(np.float64)
    for P in range(1, len(sel) + 1):
        Fb = F[sel[:P]].T                                                     # (E,P)
        Wc = np.stack([simplex_least_squares(Fb, F[t]).w for t in range(T)])   # (T,P)
        R = Uf - np.einsum("tp,pvc->tvc", Wc, Uf[sel[:P]])
        sq["global blend shapes"][P - 1] = float(np.einsum("tvc,tvc->", R, R))
    return {"P": list(range(1, max_p + 1)), "frames": T,
            "rms_mm": {k: np.sqrt(v / count).tolist() for k, v in sq.items()},
            "thin_shell_rms_mm": float(np.sqrt(shell_sq.sum() / count)),
            "basis": {f"{m} {f}": [int(pick[j]) for j in s] for (m, f), s in seq.items()}}


def plot_fig4(study: dict, path: Path, title: str) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 5.2), layout="constrained")
    style = {"global blend shapes": ("#7f7f7f", "-"), "local blend shapes": ("#bcbd22", "-"),
             "local blend shapes (LSq)": ("#bcbd22", "--"), "PSD": ("#1f77b4", "-"),
             "PSD (LSq)": ("#1f77b4", "--"), "WPSD": ("#d62728", "-"), "WPSD (LSq)": ("#d62728", "--"),
             WPSD_NO_POLY: ("#ff9896", ":")}
    for name, rms in study["rms_mm"].items():
        c, ls = style[name]
        ax.plot(study["P"], rms, ls, color=c, marker="o", ms=3, label=name)
    ax.axhline(study["thin_shell_rms_mm"], color="k", lw=0.8, ls=":", label="thin shell only (P = 0)")
    ax.set_yscale("log")
    ax.set_xlabel("basis size P (example poses)")
    ax.set_ylabel(f"L2 (RMS) vertex error over the face, {study['frames']} training frames, mm")
    ax.set_xticks(study["P"])
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------------------
# held-out accuracy

def pose_space_prediction(model, markers, tex):
    out = model.synthesize(markers, ("mesh", "displacement"))
    return out["vertices"].astype(np.float64), tex.texels(out["displacement"]), out["confidence"]


def evaluate(gt, methods: dict, tex, actor) -> dict:
    """Scores of every method (name → callable(markers) → (V, d, confidence|None)) on the
    held-out frames ``gt`` (a ``pdm_report.Heldout``): pdm_report's metric, plus the max."""
    normals = tex.normals(gt.medium, actor.faces)
    gt_hp = np.stack([tex.highpass(tex.texels(d)) for d in gt.displacement])
    signal = float(np.sqrt(np.mean(gt_hp[:, tex.face] ** 2)))
    out = {"signal_rms_mm": signal, "methods": {}}
    for name, method in methods.items():
        V, D, conf = method(gt.markers)
        acc = pr.Scores(np.asarray(actor.regions[pr.FACE]), tex.face)
        for f in range(len(gt.frames)):
            err = np.linalg.norm(V[f] - gt.vertices[f], axis=-1)
            hp = tex.highpass(tex.heights(V[f], gt.medium[f], normals[f], None if D is None else D[f]))
            acc.add(err, hp, gt_hp[f])
        r = acc.result()
        r["max_mm"] = float(np.concatenate(acc.vertex_errors).max())
        r["fine_rel"] = r["fine_rms_mm"] / signal
        r["confidence"] = None if conf is None else float(np.mean(conf))
        out["methods"][name] = r
    return out


def shell_method(model):
    """No detail: the model's own shell of the detailed neutral, fine map 0."""
    def run(markers):
        ev = model.evaluator
        pose, u = ev.deformation(markers)
        return pose.restore(ev.base.deform(u)), None, None
    return run


# --------------------------------------------------------------------------------------
# speed

def speed(model, markers: np.ndarray) -> dict:
    """Median ms per frame (one frame per call) of ``mesh`` and ``mesh + displacement``, and the
    same interpolation by scipy's RBFInterpolator (module docstring)."""
    from scipy.interpolate import RBFInterpolator

    res = {}
    for outs in (("mesh",), ("mesh", "displacement")):
        for f in range(SPEED_WARMUP):
            model.synthesize(markers[f:f + 1], outs)
        t, cpu = [], []
        for f in range(SPEED_WARMUP, len(markers)):
            t0, c0 = time.perf_counter(), time.process_time()
            model.synthesize(markers[f:f + 1], outs)
            t.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        res["+".join(outs)] = 1e3 * float(np.median(t))
        res["+".join(outs) + " cpu"] = 1e3 * float(np.median(cpu))      # CPU time (all threads)
    from service.methods.pose_space import polynomial

    ev, d = model.evaluator, model.data
    poly = ((lambda f: polynomial.evaluate(d.poly_const, ev.poly_linear, f)) if ev.poly_linear is not None
            else (lambda f: 0.0))
    _, u = ev.deformation(markers)
    feats = ev.features(u)
    # ours: the fine-scale evaluation alone (distances + weighted sum), per frame, as synthesize
    # runs it (WPSD: the compiled float32 sum; PSD: NumPy)
    fine = ((lambda f: ev.correction_sum(f)) if ev.correction_sum is not None
            else (lambda f: ev.corrections(ev.sq_distances(f[None]), f[None])))
    t, cpu = [], []
    for f in feats[SPEED_WARMUP:]:
        t0, c0 = time.perf_counter(), time.process_time()
        fine(f)
        t.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    res["ours_fine_ms"] = 1e3 * float(np.median(t))
    res["ours_fine_cpu_ms"] = 1e3 * float(np.median(cpu))
    fb = d.basis_features
    kern = lambda f: ev.corrections(ev.sq_distances(f), f) - poly(f)          # the RBF sum alone
    values = kern(fb)                                                          # (P,n,3) at the centres
    n = d.n_vertices
    if ev.alpha is None:
        interp = RBFInterpolator(fb, values.reshape(len(fb), -1), kernel="linear", degree=-1)
        t = []
        for f in feats[SPEED_WARMUP:]:
            t0 = time.perf_counter()
            got = interp(f[None])
            t.append(time.perf_counter() - t0)
        res["scipy_fine_ms"] = 1e3 * float(np.median(t))
        res["scipy_max_diff_mm"] = float(np.abs(got.reshape(n, 3) - kern(feats[-1:])[0]).max())
        res["scipy_vertices_timed"] = n
    else:
        # one interpolator per vertex in the scaled features sqrt(α_v)·f (Euclidean = eq. 3)
        k = 200
        vs = np.linspace(0, n - 1, k).round().astype(np.int64)
        A = ev.alpha
        interps = []
        for v in vs:
            row = A[v]
            s = np.sqrt(row.data)
            interps.append((row.indices, s, RBFInterpolator(fb[:, row.indices] * s, values[:, v],
                                                            kernel="linear", degree=-1)))
        t, cpu = [], []
        for f in feats[SPEED_WARMUP:SPEED_WARMUP + 5]:
            t0, c0 = time.perf_counter(), time.process_time()
            got = [it(f[idx][None] * s) for idx, s, it in interps]
            t.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        res["scipy_fine_ms"] = 1e3 * float(np.median(t)) * n / k
        res["scipy_fine_cpu_ms"] = 1e3 * float(np.median(cpu)) * n / k
        mine = kern(feats[SPEED_WARMUP + 4:SPEED_WARMUP + 5])[0][vs]
        res["scipy_max_diff_mm"] = float(np.abs(np.concatenate(got) - mine).max())
        res["scipy_vertices_timed"] = k
    res["ratio_scipy_over_ours"] = res["scipy_fine_ms"] / res["ours_fine_ms"]
    return res


def storage(model) -> dict:
    """Floats and ints per vertex that one frame's evaluation reads (the shell's basis row, the
    RBF weights, the correction sum's entries — α and the polynomial's coefficients on one
    pattern, WPSD — the polynomial's constant, the rest position, the marker regression's
    entries and its mean offset), and per map texel."""
    d, cs = model.data, model.evaluator.correction_sum
    n, P, M = d.n_vertices, d.basis_size, d.n_markers
    entries = 0.0 if cs is None else len(cs.edge) / n
    poly = cs is not None and len(cs.const) > 0
    reg = 0.0 if d.regression is None else d.regression.P.size / n   # its P (3n,r); Q is per model
    floats = M + 3 * P + 4 * entries + (3 if poly else 0) + 3 + (reg + 3 if reg else 0)
    return {"floats_per_vertex": floats, "ints_per_vertex": entries,
            "floats_per_texel": P if d.map_resolution else 0,
            "texels_per_vertex": len(d.map_index) / n,
            "layout": f"B row {M} + weights 3P = {3 * P}"
                      + (f" + α and polynomial 4 × {entries:.1f} entries" if cs is not None else "")
                      + (" + polynomial constant 3" if poly else "") + " + rest position 3"
                      + (f" + marker regression 3r = {reg:.0f} (its P) + its mean 3" if reg else "")
                      + (f"; ints: the entries' edges {entries:.1f}" if cs is not None else "")}


# --------------------------------------------------------------------------------------

def identity_overlap(source_dir: Path, target_dir: Path, tex) -> dict:
    """How much of the target's own detail any transfer could reproduce (§5.4 transfers the
    *source's* detail): per training clip both identities have, the Pearson r over the
    target's face texels (high-passed as the metric) between the two identities' maps of the
    neutral frame (static detail: pores, creases) and of the peak frame minus the neutral
    (the expression's wrinkles). Both identities come from one rig, so their UV layouts agree."""
    from service.samples.dataset import performance_names

    def maps(d: Path, name: str):
        with np.load(d / "performances" / f"{name}.npz") as z:
            w = z["weights"][z["map_frames"]].sum(axis=1)
            D = z["displacement"]
            return tex.highpass(tex.texels(D[0])), tex.highpass(tex.texels(D[int(np.argmax(w))]))

    out = {}
    common = sorted(set(performance_names(source_dir, "train_")) & set(performance_names(target_dir, "train_")))
    for name in common:
        (s0, sp_), (t0, tp) = maps(source_dir, name), maps(target_dir, name)
        f = tex.face
        out[name] = {"static_r": float(np.corrcoef(s0[f], t0[f])[0, 1]),
                     "wrinkle_r": float(np.corrcoef((sp_ - s0)[f], (tp - t0)[f])[0, 1])}
    return out


def speed_markers(actor_dir: Path) -> np.ndarray:
    """The markers (SPEED_WARMUP + SPEED_FRAMES, M, 3) the speed section evaluates: the first
    held-out performance's first frames, or, for an actor built with training clips only (a
    level-2 speed actor), frames spread over its training clips."""
    from service.samples.dataset import performance_names

    k = SPEED_WARMUP + SPEED_FRAMES
    held = heldout_names(actor_dir)
    if held:
        with np.load(actor_dir / "performances" / f"{held[0]}.npz") as d:
            return d["markers"][:k].astype(np.float64)
    mk = []
    for name in performance_names(actor_dir, "train_"):
        with np.load(actor_dir / "performances" / f"{name}.npz") as d:
            mk.append(d["markers"].astype(np.float64))
    mk = np.concatenate(mk)
    return mk[np.linspace(0, len(mk) - 1, k).round().astype(np.int64)]


SPEED_MODELS = {"PSD": {}, "WPSD": AS_PRINTED, "WPSD P=6": {"basis_size": 6, **AS_PRINTED},
                "WPSD P=20": {"basis_size": 20, **AS_PRINTED},
                "WPSD + regression": {"marker_regression": RECOMMENDED_MARKER_REGRESSION}}


def run_speed(actor_dir: Path, train_missing: bool = False, labels: list[str] | None = None) -> dict:
    """Only the speed section, with the models a previous run saved (``--speed-only``), or
    with ``train_missing`` those of :data:`SPEED_MODELS` not saved yet trained first (defaults,
    ``map_resolution`` as the clips)."""
    from service.methods.pose_space import PoseSpaceModel, PsdParams, WpsdParams, train
    from service.samples.dataset import load_actor

    models = OUT / "models" / actor_dir.name
    models.mkdir(parents=True, exist_ok=True)
    mk = speed_markers(actor_dir)
    out = {}
    actor = clips = None
    for label in labels or SPEED_MODELS:
        path = models / label.replace(" ", "_").replace("=", "")
        if train_missing and not (path / "manifest.json").is_file():
            if clips is None:
                actor = load_actor(actor_dir)
                clips = pr.training_clips(actor_dir, actor)
            cls = PsdParams if label == "PSD" else WpsdParams
            print(f"[{actor_dir.name}] training {label} for the speed section", file=sys.stderr, flush=True)
            cached_model(path, False, lambda: train(actor, clips, cls(**SPEED_MODELS[label])), PoseSpaceModel.load)
        if (path / "manifest.json").is_file():
            model = PoseSpaceModel.load(path)
            out[label] = speed(model, mk)
            out[label].update(storage(model), basis_size=model.data.basis_size,
                              train_s=json.loads(path.with_suffix(".train.json").read_text())["train_s"],
                              n_vertices=model.data.n_vertices, map_resolution=model.data.map_resolution,
                              training_frames=model.metrics["training_frames"])
    return out


def shape_space_method(model, tex):
    """bermano2014 shape space driven by the markers (its database's detail blended), scored
    at the report's map size (its fine maps box-filtered down if larger)."""
    def run(markers):
        out = model.enhance(markers, pr.SS_OUTPUTS, input_kind="markers")
        D = out.get("fine_displacement")
        if D is None:
            return out["vertices"].astype(np.float64), None, None
        k = D.shape[-1] // tex.H
        if k > 1:
            D = D.reshape(len(D), tex.H, k, tex.H, k).mean(axis=(2, 4))
        return out["vertices"].astype(np.float64), np.stack([tex.texels(m) for m in D]), None
    return run


def run_actor(actor_dir: Path, target_dir: Path | None, quick: bool, reuse: bool, fig4: bool = True,
              only: list[str] | None = None, shape_space: bool = True, frames: int | None = None) -> dict:
    """One actor's sections (module docstring); ``frames``: held-out map frames per
    performance, evenly spaced (None: all; ``quick``: 6)."""
    from service.methods.pdm.model import PdmModel, PdmParams, train as pdm_train
    from service.methods.shape_space import ShapeSpaceModel, ShapeSpaceParams
    from service.methods.pose_space import PoseSpaceModel, PsdParams, WpsdParams, train
    from service.methods.pose_space.transfer import transfer
    from service.samples.dataset import load_actor

    name = actor_dir.name
    frames = 6 if quick and frames is None else frames
    models = OUT / "models" / name
    models.mkdir(parents=True, exist_ok=True)
    actor = load_actor(actor_dir)
    clips = pr.training_clips(actor_dir, actor)
    res = {"actor": str(actor_dir), "vertices": actor.n_vertices, "markers": actor.n_markers,
           "train_frames": sum(c.frames for c in clips), "train_clips": len(clips)}
    log = lambda msg: print(f"[{name}] {msg}", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    cache = models / f"fig4{'_quick' if quick else ''}.json"
    if fig4 and reuse and cache.is_file():
        res["fig4"] = json.loads(cache.read_text())
    elif fig4:
        log("Fig. 4 study")
        res["fig4"] = fig4_study(actor, clips, 8 if quick else FIG4_MAX_P)
        res["fig4"]["seconds"] = time.perf_counter() - t0
        cache.write_text(json.dumps(res["fig4"]))
    if fig4:
        plot_fig4(res["fig4"], OUT / f"fig4_{name}.png",
                  f"bickel2008 Fig. 4 on {name}: L2 error over a {res['fig4']['frames']}-frame training sequence")

    log("training")
    train_s = {}
    pdm, train_s["PDM biquadratic"] = cached_model(models / "pdm", reuse, lambda: pdm_train(actor, clips, PdmParams(
        fine_resolution=clips[0].displacement.shape[1])),
                                                   PdmModel.load)
    variants = {"PSD": PsdParams(), "WPSD": WpsdParams(**AS_PRINTED),
                "WPSD P=6": WpsdParams(basis_size=6, **AS_PRINTED), "WPSD P=20": WpsdParams(basis_size=20, **AS_PRINTED)}
    if quick:
        variants = {"PSD": PsdParams(), "WPSD": WpsdParams(**AS_PRINTED)}
    if only:
        variants = {k: v for k, v in variants.items() if k in only}
    ps = {}
    for label, params in variants.items():
        log(f"  {label}")
        ps[label], train_s[label] = cached_model(models / label.replace(" ", "_").replace("=", ""), reuse,
                                                 lambda p=params: train(actor, clips, p), PoseSpaceModel.load)
    res["train_s"] = train_s
    res["fit"] = {k: {kk: m.metrics[kk] for kk in ("basis_size", "smoothing", "validation", "correction_fit_rms_mm",
                                                  "correction_signal_rms_mm", "map_fit_rms_mm", "map_signal_rms_mm",
                                                  "feature_edges", "alpha_nonzero_per_vertex", "basis")}
                  for k, m in ps.items()}

    log("held-out accuracy")
    sigma = pdm.metrics["highpass_sigma_texels"]
    tex = pr.DetailTexels.build(actor, pdm.data.fine.resolution, sigma)
    baselines = pr.Baselines.build(actor, clips, pdm, tex)
    methods = {
        "thin shell (no detail)": lambda m: baselines.no_detail(m)[:2] + (None,),
        "nearest training frame": lambda m: baselines.nearest(m)[:2] + (None,),
        "PDM biquadratic": lambda m: pr.pdm_prediction(pdm, m, tex)[:2] + (None,),
    }
    for label in ("PSD", "WPSD", "WPSD P=20"):          # the scored pose-space models that were trained
        if label in ps:
            methods[label] = lambda m, model=ps[label]: pose_space_prediction(model, m, tex)
    if shape_space:
        log("shape space (markers)")
        ss_dir, ss_rec = pr.shape_space_model(actor_dir, ShapeSpaceParams(), False)
        train_s[SS_MARKERS] = ss_rec["train_s"]
        methods[SS_MARKERS] = shape_space_method(ShapeSpaceModel.load(ss_dir), tex)
    res["heldout"] = {}
    for rname, perf in RANGES.items():
        if not (actor_dir / "performances" / f"{perf}.npz").is_file():
            continue
        gt = pr.load_heldout(actor_dir, perf, frames)
        clean = gt.markers
        for cond, suffix in CONDITIONS.items():
            variant = actor_dir / "performances" / f"{perf}{suffix}.npz"
            if suffix and variant.is_file():       # the actor's stored marker variant
                with np.load(variant) as z:
                    gt.markers = z["markers"][gt.frames].astype(np.float64)
            else:                                  # or our own (σ 0.3 mm / 10 % NaN, seeded)
                gt.markers = perturb(clean, cond, np.random.default_rng(SEED))
            log(f"  {rname} / {cond}")
            key = f"{rname} / {cond}"
            res["heldout"][key] = evaluate(gt, methods, tex, actor)
            res["heldout"][key]["frames"] = len(gt.frames)
            res["heldout"][key]["performance"] = perf + suffix
        gt.markers = clean
    del baselines

    if target_dir is not None:
        log("transfer")
        target = load_actor(target_dir)
        lm = pr.face_landmarks(actor)
        t0 = time.perf_counter()
        moved = transfer(ps["WPSD"], target, np.stack([lm, lm], axis=1))
        transfer_s = time.perf_counter() - t0
        tclips = pr.training_clips(target_dir, target)
        own, own_s = cached_model(models / f"target_{target_dir.name}_WPSD", reuse,
                                  lambda: train(target, tclips, WpsdParams(**AS_PRINTED)), PoseSpaceModel.load)
        del tclips
        ttex = pr.DetailTexels.build(target, moved.data.map_resolution, sigma)
        tmethods = {"thin shell (no detail)": shell_method(own),
                    "WPSD transferred from " + name: lambda m: pose_space_prediction(moved, m, ttex),
                    "WPSD trained on the target": lambda m: pose_space_prediction(own, m, ttex)}
        res["transfer"] = {"target": str(target_dir), "landmarks": pr.LANDMARKS, "seconds": transfer_s,
                           "target_train_s": own_s, "correspondence": moved.metrics["transfer"], "scores": {}}
        res["transfer"]["identity_overlap"] = identity_overlap(actor_dir, target_dir, ttex)
        for perf in heldout_names(target_dir):
            gt = pr.load_heldout(target_dir, perf, frames)
            log(f"  target {perf}")
            res["transfer"]["scores"][perf] = evaluate(gt, tmethods, ttex, target)
            res["transfer"]["scores"][perf]["frames"] = len(gt.frames)

    log("speed")
    mk = speed_markers(actor_dir)
    res["speed"] = {}
    for label in ("PSD", "WPSD", "WPSD P=6", "WPSD P=20"):
        if label in ps:
            res["speed"][label] = speed(ps[label], mk)
            res["speed"][label].update(storage(ps[label]), basis_size=ps[label].data.basis_size,
                                       train_s=train_s[label])
    return res


# --------------------------------------------------------------------------------------
# the report

def _f(x, d=3):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.{d}f}"


def report(results: list[dict], meta: dict) -> str:
    L = ["# Pose-space detail report (bickel2008 §6): Fig. 4, held-out accuracy, transfer, speed", "",
         f"{meta['cpus']} CPU cores, load average {meta['load_before']} before / {meta['load_after']} after; "
         f"{meta['git']}." + (" **--quick** run." if meta["quick"] else ""), ""]
    for r in results:
        name = Path(r["actor"]).name
        L += [f"## {name}", "",
              f"{r['actor']}: {r['vertices']:,} vertices, {r['markers']} markers, "
              f"{r['train_frames']} training frames in {r['train_clips']} clips.", ""]
        if "fig4" in r:
            L += ["### Fig. 4: L2 error over the training sequence vs basis size", "",
                  f"RMS vertex error (mm) over the face region and the {r['fig4']['frames']} frames of the "
                  f"training sequence; thin shell alone {r['fig4']['thin_shell_rms_mm']:.4f} mm. "
                  f"![Fig. 4](fig4_{name}.png)", ""]
            names = list(r["fig4"]["rms_mm"])
            L += ["| P | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
            for i, P in enumerate(r["fig4"]["P"]):
                vals = [r["fig4"]["rms_mm"][k][i] for k in names]
                best = int(np.argmin(vals))
                L.append(f"| {P} | " + " | ".join(("**%.4f**" if j == best else "%.4f") % v
                                                 for j, v in enumerate(vals)) + " |")
            P_, rms_ = r["fig4"]["P"], r["fig4"]["rms_mm"]
            lowest = [P for i, P in enumerate(P_) if min(rms_, key=lambda k: rms_[k][i]).startswith("WPSD")]
            L += ["", f"WPSD (either fit) lowest at P = {', '.join(map(str, lowest)) or 'none'} "
                  f"(of {P_[0]}–{P_[-1]})."]
        L += ["", "### Held-out performances", "",
              "Vertex error |V − V_gt| over the face region (mean, max, mm); fine detail: high-passed "
              "detail heights at the face texels (pdm_report's metric): Pearson r and relative error "
              "(RMS error / RMS of the ground truth's high-passed detail). Confidence: mean per-frame "
              "confidence of the pose-space models.", "",
              "| performance / markers | frames | method | mean mm | max mm | p95 mm | fine r | fine rel. err | confidence |",
              "|---|---|---|---|---|---|---|---|---|"]
        for key, ev in r["heldout"].items():
            for m, s in ev["methods"].items():
                L.append(f"| {key} | {ev['frames']} | {m} | {_f(s['medium_mean_mm'])} | {_f(s['max_mm'], 2)} | "
                         f"{_f(s['medium_p95_mm'])} | {_f(s['fine_r'])} | {_f(s['fine_rel'])} | {_f(s['confidence'], 3)} |")
        L += ["", "Claims checked on every row (WPSD = the default WPSD model):", ""]
        for key, ev in r["heldout"].items():
            mm = ev["methods"]
            w = mm["WPSD"]
            checks = [f"fine rel. err below the nearest frame: {'yes' if w['fine_rel'] < mm['nearest training frame']['fine_rel'] else 'NO'}",
                      f"below the PDM: {'yes' if w['fine_rel'] < mm['PDM biquadratic']['fine_rel'] else 'NO'}",
                      f"max error ≤ the thin shell's: {'yes' if w['max_mm'] <= mm['thin shell (no detail)']['max_mm'] else 'NO'}"]
            L.append(f"- {key}: " + "; ".join(checks))
        L += ["", "### Training", "", "| model | training s | P | smoothing λ | correction fit RMS mm (face) | "
              "correction signal RMS mm (face) | map fit / signal RMS mm | α per vertex |", "|---|---|---|---|---|---|---|---|"]
        for k, f in r["fit"].items():
            L.append(f"| {k} | {r['train_s'][k]:.1f} | {f['basis_size']} | {f['smoothing']:g} | "
                     f"{f['correction_fit_rms_mm'][pr.FACE]:.4f} | {f['correction_signal_rms_mm'][pr.FACE]:.4f} | "
                     f"{_f(f['map_fit_rms_mm'], 4)} / {_f(f['map_signal_rms_mm'], 4)} | {_f(f['alpha_nonzero_per_vertex'], 1)} |")
        L.append(f"| PDM biquadratic | {r['train_s']['PDM biquadratic']:.1f} | | | | | | |")
        L += ["", "Smoothing validation (held-out every 4th training frame, their markers with 0.3 mm noise; "
              "RMS correction error, mm, on the selection vertices):", ""]
        for k, f in r["fit"].items():
            if f["validation"]:
                L.append(f"- {k}: " + ", ".join(f"λ={v['smoothing']:g}: {v['rms']:.4f}" for v in f["validation"])
                         + f" → **{f['smoothing']:g}**")
        if "transfer" in r:
            t = r["transfer"]
            c = t["correspondence"]
            L += ["", f"### Transfer to {Path(t['target']).name}", "",
                  f"{t['landmarks']} landmark pairs; transfer {t['seconds']:.1f} s; projection distance of the "
                  f"target vertices onto the fitted source mean {c['projection_mean_mm']:.3f} / p95 "
                  f"{c['projection_p95_mm']:.3f} / max {c['projection_max_mm']:.2f} mm; landmark RMS after the "
                  f"rigid pre-alignment {c['landmark_rms_after_rigid_mm']:.2f} mm. The target's own WPSD "
                  f"trained in {t['target_train_s']:.0f} s.", "",
                  "| performance | frames | method | mean mm | max mm | fine r | fine rel. err | confidence |",
                  "|---|---|---|---|---|---|---|---|"]
            for perf, ev in t["scores"].items():
                for m, s in ev["methods"].items():
                    L.append(f"| {perf} | {ev['frames']} | {m} | {_f(s['medium_mean_mm'])} | {_f(s['max_mm'], 2)} | "
                             f"{_f(s['fine_r'])} | {_f(s['fine_rel'])} | {_f(s['confidence'])} |")
            ov = t.get("identity_overlap") or {}
            if ov:
                L += ["", "What a transfer can reach: Pearson r between the source's and the target's own "
                      "maps (high-passed, target face texels) of the same training clip — the neutral frame "
                      "(static detail) and peak − neutral (the expression's wrinkles):", "",
                      "| clip | static r | wrinkle r |", "|---|---|---|"]
                L += [f"| {k} | {v['static_r']:.3f} | {v['wrinkle_r']:.3f} |" for k, v in ov.items()]
        L += ["", f"### Speed ({meta['cpus']} cores, {BLAS_THREADS} BLAS thread(s), one frame per call, median of {SPEED_FRAMES})", "",
              "| model | P | mesh ms/frame | mesh + displacement ms/frame | fine-scale eval ms | scipy RBFInterpolator ms "
              "(same interpolation) | scipy / ours | scipy max diff mm | training s | floats / ints per vertex |",
              "|---|---|---|---|---|---|---|---|---|---|"]
        for k, s in r["speed"].items():
            L.append(f"| {k} | {s['basis_size']} | {s['mesh']:.1f} | {s['mesh+displacement']:.1f} | {s['ours_fine_ms']:.2f} | "
                     f"{s['scipy_fine_ms']:.1f}{' (est. from %d vertices)' % s['scipy_vertices_timed'] if k != 'PSD' else ''} | "
                     f"{s['ratio_scipy_over_ours']:.1f}× | {s['scipy_max_diff_mm']:.1e} | {s['train_s']:.0f} | "
                     f"{s['floats_per_vertex']:.0f} / {s['ints_per_vertex']:.0f} |")
        L += ["", "Stored per vertex: " + "; ".join(f"{k}: {s['layout']}" for k, s in r["speed"].items())
              + f". Plus per map texel P floats ({r['speed'][next(iter(r['speed']))]['texels_per_vertex']:.1f} "
              "texels per vertex). The paper: 137 floats and 24 ints per vertex (H = 89, P = 6).", ""]
    return "\n".join(L) + "\n"


def main() -> None:
    global OUT
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("actors", nargs="+", type=Path, help="actor directories (sample-actor layout)")
    parser.add_argument("--target", type=Path, help="second identity of the first actor's rig (another seed) for "
                        "the transfer of the first actor's WPSD (sample-actor layout)")
    parser.add_argument("--quick", action="store_true", help="6 held-out frames, P ≤ 8, two models")
    parser.add_argument("--reuse", action="store_true", help="reuse models saved under benchmarks/out/pose_space/models")
    parser.add_argument("--speed-only", action="store_true",
                        help="only the speed section, with the models of a previous run (report_speed.md)")
    parser.add_argument("--train-missing", action="store_true",
                        help="with --speed-only: train the speed section's models that are not saved yet")
    parser.add_argument("--speed-models", help="with --speed-only: comma-separated labels of SPEED_MODELS "
                        f"(default all: {', '.join(SPEED_MODELS)})")
    parser.add_argument("--no-fig4", action="store_true", help="skip the Fig. 4 study")
    parser.add_argument("--frames", type=int, help="held-out map frames per performance, evenly spaced "
                        "(default all; --quick 6)")
    parser.add_argument("--no-shape-space", action="store_true",
                        help="skip the shape-space (marker input) rows (its model is built from the "
                             "actor's database in a fresh process, cached under benchmarks/out/shape_space)")
    parser.add_argument("--models", help="comma-separated pose-space models to train and score "
                        "(default PSD, WPSD, WPSD P=6, WPSD P=20)")
    parser.add_argument("--out", type=Path, help="output directory (default benchmarks/out/pose_space)")
    args = parser.parse_args()
    OUT = args.out.resolve() if args.out else OUT
    OUT.mkdir(parents=True, exist_ok=True)
    if args.speed_only:
        labels = None
        if args.speed_models:
            labels = [x.strip() for x in args.speed_models.split(",")]
            unknown = set(labels) - set(SPEED_MODELS)
            if unknown:
                parser.error(f"unknown --speed-models {sorted(unknown)}; known: {list(SPEED_MODELS)}")
        res = {a.name: run_speed(a.resolve(), args.train_missing, labels) for a in args.actors}
        threads = int(os.environ["OPENBLAS_NUM_THREADS"]), int(os.environ["NUMBA_NUM_THREADS"])
        lines = [f"# Pose-space speed ({os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}, "
                 f"{threads[0]} BLAS thread(s), {threads[1]} kernel thread(s))", ""]
        for name, sp_ in res.items():
            first = next(iter(sp_.values()), {})
            lines += [f"## {name}", "", f"{first.get('n_vertices', 0):,} vertices, {first.get('map_resolution', 0)}² "
                      f"map, trained on {first.get('training_frames', 0)} frames.", "", "| model | P | mesh ms/frame | mesh + displacement ms/frame | fine-scale eval ms | "
                      "scipy RBFInterpolator ms | scipy / ours | scipy max diff mm | training s | floats / ints per vertex | "
                      "mesh CPU ms/frame | fine-scale CPU ms | scipy CPU ms |",
                      "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
            for k, s_ in sp_.items():
                lines.append(f"| {k} | {s_['basis_size']} | {s_['mesh']:.1f} | {s_['mesh+displacement']:.1f} | "
                             f"{s_['ours_fine_ms']:.2f} | {s_['scipy_fine_ms']:.1f} | {s_['ratio_scipy_over_ours']:.1f}× | "
                             f"{s_['scipy_max_diff_mm']:.1e} | {s_['train_s']:.0f} | {s_['floats_per_vertex']:.0f} / "
                             f"{s_['ints_per_vertex']:.0f} | {s_.get('mesh cpu', float('nan')):.1f} | "
                             f"{s_.get('ours_fine_cpu_ms', float('nan')):.2f} | {s_.get('scipy_fine_cpu_ms', float('nan')):.1f} |")
            lines.append("")
        stem = "report_speed" + ("" if threads == (BLAS_THREADS, BLAS_THREADS) else f"_{threads[0]}x{threads[1]}threads")
        (OUT / f"{stem}.md").write_text("\n".join(lines))
        (OUT / f"{stem}.json").write_text(json.dumps(res, indent=1))
        print("\n".join(lines))
        return
    t0 = time.perf_counter()
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    meta = {"cpus": os.cpu_count(), "load_before": f"{os.getloadavg()[0]:.1f}", "git": f"commit {git}",
            "quick": args.quick}
    # the transfer's landmark pairs are vertex i ↔ vertex i (one rig): only the first actor's
    results = [run_actor(a.resolve(), args.target.resolve() if args.target and i == 0 else None, args.quick,
                         args.reuse, not args.no_fig4, args.models and [x.strip() for x in args.models.split(",")],
                         not args.no_shape_space, args.frames)
               for i, a in enumerate(args.actors)]
    meta["load_after"] = f"{os.getloadavg()[0]:.1f}"
    text = report(results, meta) + f"\nTotal run {time.perf_counter() - t0:.0f} s.\n"
    (OUT / "report.md").write_text(text)
    (OUT / "report.json").write_text(json.dumps(results, indent=1, default=float))
    print(text)


if __name__ == "__main__":
    main()

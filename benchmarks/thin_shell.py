"""Thin-shell speed benchmark (bickel2008 §4): 150 markers → large-scale face deformation.

Per frame, the displacements of all vertices of the sample actor's neutral (level 1:
44,786 vertices, level 2: 178,726) are computed from 150 marker displacements by

  (a) the precomputed basis, ``u = B @ u_H`` (float64 and float32 storage; one frame at a
      time and a batch of 30 frames as one GEMM),
  (b) the prefactored sparse solve (:class:`ThinShellSolver.deform`),
  (c) libigl's ``igl.harmonic(V, F, b, bc, k=2)``, which rebuilds and refactors the
      bi-Laplacian system for every call (the peer re-solving per frame).

libigl's k=2 is the pure bi-Laplacian ``L M⁻¹ L`` with Voronoi mass, i.e. our ``ks=0``; as
an accuracy check our solver with ``ks=0, kb=1`` is compared with igl on one frame.

Memory: every method runs in a **fresh subprocess** that first loads the mesh (a small
.npz written by the parent) and imports everything, then resets the kernel's resident-set
high-water mark (``echo 5 > /proc/self/clear_refs``) and reports ``VmHWM − VmRSS`` at the
reset: the peak resident memory the method added, including C/C++ allocations (SuperLU's
factor, Eigen inside libigl, OpenBLAS buffers) that ``tracemalloc`` cannot see.
``tracemalloc``'s peak (NumPy buffers and Python objects only) is reported beside it,
measured in a **second, separate** fresh process per method: tracing every allocation
slows the timed loops (+35–50 % on the float32 basis), so the timing pass never has
``tracemalloc`` on, and the tracing pass reports memory only.

Run: ``python benchmarks/thin_shell.py [--levels 1,2]`` (``make bench``). Writes the table to stdout and
``benchmarks/out/thin_shell.md`` and a bar chart to ``benchmarks/out/thin_shell.png``.
Timings are wall-clock medians on whatever else the machine is doing (the load average
is printed with the table), with the CPU time (``time.process_time``, every thread) of the
basis and solve beside them, which the other processes do not inflate.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "benchmarks" / "out"

LEVELS = (1, 2)
SEED = 1
MARKERS = 150
FRAMES = 30                       # per-frame medians over this many frames
IGL_FRAMES = {0: 10, 1: 5, 2: 3}  # libigl refactors every frame: ~2 s (level 1), ~20 s (level 2)
DISPLACEMENT_MM = 3.0             # std. dev. of the random marker displacements
TARGET_MS = 5.0                   # issue target at level 1 for the basis
TARGET_RATIO = 20.0               # ... and at least this much faster than libigl
METHODS = ("basis64", "basis32", "solve", "igl")


# --------------------------------------------------------------------------------------
# meshes

def rig_fallback_neutral(level: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fallback when ``service.samples.actor.sample_neutral`` is unavailable.

    The ICT rig's generic neutral, Loop-subdivided ``level`` times, with 150 markers by
    farthest-point sampling (Euclidean, seeded start) over the narrow-face region
    (rig vertices ``[0, 6706)``, which keep their indices under subdivision).
    """
    from service.geometry.subdivision import subdivide

    rig = np.load(ROOT / "service/samples/data/ict_face_rig.npz")
    V0 = rig["neutral"].astype(np.float64)
    F0 = rig["triangles"].astype(np.int64)
    sub = subdivide(F0, len(V0), iterations=level)
    V = sub.S @ V0
    face = np.flatnonzero(rig["region"] == 0)
    rng = np.random.default_rng(seed)
    chosen = [int(face[rng.integers(len(face))])]
    dist = np.linalg.norm(V[face] - V[chosen[0]], axis=1)
    for _ in range(MARKERS - 1):
        chosen.append(int(face[np.argmax(dist)]))
        dist = np.minimum(dist, np.linalg.norm(V[face] - V[chosen[-1]], axis=1))
    return V, sub.faces, np.array(chosen)


def load_neutral(level: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """(V, F, marker vertices, source description) of the sample actor at ``level``."""
    try:
        from service.samples.actor import sample_neutral
    except ImportError:
        return (*rig_fallback_neutral(level, seed), "ICT rig neutral + FPS markers (fallback)")
    V, F, markers = sample_neutral(level, seed)
    return V, F, markers, "service.samples.actor.sample_neutral"


# --------------------------------------------------------------------------------------
# worker (one method, fresh process)

def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def _median_ms(fn, frames, clock=time.perf_counter) -> float:
    times = []
    for f in frames:
        t0 = clock()
        fn(f)
        times.append(clock() - t0)
    return 1e3 * float(np.median(times))


def _traced_mb(trace: bool) -> float | None:
    """tracemalloc's peak, MB, and stop tracing (None in the timing pass)."""
    if not trace:
        return None
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def worker(method: str, mesh_path: str, trace: bool = False) -> dict:
    """Run one method. ``trace``: the memory pass (tracemalloc on; only its peak is
    kept by the caller), else the timing pass (tracemalloc off)."""
    import igl  # noqa: F401  (imported before the baseline so its code pages don't count)

    from service.geometry.thin_shell import ThinShellSolver, apply_basis

    data = np.load(mesh_path)
    V, F, handles, level = data["V"], data["F"], data["handles"], int(data["level"])
    rng = np.random.default_rng([SEED, level])
    uH = rng.normal(scale=DISPLACEMENT_MM, size=(FRAMES, len(handles), 3))

    try:
        Path("/proc/self/clear_refs").write_text("5")
        hwm_reset = True
    except OSError:
        hwm_reset = False
    rss0 = _status_kb("VmRSS") if hwm_reset else _status_kb("VmHWM")
    if trace:
        tracemalloc.start()
    res: dict = {"method": method, "level": level, "n": len(V), "h": len(handles),
                 "hwm_reset": hwm_reset}

    if method in ("basis64", "basis32"):
        dtype = np.float64 if method == "basis64" else np.float32
        t0 = time.perf_counter()
        solver = ThinShellSolver(V, F, handles)
        res["factor_s"] = time.perf_counter() - t0
        res["fill"] = solver.factor.fill
        res["pivot_ratio"] = solver.factor.pivot_ratio
        t0 = time.perf_counter()
        B = solver.basis(dtype=dtype)
        res["basis_s"] = time.perf_counter() - t0
        res["basis_mb"] = B.nbytes / 2**20
        for f in range(3):                                     # warm-up
            apply_basis(B, uH[f])
        res["ms_frame"] = _median_ms(lambda f: apply_basis(B, f), uH)
        # CPU time (all threads) beside the wall clock: on a shared machine the wall clock
        # counts the other processes' share of the cores too
        res["cpu_ms_frame"] = _median_ms(lambda f: apply_basis(B, f), uH, time.process_time)
        batch = []
        for _ in range(5):
            t0 = time.perf_counter()
            apply_basis(B, uH)
            batch.append(time.perf_counter() - t0)
        res["ms_frame_batch"] = 1e3 * float(np.median(batch)) / FRAMES
        peak = _status_kb("VmHWM")
        res["tracemalloc_mb"] = _traced_mb(trace)
        ref = solver.deform(uH[:2])
        res["max_diff_vs_solve_mm"] = float(np.abs(apply_basis(B, uH[:2]) - ref).max())
    elif method == "solve":
        t0 = time.perf_counter()
        solver = ThinShellSolver(V, F, handles)
        res["factor_s"] = time.perf_counter() - t0
        solver.deform(uH[0])
        res["ms_frame"] = _median_ms(solver.deform, uH)
        res["cpu_ms_frame"] = _median_ms(solver.deform, uH, time.process_time)
        t0 = time.perf_counter()
        solver.deform(uH)
        res["ms_frame_batch"] = 1e3 * (time.perf_counter() - t0) / FRAMES
        peak = _status_kb("VmHWM")
        res["tracemalloc_mb"] = _traced_mb(trace)
    elif method == "igl":
        import igl

        Vc, Fc, b = (np.ascontiguousarray(V, dtype=np.float64),
                     np.ascontiguousarray(F, dtype=np.int64), handles.astype(np.int64))
        frames = uH[:IGL_FRAMES[level]]
        results = []
        res["ms_frame"] = _median_ms(lambda f: results.append(igl.harmonic(Vc, Fc, b, f, 2)), frames)
        res["frames"] = len(frames)
        peak = _status_kb("VmHWM")
        res["tracemalloc_mb"] = _traced_mb(trace)
        ours = ThinShellSolver(V, F, handles, ks=0.0, kb=1.0).deform(frames[0])
        res["max_diff_ks0_vs_igl_mm"] = float(np.abs(ours - results[0]).max())
        res["max_abs_igl_mm"] = float(np.abs(results[0]).max())
    else:
        raise ValueError(method)
    res["peak_rss_mb"] = (peak - rss0) / 1024
    return res


# --------------------------------------------------------------------------------------
# report

def _fmt(x: float, digits: int = 2) -> str:
    return f"{x:.{digits}f}" if x < 100 else f"{x:.0f}"


def report(results: list[dict], meta: dict, levels: tuple[int, ...] = LEVELS) -> str:
    by = {(r["level"], r["method"]): r for r in results}
    lines = [
        "# Thin-shell benchmark (bickel2008 §4): 150 markers → all vertices",
        "",
        f"Meshes: {meta['source']}. ks = {meta['ks']}, kb = {meta['kb']} mm² "
        f"(libigl: pure bi-Laplacian). {FRAMES} random frames (σ = {DISPLACEMENT_MM} mm); "
        f"libigl over " + " / ".join(f"{IGL_FRAMES[lv]} (level {lv})" for lv in levels) + " frames. "
        f"{meta['cpus']} CPUs, load average {meta['load_before']} before / "
        f"{meta['load_after']} after; NumPy {meta['numpy']}, SciPy {meta['scipy']}, "
        f"libigl {meta['igl']}.",
        "",
        "Per frame (median wall-clock; *batch* = 30 frames in one call, divided by 30). "
        "Peak RSS = resident high-water mark added by the method in a fresh process "
        "(includes the one-time precompute: factor and basis); tracemalloc = NumPy/Python "
        "allocations only, measured in a separate run (tracing is off while timing).",
        "",
        "| level | vertices | method | ms/frame | CPU ms/frame | ms/frame (batch 30) | × vs libigl | "
        "peak RSS MB | tracemalloc MB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    names = {"basis64": "(a) basis B @ u_H, float64", "basis32": "(a) basis B @ u_H, float32",
             "solve": "(b) prefactored solve", "igl": "(c) libigl harmonic k=2"}
    for level in levels:
        ref = by[(level, "igl")]["ms_frame"]
        for m in METHODS:
            r = by[(level, m)]
            batch = _fmt(r["ms_frame_batch"]) if "ms_frame_batch" in r else "–"
            ratio = "1" if m == "igl" else f"{ref / r['ms_frame']:.0f}×"
            cpu = _fmt(r["cpu_ms_frame"]) if "cpu_ms_frame" in r else "–"
            lines.append(f"| {level} | {r['n']:,} | {names[m]} | {_fmt(r['ms_frame'])} | {cpu} | {batch} | "
                         f"{ratio} | {r['peak_rss_mb']:.0f} | {r['tracemalloc_mb']:.0f} |")
    lines += [
        "",
        "One-time precompute per actor (ours):",
        "",
        "| level | factorization s | basis s (f64) | basis s (f32) | basis MB (f64 / f32) | "
        "factor nnz(L+U) | pivot ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for level in levels:
        a, b = by[(level, "basis64")], by[(level, "basis32")]
        lines.append(f"| {level} | {a['factor_s']:.2f} | {a['basis_s']:.1f} | {b['basis_s']:.1f} | "
                     f"{a['basis_mb']:.0f} / {b['basis_mb']:.0f} | {a['fill'] / 1e6:.1f} M | "
                     f"{a['pivot_ratio']:.1e} |")
    lines += ["", "Accuracy:", ""]
    for level in levels:
        a, b, g = by[(level, "basis64")], by[(level, "basis32")], by[(level, "igl")]
        lines.append(
            f"- level {level}: |basis − solve| ≤ {a['max_diff_vs_solve_mm']:.1e} mm (float64), "
            f"≤ {b['max_diff_vs_solve_mm']:.1e} mm (float32); ours with ks=0 vs libigl k=2: "
            f"max |Δu| = {g['max_diff_ks0_vs_igl_mm']:.1e} mm (max |u| = {g['max_abs_igl_mm']:.1f} mm)")
    if 1 not in levels:
        return "\n".join(lines) + "\n"
    l1 = {m: by[(1, m)] for m in METHODS}
    best = min(l1["basis64"]["ms_frame"], l1["basis32"]["ms_frame"])
    ratio = l1["igl"]["ms_frame"] / best
    lines += [
        "",
        f"Targets (level 1): basis ≤ {TARGET_MS:g} ms/frame: **{'met' if best <= TARGET_MS else 'MISSED'}** "
        f"({best:.2f} ms, float32 {l1['basis32']['ms_frame']:.2f} ms, float64 "
        f"{l1['basis64']['ms_frame']:.2f} ms); ≥ {TARGET_RATIO:g}× faster than libigl: "
        f"**{'met' if ratio >= TARGET_RATIO else 'MISSED'}** ({ratio:.0f}×).",
    ]
    return "\n".join(lines) + "\n"


def plot(results: list[dict], path: Path, levels: tuple[int, ...] = LEVELS) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by = {(r["level"], r["method"]): r for r in results}
    bars = [("basis f64", "basis64", "ms_frame"), ("basis f32", "basis32", "ms_frame"),
            ("basis f32, batch 30", "basis32", "ms_frame_batch"),
            ("prefactored solve", "solve", "ms_frame"), ("libigl harmonic k=2", "igl", "ms_frame")]
    colors = ["#4c72b0", "#55a868", "#8dd3a0", "#dd8452", "#c44e52"]
    fig, ax = plt.subplots(figsize=(9, 4.8))
    width = 0.16
    x = np.arange(len(levels))
    for k, ((label, m, key), color) in enumerate(zip(bars, colors)):
        vals = [by[(lv, m)][key] for lv in levels]
        pos = x + (k - 2) * width
        ax.bar(pos, vals, width, label=label, color=color)
        for p, v in zip(pos, vals):
            ax.text(p, v * 1.12, f"{v:.3g}", ha="center", va="bottom", fontsize=7)
    ax.set_yscale("log")
    ax.set_ylim(top=ax.get_ylim()[1] * 4)
    ax.axhline(TARGET_MS, color="gray", ls="--", lw=0.8, label=f"{TARGET_MS:g} ms target (level 1)")
    ax.set_xticks(x, [f"level {lv}\n{by[(lv, 'igl')]['n']:,} vertices" for lv in levels])
    ax.set_ylabel("ms per frame (log scale)")
    ax.set_title("Thin shell (bickel2008 §4), 150 markers → all vertices")
    ax.legend(fontsize=8, ncols=3, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", choices=METHODS, help=argparse.SUPPRESS)
    parser.add_argument("--mesh", help=argparse.SUPPRESS)
    parser.add_argument("--trace", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--levels", default=",".join(map(str, LEVELS)),
                        help="comma-separated sample-actor levels (default %(default)s)")
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.mesh, args.trace)))
        return
    levels = tuple(int(x) for x in args.levels.split(","))
    if any(lv not in IGL_FRAMES for lv in levels):
        parser.error(f"--levels takes levels of {sorted(IGL_FRAMES)}")

    import igl
    import scipy

    from service.geometry.thin_shell import KB, KS

    OUT.mkdir(parents=True, exist_ok=True)
    meta = {"cpus": os.cpu_count(), "load_before": f"{os.getloadavg()[0]:.1f}",
            "numpy": np.__version__, "scipy": scipy.__version__, "ks": KS, "kb": KB,
            "igl": getattr(igl, "__version__", "2.6")}
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for level in levels:
            t0 = time.perf_counter()
            V, F, handles, meta["source"] = load_neutral(level, SEED)
            mesh = Path(tmp) / f"level{level}.npz"
            np.savez(mesh, V=np.asarray(V, np.float64), F=np.asarray(F, np.int64),
                     handles=np.asarray(handles, np.int64), level=level)
            print(f"level {level}: {len(V):,} vertices, {len(handles)} markers "
                  f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
            for method in METHODS:
                t0 = time.perf_counter()
                res = _run_worker(method, mesh, level, trace=False)
                res["tracemalloc_mb"] = _run_worker(method, mesh, level, trace=True)["tracemalloc_mb"]
                results.append(res)
                print(f"  {method}: {time.perf_counter() - t0:.1f} s (timing + memory pass)", file=sys.stderr)
    meta["load_after"] = f"{os.getloadavg()[0]:.1f}"
    text = report(results, meta, levels)
    print(text)
    (OUT / "thin_shell.md").write_text(text)
    plot(results, OUT / "thin_shell.png", levels)


def _run_worker(method: str, mesh: Path, level: int, trace: bool) -> dict:
    """One method in a fresh process: the timing pass or (``trace``) the memory pass."""
    cmd = [sys.executable, __file__, "--worker", method, "--mesh", str(mesh)] + (["--trace"] if trace else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        sys.exit(f"worker {method} level {level} ({'memory' if trace else 'timing'} pass) failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    main()

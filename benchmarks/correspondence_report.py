"""Scan correspondence report (Vuvuzela, digital_ira_course2014): warp error against the
known correspondence, the pipeline's stages and the OpenCV peers, speed, figures.

Scans: :func:`service.samples.uv_scans.build_uv_scans` of each actor directory given (default
the level-1 sample actor ``benchmarks/out/actor-l1``, built if missing; a second family's directory works the same way): the neutral
(target) and the peak frame of every ``train_*`` performance (sources), each as albedo and
position maps in its own cylindrical UV layout, with 32 clicked landmarks off by 0.3 mm.

Methods (rows), each one :func:`~service.methods.correspondence.correspond` call per pair:

* *pre-warp alone*: the Delaunay piecewise-affine warp of the landmarks (step 1);
* *flow alone*: the refined flow (DIS to the finest scale + a residual DIS pass) on the
  over-sharpened textures, from the identity (step 2 without step 1);
* *pre-warp + flow*: the method (steps 1–3);
* *OpenCV DIS* / *OpenCV Farneback*: the plain peers — OpenCV's flow on the raw albedo
  luminance (8-bit), no pre-warp, no sharpening, default settings (DIS: medium preset);
* *pre-warp + DIS* / *pre-warp + Farneback*: the peers in place of the refined flow;
* *method, 2nd round of clicks*: the paper's interactive loop ("the user can then add [...]
  points, and repeat the process"), simulated: up to 8 more click pairs (0.3 mm noise), one
  in each of the largest regions where the first result's NCC confidence is below 0.6.

Metrics over the target texels where the known correspondence is valid (the point is
visible in the source; fold-overs of the unwrap are not) and the method has a result,
pooled over the scan pairs: warp error in source texels (median, 95th percentile) and in mm
on the source surface (:mod:`service.methods.correspondence.accuracy`); coverage (valid
texels with a result); mean NCC confidence (fyffe §4.1). *Blendshapes*: the method's
artist-mesh vertices looked up in the warped position map against the expression's
vertices, at face vertices visible in both scans, mm; also for the vertices at least 2
texels from an occlusion (the flow's errors concentrate next to fold-overs, where the
source has no matching skin).

Speed: wall time of one ``correspond`` call per pair (the scans already in memory), at
each resolution, median over the pairs, OpenCV and BLAS on ``--cores`` cores (2).

Figures (``benchmarks/out/correspondence/``): per actor and resolution, for the brow
raise, the smile and the surprise (open mouth) where present, the target albedo, the warped source and the difference |warped − target| of the
luminance's pore band (``L − G_σ*L``, σ = 3 texels: the blood-flow colour change of the
expression is low-frequency and would hide the alignment) for the pre-warp alone, plain
DIS, the method, and the known correspondence (the floor: what the expression changes in
the pores themselves), full face and a zoom at pore scale; and the method's texel-error map.

Run: ``python benchmarks/correspondence_report.py [ACTOR_DIR ...] [--resolutions 1024 2048]
[--expressions N] [--expressions-2048 N]``. Writes the tables to stdout and
``benchmarks/out/correspondence_report.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CORES = 2


def _limit_threads(cores: int) -> None:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(cores)
    try:
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:cores])
    except (AttributeError, OSError):
        pass


_limit_threads(CORES)                  # before NumPy loads its BLAS

import numpy as np

OUT = ROOT / "benchmarks" / "out"
FIGURES = OUT / "correspondence"

METHODS = {
    "pre-warp alone": dict(flow="none"),
    "flow alone (refined)": dict(prewarp=False),
    "pre-warp + flow (refined) [method]": dict(),
    "OpenCV DIS (plain)": dict(prewarp=False, flow="dis", sharpen_amount=0.0),
    "OpenCV Farneback (plain)": dict(prewarp=False, flow="farneback", sharpen_amount=0.0),
    "pre-warp + DIS": dict(flow="dis"),
    "pre-warp + Farneback": dict(flow="farneback"),
}
METHOD = "pre-warp + flow (refined) [method]"
SECOND = "method, 2nd round of clicks (simulated user)"
#: expressions with figures (where present): an easy one, the smile, the open mouth
FIGURE_EXPRESSIONS = ("train_brow_raise", "train_smile", "train_surprise")
CLICK_NOISE_MM = 0.3
SECOND_ROUND = dict(clicks=8, below=0.6, min_texels=100)


def second_round_landmarks(S, i, result, truth, valid, rng):
    """The paper's loop ("the user can then add [...] points, and repeat"), simulated: one
    click pair at the most interior texel of each of the largest regions where the first
    result's NCC confidence is below ``below``, each click off by the click noise."""
    from scipy import ndimage

    from service.samples.uv_scans import mm_per_texel

    H = S.resolution
    low = (result.confidence < SECOND_ROUND["below"]) & valid
    labels, n = ndimage.label(low)
    if n == 0:
        return None
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    keep = [j + 1 for j in np.argsort(sizes)[::-1][:SECOND_ROUND["clicks"]]
            if sizes[j] >= SECOND_ROUND["min_texels"]]
    if not keep:
        return None
    depth = ndimage.distance_transform_edt(low)
    pts = []
    for lab in keep:                                   # a loop over a few regions
        r, c = np.unravel_index(np.argmax(np.where(labels == lab, depth, -1)), labels.shape)
        pts.append((c, r))
    tgt = np.array(pts, np.float64)
    src = truth[tgt[:, 1].astype(int), tgt[:, 0].astype(int)]
    noise = CLICK_NOISE_MM / mm_per_texel(S.target)
    tgt = tgt + rng.standard_normal(tgt.shape) * noise
    src = src + rng.standard_normal(src.shape) * noise

    def uv(xy):
        return np.column_stack([(xy[:, 0] + 0.5) / H, 1 - (xy[:, 1] + 0.5) / H])

    return np.stack([uv(src), uv(tgt)], axis=1)


def run_pairs(S, params_by_name, log):
    """Every method on every pair: pooled errors, confidences, times, blendshape errors."""
    from service.methods.correspondence import (
        CorrespondenceParams,
        blendshape_vertices,
        correspond,
    )
    from scipy import ndimage

    from service.methods.correspondence.accuracy import warp_errors

    rows = {name: {"tex": [], "mm": [], "cover": [], "conf": [], "seconds": []}
            for name in list(params_by_name) + ([SECOND] if METHOD in params_by_name else [])}
    blend, results = [], {}
    face = np.flatnonzero(np.isfinite(S.target.layout).all(axis=1))
    H = S.resolution
    uv = S.target.layout[face]
    vr = np.clip(np.rint((1 - uv[:, 1]) * H - 0.5).astype(int), 0, H - 1)
    vc = np.clip(np.rint(uv[:, 0] * H - 0.5).astype(int), 0, H - 1)
    for i, src in enumerate(S.sources):
        truth, valid = S.truth(i)
        lm = np.stack([S.source_landmarks[i], S.target_landmarks[i]], axis=1)
        for name, kw in params_by_name.items():
            t = time.perf_counter()
            r = correspond(src.maps, S.target.maps, lm, CorrespondenceParams(**kw))
            dt = time.perf_counter() - t
            ok = valid & r.mask
            tex, mm = warp_errors(r.coords, truth, ok, src.maps["position"])
            row = rows[name]
            row["tex"].append(tex)
            row["mm"].append(mm)
            row["cover"].append(ok.sum() / max(valid.sum(), 1))
            row["conf"].append(float(r.confidence[ok].mean()))
            row["seconds"].append(dt)
            log(f"  {src.name:18s} {name:36s} median {np.median(tex):.3f} tx "
                f"{np.median(mm):.3f} mm  p95 {np.percentile(tex, 95):.2f} tx  {dt:.1f} s")
            if name == METHOD and SECOND in rows:
                extra = second_round_landmarks(S, i, r, truth, valid, np.random.default_rng([i, 2]))
                lm2 = lm if extra is None else np.concatenate([lm, extra])
                t = time.perf_counter()
                r2 = correspond(src.maps, S.target.maps, lm2, CorrespondenceParams(**kw))
                dt2 = time.perf_counter() - t
                ok2 = valid & r2.mask
                tex2, mm2 = warp_errors(r2.coords, truth, ok2, src.maps["position"])
                row2 = rows[SECOND]
                row2["tex"].append(tex2)
                row2["mm"].append(mm2)
                row2["cover"].append(ok2.sum() / max(valid.sum(), 1))
                row2["conf"].append(float(r2.confidence[ok2].mean()))
                row2["seconds"].append(dt2)
                log(f"  {src.name:18s} {SECOND:36s} median {np.median(tex2):.3f} tx "
                    f"{np.median(mm2):.3f} mm  p95 {np.percentile(tex2, 95):.2f} tx  "
                    f"(+{0 if extra is None else len(extra)} clicks)")
            if name == METHOD:
                seen = valid[vr, vc]
                inner = ndimage.binary_erosion(valid, iterations=2)[vr, vc][seen]
                V = blendshape_vertices(r.maps["position"], r.mask, uv)
                err = np.linalg.norm(V - src.vertices[face], axis=1)[seen]
                moved = np.linalg.norm(src.vertices[face] - S.target.vertices[face], axis=1)[seen]
                blend.append((src.name, err, moved, inner, np.median(tex), np.percentile(tex, 95),
                              np.median(mm), np.percentile(mm, 95)))
            if src.name in FIGURE_EXPRESSIONS and name in ("pre-warp alone", "OpenCV DIS (plain)", METHOD):
                results[(i, name)] = r
        if src.name in FIGURE_EXPRESSIONS:
            results[(i, "truth")] = truth
    return rows, blend, results


def figures(S, results, tag, log):
    """Warped-vs-target texture differences (full face and pore-scale zoom), error maps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from service.geometry import optical_flow as of
    from service.methods.correspondence.texture import luminance, oversharpen

    def detail(L, mask):
        """Pore-scale band of a luminance image: L − G_3 * L (masked), relative to the local mean."""
        return oversharpen(L, mask, 3.0, 1.0) - np.where(mask, L, 0.0)

    FIGURES.mkdir(parents=True, exist_ok=True)
    paths = []
    tgt = S.target
    L_t = luminance(tgt.maps["albedo"])
    H = S.resolution
    for i in sorted({k[0] for k in results}):
        src = S.sources[i]
        truth = results[(i, "truth")]
        method = results[(i, METHOD)]
        panels = [("pre-warp alone", results[(i, "pre-warp alone")].coords),
                  ("OpenCV DIS (plain)", results[(i, "OpenCV DIS (plain)")].coords),
                  ("pre-warp + flow [method]", method.coords),
                  ("known correspondence (floor)", np.nan_to_num(truth).astype(np.float32))]
        L_s = luminance(src.maps["albedo"])
        lo, hi = np.percentile(L_t[tgt.mask], [1, 99])
        # zoom: a window on the cheek beside the mouth corner (moves most), at pore scale
        ys, xs = np.nonzero(tgt.mask)
        cy = int(ys.min() + 0.68 * (ys.max() - ys.min()))
        cx = int(xs.min() + 0.33 * (xs.max() - xs.min()))
        z = max(48, H // 16)
        zoom = (slice(cy - z, cy + z), slice(cx - z, cx + z))
        fig, ax = plt.subplots(3, 5, figsize=(21, 13))
        ax[0, 0].imshow(L_t, cmap="gray", vmin=lo, vmax=hi)
        ax[0, 0].set_title("target (neutral) albedo luminance")
        warped = of.remap(L_s, method.coords)
        ax[1, 0].imshow(np.where(method.mask, warped, 0), cmap="gray", vmin=lo, vmax=hi)
        ax[1, 0].set_title(f"source ({src.name}) warped by the method")
        e = np.linalg.norm(method.coords - truth, axis=-1)
        _, valid = S.truth(i)
        im = ax[2, 0].imshow(np.where(valid & method.mask, e, np.nan), cmap="magma", vmin=0, vmax=2)
        ax[2, 0].set_title("method warp error, texels (NaN: not visible in the source)")
        plt.colorbar(im, ax=ax[2, 0], fraction=0.046)
        D_t = detail(L_t, tgt.mask)
        D_s = detail(L_s, src.mask)
        scale = 0.5 * np.percentile(np.abs(D_t[tgt.mask]), 95)
        for k, (name, coords) in enumerate(panels):
            full = np.abs(of.remap(L_s, coords) - L_t)[tgt.mask].mean()
            d = np.abs(of.remap(D_s, coords) - D_t)
            d[~tgt.mask] = np.nan
            ax[0, k + 1].imshow(d, cmap="inferno", vmin=0, vmax=scale)
            ax[0, k + 1].set_title(f"|warped − target| pore band: {name}\nmean {np.nanmean(d):.4f} "
                                   f"(luminance: {full:.4f})")
            ax[1, k + 1].imshow(d[zoom], cmap="inferno", vmin=0, vmax=scale, interpolation="nearest")
            ax[1, k + 1].set_title(f"zoom {2 * z}² texels (cheek by the mouth corner)")
            w = of.remap(L_s, coords)
            ax[2, k + 1].imshow(np.concatenate([L_t[zoom], w[zoom]], axis=1), cmap="gray",
                                vmin=lo, vmax=hi, interpolation="nearest")
            ax[2, k + 1].set_title("zoom: target | warped source")
        for a in ax.ravel():
            a.set_xticks([])
            a.set_yticks([])
        fig.suptitle(f"{tag}: {src.name} → neutral at {H}²")
        fig.tight_layout()
        path = FIGURES / f"{tag}_{H}_{src.name}.png"
        fig.savefig(path, dpi=70)
        plt.close(fig)
        paths.append(path)
        log(f"  figure {path.relative_to(ROOT)}")
    return paths


def table(rows):
    lines = ["| method | median tx | p95 tx | median mm | p95 mm | coverage | confidence | s / pair |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        tex, mm = np.concatenate(r["tex"]), np.concatenate(r["mm"])
        lines.append(f"| {name} | {np.median(tex):.3f} | {np.percentile(tex, 95):.2f} | "
                     f"{np.median(mm):.3f} | {np.percentile(mm, 95):.2f} | "
                     f"{np.mean(r['cover']):.3f} | {np.mean(r['conf']):.2f} | "
                     f"{np.median(r['seconds']):.2f} |")
    return lines


def blend_table(blend):
    lines = ["| expression | warp median tx | warp p95 tx | warp median mm | warp p95 mm | "
             "blendshape median mm | p95 mm | ≥2 texels from occlusions: median mm | p95 mm | "
             "moved >3 mm: median mm | vertices (≥2 texels) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, err, moved, inner, mt, pt, mm, pm in blend:
        big = err[inner & (moved > 3.0)]
        lines.append(f"| {name} | {mt:.3f} | {pt:.2f} | {mm:.3f} | {pm:.2f} | {np.median(err):.3f} | "
                     f"{np.percentile(err, 95):.2f} | {np.median(err[inner]):.3f} | "
                     f"{np.percentile(err[inner], 95):.2f} | "
                     f"{np.median(big) if len(big) else float('nan'):.3f} | "
                     f"{len(err)} ({inner.sum()}) |")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("actors", nargs="*", default=[])
    ap.add_argument("--resolutions", type=int, nargs="+", default=[1024, 2048])
    ap.add_argument("--expressions", type=int, default=8, help="expressions per actor at ≤ 1024²")
    ap.add_argument("--expressions-2048", type=int, default=3,
                    help="expressions per actor above 1024² (memory)")
    ap.add_argument("--cores", type=int, default=CORES)
    ap.add_argument("--names", nargs="+", default=None,
                    help="these expressions (performance names) instead of the first N")
    ap.add_argument("--report", default="correspondence_report.md",
                    help="file name of the report under benchmarks/out/")
    args = ap.parse_args(argv)
    _limit_threads(args.cores)
    import cv2

    cv2.setNumThreads(args.cores)
    from service.samples import dataset
    from service.samples.uv_scans import build_uv_scans, mm_per_texel


    def log(s=""):
        print(s, flush=True)

    report = ["# Scan correspondence (Vuvuzela) report", "",
              f"{args.cores} cores (OpenCV threads {cv2.getNumThreads()}), opencv "
              f"{cv2.__version__}; scans from `service.samples.uv_scans`, 32 landmarks "
              "clicked with 0.3 mm noise.", ""]
    if not args.actors:
        sys.path.insert(0, str(ROOT / "benchmarks"))
        import harness

        args.actors = [str(harness.sample_actor("a", 1))]
    for actor_dir in args.actors:
        actor_dir = Path(actor_dir)
        tag = actor_dir.name
        names = dataset.performance_names(actor_dir, "train_")
        for res in args.resolutions:
            k = args.expressions if res <= 1024 else args.expressions_2048
            t = time.perf_counter()
            chosen = args.names if args.names else names[:k]
            S = build_uv_scans(actor_dir, resolution=res, expressions=chosen, landmarks=32)
            build = time.perf_counter() - t
            log(f"{tag} {res}²: {len(S.sources)} scan pairs built in {build:.0f} s, "
                f"{mm_per_texel(S.target):.3f} mm per texel")
            methods = METHODS if res <= 1024 else {n: METHODS[n] for n in
                                                   ("pre-warp alone", METHOD, "OpenCV DIS (plain)",
                                                    "OpenCV Farneback (plain)")}
            rows, blend, results = run_pairs(S, methods, log)
            report += [f"## {tag}, {res}² ({len(S.sources)} expression → neutral pairs, "
                       f"{mm_per_texel(S.target):.3f} mm/texel; scans built in {build:.0f} s)", ""]
            report += table(rows) + [""]
            report += ["Per expression, the method, and its blendshapes (visible face vertices):", ""]
            report += blend_table(blend) + [""]
            paths = figures(S, results, tag, log)
            report += [f"![{p.stem}](correspondence/{p.name})" for p in paths] + [""]
            for line in table(rows):
                log(line)
            del S, results
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / args.report).write_text("\n".join(report) + "\n")
    log("\n".join(report))


if __name__ == "__main__":
    main()

"""Generalization report (issue 17): every method on both actor families, beyond the training data.

For each actor family (a: ``service.samples.actor``; b: ``service.samples.family_b``, an
independent generator) × {in range, combinations, out of range} × {clean, noisy, occluded}
markers, the held-out map frames (``--frames`` of them, evenly spaced between the ends) are
synthesized by

* *no detail*: the thin shell of the detailed neutral (``pdm_report.Baselines.no_detail``);
* *static neutral map*: the same plus a neutral training frame's fine map (ma2008 Fig. 7);
* *nearest training frame*: the training frame with the nearest aligned markers, its detail
  moved onto the thin shell (the honest non-parametric reference row);
* *PDM linear* and *PDM biquadratic* (ma2008 eq. 1), trained on the family's ``train_*``
  clips, with their extrapolation limit;
* *shape space (markers)* and, on clean rows, *shape space (rig)*: bermano2014 trained on the
  family's ``database`` performance, given the markers, or the low-resolution rig meshes
  carried to the neutral by the rig registration (the rig input has no markers to corrupt);
* *WPSD* (bickel2008 §5.3 with its defaults: no marker regression) and *WPSD + marker
  regression (s=S, λ=R)* (default the recommended s = 3, λ = 0.1;
  ``WpsdParams(marker_regression=S, marker_regression_ridge=R)``,
  ``--regression S[:R] ...``), trained on the family's ``train_*`` clips (fresh process,
  cached with the PDMs), with their own marker prior (``marker_prior = "posterior"``: they
  do not take ``--marker-noise``). Their rows also give the median synthesis time per frame
  (``mesh`` + ``displacement``, one call for the performance's frames, level 0 here) and the
  report their training time.

Performances: ``heldout_in_range``, ``heldout_combinations`` (combinations no training clip
shows) and ``heldout_amplified`` (every training expression 25–40 % beyond its peak), and
their ``_noisy`` (σ = 0.3 mm per coordinate) and ``_occluded`` (NaN bursts) marker variants,
scored against the same clean ground truth.

The PDMs are trained with their default parameters (``pdm_report.worker_train``: fine band
1024²); on a level-0 actor, whose maps are 512², their fine maps are box-filtered to 512²
and the band split's σ halved, so every method is scored at the actor's map resolution.

Metrics are those of ``pdm_report.py`` (:func:`pdm_report.evaluate_performance`, face
region): vertex error |V − V_gt| pooled over frames and face vertices — mean, p95 and max —
and the high-passed detail height (mesh + map) against the ground truth's: Pearson r
(*detail corr*) and *rel err* = RMS error / RMS of the ground truth's detail (0 perfect,
1 no better than no detail).

Per-frame confidence (the PDM's ``confidence``, X-Facesynth-Confidence) is ranked against the
per-frame mean face vertex error: Spearman ρ of ``1 − confidence`` and the error, per input
range with every marker condition pooled (issue 17: ≥ 0.6 out of range).

Also writes, per family, a heat map PNG of the vertex errors of every method on the worst
frame (the largest PDM-biquadratic vertex error over all rows): the ground truth and one tile
per method, four to a row, the colour scale (0 … 2 mm) below. The rows held against the thin
shell (PDM, WPSD) list the frames whose max face error exceeds the shell's, and the frame
number of the largest excess.

Models are cached: the PDMs and pose-space models under ``benchmarks/out/generalization/models/`` and the
shape-space model and rig registration in shape_space_report's cache, all keyed by the
actor's files. A method that fails on an input (e.g. occluded markers) gets a row saying so.

Run: ``python benchmarks/generalization_report.py [--actor a=DIR] [--actor b=DIR]
[--frames K] [--retrain] [--marker-filter S] [--marker-noise SIGMA] [--split] [--pdm-only]
[--pdm-params JSON] [--regression S[:R] ...] [--pose-space-params JSON] [--out DIR]`` (``--pdm-params '{"neutral_anchor": true}'``: other PDM training
parameters, their models cached apart); default actors (built
when missing, seed 1, level 0):
``benchmarks/out/generalization/actor-{a,b}-l0``. Writes the table to stdout and
``benchmarks/out/generalization/report.md`` (``--out DIR``: there), figures beside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import harness as pdm  # noqa: E402  (data loading, baselines, detail metric, workers, cached builds)
from service.geometry.marker_prior import AUTO  # noqa: E402
from service.methods.pose_space.params import MARKER_REGRESSION_RIDGE, RECOMMENDED_MARKER_REGRESSION  # noqa: E402

OUT = pdm.GENERALIZATION
MODELS = pdm.GENERALIZATION_MODELS
RANGES = pdm.HELDOUT_RANGES
CONDITIONS = pdm.MARKER_CONDITIONS
ORDERS = pdm.PDM_ORDERS
DEFAULT_FRAMES = 8
SS_MARKERS, SS_RIG = "shape space (markers)", "shape space (rig)"
WORST_OF = "PDM biquadratic"
WPSD = "WPSD"
#: (s, ridge) of the regression rows: the recommended values (service.methods.pose_space.params)
DEFAULT_REGRESSION = ((RECOMMENDED_MARKER_REGRESSION, MARKER_REGRESSION_RIDGE),)
#: the rows whose per-frame max is held against the thin shell's (issue 17: never above it)
AGAINST_SHELL = ("PDM", "WPSD")
#: ``--split``: each PDM, pose-space and shape-space row's detail error carried by its mesh (its
#: mesh with the truth's map) and by its map (the truth's mesh with its map), rows named with
#: these prefixes
SPLIT_PARTS = ("mesh part of", "map part of")
CONFIDENCE = "confidence"          # service.methods.confidence.CONFIDENCE (the result key)
HEAT_MM = 2.0                     # heat-map colour range, mm
#: a PDM frame's max error counts as above the thin shell's beyond this (the PDM's vertices
#: are float32: at the neutral the shell's error is 0 and the PDM's its rounding, ~1e-5 mm)
WORSE_TOL_MM = 1e-3


def _guard(method):
    """A method whose failure on an input becomes a row (the message) instead of ending the run."""
    def run(markers):
        try:
            return method(markers)
        except Exception as e:          # noqa: BLE001  (any refusal is a finding to report)
            raise MethodFailed(f"{type(e).__name__}: {str(e)[:120]}") from e
    return run


class MethodFailed(Exception):
    pass


def _once(method):
    """``method`` answering the same markers array (the one performance's) from its last call:
    a split row and its method's row share one synthesis."""
    last = {}

    def run(markers):
        if last.get("key") is not markers:
            last.update(key=markers, value=method(markers))
        return last["value"]
    return run


def regression_arg(text: str) -> tuple[float, float]:
    """``--regression S[:R]``: the marker regression's s (median marker spacings) and ridge λ
    (default the field's)."""
    s, _, r = text.partition(":")
    return float(s), float(r) if r else MARKER_REGRESSION_RIDGE


def regression_name(s: float, ridge: float) -> str:
    return f"WPSD + marker regression (s={s:g}, λ={ridge:g})"


def pose_space_variants(regressions, extra: dict | None = None) -> dict:
    """Row name → WpsdParams: plain WPSD and one row per (s, ridge) of the marker regression;
    with ``extra`` (other WpsdParams fields, ``--pose-space-params``) also each of those rows
    with them, named with the fields appended (e.g. ``..., posterior_noise=frame``)."""
    from service.methods.pose_space import WpsdParams

    out = {WPSD: WpsdParams(marker_regression=None)}
    out.update({regression_name(s, r): WpsdParams(marker_regression=s, marker_regression_ridge=r)
                for s, r in regressions})
    if extra:
        tag = ", ".join(f"{k}={v}" for k, v in extra.items())
        out.update({f"{name} + {tag}": p.model_copy(update=extra) for name, p in list(out.items())})
    return out


def evaluate_family(family: str, actor_dir: Path, frames: int | None, retrain: bool,
                    marker_filter: float | str = 0.0, marker_noise_mm: float | str = 0.0,
                    shape_space_rows: bool = True, pdm_params: dict | None = None,
                    only: set | None = None, ranges=None, conditions=None,
                    pose_space: dict | None = None, split: bool = False) -> dict:
    """Rows {(range, condition, method): metrics} and the worst frame's data of one family;
    ``only`` (method names), ``ranges`` and ``conditions`` restrict the rows (None: all);
    ``pose_space``: row name → pose-space params (:func:`pose_space_variants`); ``split``:
    the :data:`SPLIT_PARTS` rows beside each PDM, pose-space and shape-space row."""
    from service.methods.pose_space import PoseSpaceModel
    from service.methods.shape_space import ShapeSpaceModel, ShapeSpaceParams
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    wanted = lambda name: only is None or name in only          # noqa: E731
    # the biquadratic PDM is always built: the baselines and the detail band split use it
    models = pdm.generalization_pdm_models(actor_dir, retrain, marker_noise_mm, pdm_params,
                        [o for o in ORDERS if o == "biquadratic" or wanted(f"PDM {o}")])
    bq = models["biquadratic"]
    # scored at the actor's map resolution (a level-0 actor's maps are 512², the PDM's fine
    # band 1024²: its maps are box-filtered down, its band split's σ scaled with them)
    H = json.loads((actor_dir / "manifest.json").read_text())["map_resolution"]
    tex = pdm.DetailTexels.build(actor, H, bq.metrics["highpass_sigma_texels"] * H / bq.data.fine.resolution)

    def at_map_resolution(D):
        k = D.shape[-1] // H
        return D.reshape(len(D), H, k, H, k).mean(axis=(2, 4)) if k > 1 else D

    # the performance's markers as captured, where a filter smoothed them: the models read
    # their noise for the confidence, as a synthesis job passes them (``captured``)
    captured: dict = {"markers": None}

    def as_captured():
        return {} if captured["markers"] is None else {"captured": captured["markers"]}

    def pdm_prediction(model, markers):
        out = model.synthesize(markers, pdm.BASIC_OUTPUTS, **as_captured())
        return (out["vertices"].astype(np.float64), tex.texels(at_map_resolution(out["displacement"])),
                out["clamped"], out.get(CONFIDENCE))

    ps_models, ps_train, synth_ms = {}, {}, {}
    for name, params in (pose_space or {}).items():
        if wanted(name):
            path, ps_train[name] = pdm.pose_space_model(actor_dir, params, retrain)
            ps_models[name] = PoseSpaceModel.load(path)

    def pose_space_prediction(name, markers):
        t0 = time.perf_counter()
        out = ps_models[name].synthesize(markers, pdm.BASIC_OUTPUTS, **as_captured())
        synth_ms.setdefault(name, []).append(1e3 * (time.perf_counter() - t0) / len(markers))
        return (out["vertices"].astype(np.float64), tex.texels(at_map_resolution(out["displacement"])),
                None, out.get(CONFIDENCE))

    clips = pdm.training_clips(actor_dir, actor)
    base = pdm.Baselines.build(actor, clips, bq, tex)
    del clips
    if shape_space_rows:
        ss_dir, _ = pdm.shape_space_model(actor_dir, ShapeSpaceParams(marker_noise_mm=marker_noise_mm), retrain)
        shape = ShapeSpaceModel.load(ss_dir)
        reg, _ = pdm.rig_registration(actor_dir, retrain)

    def shape_space(V_or_markers, kind):
        out = shape.enhance(V_or_markers, pdm.SS_OUTPUTS, input_kind=kind)
        D = (np.stack([tex.texels(m) for m in out["fine_displacement"]])
             if "fine_displacement" in out else None)
        return out["vertices"].astype(np.float64), D, None

    rows, worst = {}, None
    worst_frame = only is None and ranges is None and conditions is None
    for rname, perf in RANGES.items():
        if ranges is not None and rname not in ranges:
            continue
        gt_clean = pdm.heldout_frames(actor_dir, perf, frames)
        with np.load(actor_dir / "performances" / f"{perf}.npz") as d:
            lowres = d["lowres"][gt_clean.frames].astype(np.float64)
        for cname, suffix in CONDITIONS.items():
            if conditions is not None and cname not in conditions:
                continue
            # filtered as a synthesis job filters them for the model: "auto" in its prior's
            # modes (the baselines and the PDMs: the biquadratic's; every other model its own;
            # the worst-frame figure gives every method the biquadratic's)
            def take(model, name=perf + suffix):
                return pdm.variant_markers(actor_dir, name, gt_clean.frames, marker_filter,
                                           model.marker_modes if marker_filter == AUTO else None)

            gt = dataclasses.replace(gt_clean, name=perf + suffix, markers=take(bq))
            captured["markers"] = (pdm.variant_markers(actor_dir, perf + suffix, gt_clean.frames)
                                   if marker_filter else None)
            own = take if marker_filter == AUTO else (lambda model: None)
            methods = {"no detail": base.no_detail, "static neutral map": base.static_neutral_map,
                       "nearest training frame": lambda m: base.nearest(m)[:3]}
            methods.update({f"PDM {o}": (lambda m, model=model: pdm_prediction(model, m))
                            for o, model in models.items()})
            if shape_space_rows:
                methods[SS_MARKERS] = lambda m, mine=own(shape): shape_space(m if mine is None else mine, "markers")
            if shape_space_rows and cname == "clean":
                methods[SS_RIG] = lambda m: shape_space(reg.propagate(lowres), "vertices")
            methods.update({k: (lambda m, k=k, mine=own(ps_models[k]): pose_space_prediction(k, m if mine is None else mine))
                            for k in ps_models})
            methods = {k: m for k, m in methods.items() if wanted(k)}
            if split:
                truth_map = tex.truth_map(actor, gt)
                for name in [k for k in methods if k.startswith(AGAINST_SHELL) or k in (SS_MARKERS, SS_RIG)]:
                    methods[name] = once = _once(methods[name])
                    mesh_part, map_part = (f"{part} {name}" for part in SPLIT_PARTS)
                    methods[mesh_part] = lambda m, f=once, t=truth_map: (f(m)[0], t, None)
                    methods[map_part] = lambda m, f=once, gt=gt: (gt.vertices, f(m)[1], None)
            t0 = time.perf_counter()
            try:                # every method in one pass: the ground-truth row is scored once
                together = pdm.evaluate_performance(gt, {k: _guard(m) for k, m in methods.items()}, tex, actor,
                                                    gt.frames.tolist())
            except MethodFailed:
                together = None  # one method failed: each on its own, as before
            for name, method in methods.items():
                r = together
                if r is None:
                    try:
                        r = pdm.evaluate_performance(gt, {name: _guard(method)}, tex, actor, gt.frames.tolist())
                    except MethodFailed as e:
                        rows[(rname, cname, name)] = {"failed": str(e)}
                        print(f"  {family} {rname} {cname} {name}: failed ({e})", file=sys.stderr)
                        continue
                s = r["scores"][pdm.FACE][name]
                errs = np.stack([r["figure"]["vertex_error"][(name, f)] for f in gt.frames])   # (k,n)
                face_err = errs[:, np.asarray(actor.regions[pdm.FACE])]
                rows[(rname, cname, name)] = {
                    "mean": s["medium_mean_mm"], "p95": s["medium_p95_mm"], "max": float(face_err.max()),
                    "corr": s["fine_r"], "rel": s["fine_rms_mm"] / r["signal_rms_mm"][pdm.FACE],
                    "frames": len(gt.frames), "seconds": time.perf_counter() - t0,
                    "frame_max": face_err.max(axis=1).tolist(), "frame_numbers": gt.frames.tolist()}
                r_ = rows[(rname, cname, name)]
                if name in synth_ms:            # this performance's call (the last one timed)
                    r_["synth_ms_per_frame"] = synth_ms[name][-1]
                if r["extra"].get(name) is not None:        # per-frame confidence (PDM)
                    r_["confidence"] = np.asarray(r["extra"][name], np.float64).tolist()
                    r_["frame_error"] = face_err.mean(axis=1).tolist()
                    model = models.get(name.removeprefix("PDM "))
                    if model is not None and model.evaluator.base.marker_prior is not None:
                        # each frame's noise estimate (service.geometry.marker_prior.frame_noise)
                        from service.geometry.marker_prior import frame_noise
                        from service.methods.pdm.base_surface import head_alignment
                        ev = model.evaluator
                        p = head_alignment(gt.markers, ev.base.rest_markers, model.data.pose_weights)
                        r_["noise_mm"] = frame_noise(ev.base.marker_prior,
                                                     p.remove(gt.markers) - ev.base.rest_markers).tolist()
                        if marker_filter:       # and of the markers as captured, before the filter
                            noise = ev.base.captured_noise(captured["markers"], model.data.pose_weights)
                            r_["noise_captured_mm"] = None if noise is None else noise.tolist()
                print(f"ROW | {family} | {rname} | {cname} | {name} | {r_['mean']:.3f} | {r_['p95']:.3f} "
                      f"| {r_['max']:.2f} | {r_['corr']:.2f} | {r_['rel']:.2f} |", file=sys.stderr, flush=True)
                if name == WORST_OF and worst_frame:
                    k = int(np.argmax(face_err.max(axis=1)))
                    if worst is None or face_err[k].max() > worst["max"]:
                        worst = {"max": float(face_err[k].max()), "range": rname, "condition": cname,
                                 "performance": gt.name, "frame": int(gt.frames[k]), "slot": k,
                                 "gt": gt_clean.vertices[k], "markers": gt.markers[k:k + 1],
                                 "lowres": lowres[k:k + 1]}
    # the worst frame, every method (its figure reads no confidence)
    captured["markers"] = None
    errors = {}
    if worst is None:
        return {"rows": rows, "worst": None, "actor": actor, "pose_space_training": ps_train,
                "meta": {"vertices": actor.n_vertices, "markers": actor.n_markers}}
    fns = {"no detail": base.no_detail, "nearest training frame": lambda m: base.nearest(m)[:3],
           "PDM linear": lambda m: pdm_prediction(models["linear"], m),
           "PDM biquadratic": lambda m: pdm_prediction(bq, m)}
    if shape_space_rows:
        fns[SS_MARKERS] = lambda m: shape_space(m, "markers")
    fns.update({k: (lambda m, k=k: pose_space_prediction(k, m)) for k in ps_models})
    for name, fn in fns.items():
        try:
            V = fn(worst["markers"])[0][0]
            errors[name] = np.linalg.norm(V - worst["gt"], axis=-1)
        except Exception as e:          # noqa: BLE001
            print(f"  worst frame, {name}: failed ({e})", file=sys.stderr)
    worst["errors"] = errors
    return {"rows": rows, "worst": worst, "actor": actor, "pose_space_training": ps_train,
            "meta": {"vertices": actor.n_vertices, "markers": actor.n_markers}}


#: tiles per row of the worst-frame figure (8 tiles of 420 px in one row were 3360 px wide:
#: unreadable wherever the figure is shown scaled to a page)
FIGURE_COLUMNS = 4
#: caption characters the renderer's font lacks (PIL's default font draws λ as a box)
ASCII = str.maketrans({"λ": "lambda", "σ": "sigma", "ρ": "rho", "–": "-", "—": "-"})


def heat_colour(err: np.ndarray) -> np.ndarray:
    """Linear RGB (…,3) of vertex errors (…) mm: blue at 0, yellow at HEAT_MM / 2, red at and
    beyond HEAT_MM."""
    t = np.clip(np.asarray(err, np.float64) / HEAT_MM, 0, 1)[..., None]
    blue, yellow, red = np.array([0.1, 0.2, 0.8]), np.array([0.95, 0.9, 0.2]), np.array([0.8, 0.05, 0.05])
    return np.where(t < 0.5, (1 - 2 * t) * blue + 2 * t * yellow, (2 - 2 * t) * yellow + (2 * t - 1) * red)


def heat_legend(width: int, height: int = 36) -> np.ndarray:
    """(height, width, 3) uint8 strip: the heat colours from 0 to HEAT_MM, labelled."""
    from PIL import Image, ImageDraw

    from service.samples.render import to_srgb8

    bar = np.zeros((height, width, 3), np.uint8)
    x0, x1 = 80, width - 80
    bar[8:20, x0:x1] = to_srgb8(heat_colour(np.linspace(0, HEAT_MM, x1 - x0)))[None]
    img = Image.fromarray(bar)
    draw = ImageDraw.Draw(img)
    draw.text((8, 8), "0 mm", fill=(255, 255, 255))
    draw.text(((x0 + x1) // 2 - 20, 22), f"{HEAT_MM / 2:g} mm", fill=(255, 255, 255))
    draw.text((x1 + 8, 8), f">= {HEAT_MM:g} mm", fill=(255, 255, 255))
    return np.asarray(img)


def plot_worst(result: dict, family: str, path: Path) -> None:
    """Vertex-error heat maps (0 … HEAT_MM) of every method on the family's worst frame: the
    ground truth and one tile per method, FIGURE_COLUMNS to a row, the colour scale below."""
    from service.samples.gallery import caption, front_camera
    from service.samples.render import shade, to_srgb8, write_png

    actor, worst = result["actor"], result["worst"]
    cam = front_camera(worst["gt"], 420)
    tiles = [caption(to_srgb8(shade(cam, worst["gt"], actor.faces, np.full((actor.n_vertices, 3), 0.6),
                                    light_dir=(0.15, 1.0, 0.45), ambient=0.05)),
                     f"family {family}: ground truth, {worst['performance']} frame {worst['frame']}".translate(ASCII))]
    for name, err in worst["errors"].items():
        img = shade(cam, worst["gt"], actor.faces, heat_colour(err), light_dir=(0.0, 0.3, 1.0), ambient=0.6)
        tiles.append(caption(to_srgb8(img), f"{name}: max {err[np.asarray(actor.regions[pdm.FACE])].max():.2f} mm "
                                            f"(0-{HEAT_MM:g} mm)".translate(ASCII)))
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % FIGURE_COLUMNS)
    rows = [np.concatenate(tiles[i:i + FIGURE_COLUMNS], axis=1) for i in range(0, len(tiles), FIGURE_COLUMNS)]
    write_png(path, np.concatenate(rows + [heat_legend(rows[0].shape[1])], axis=0))


def _n(x, d=3):
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{d}f}"


def worse_frames(rows: dict) -> dict:
    """Per PDM and pose-space row (:data:`AGAINST_SHELL`) with a *no detail* row of the same
    input: (frames whose max face vertex error exceeds the thin shell's by more than
    :data:`WORSE_TOL_MM`, frames, largest excess mm, the performance's frame number of that
    largest excess)."""
    out = {}
    for (rname, cname, name), r in rows.items():
        shell = rows.get((rname, cname, "no detail"), {})
        if name.startswith(AGAINST_SHELL) and "frame_max" in r and "frame_max" in shell:
            excess = np.asarray(r["frame_max"]) - np.asarray(shell["frame_max"])
            k = int(np.argmax(excess))
            out[(rname, cname, name)] = (int(np.sum(excess > WORSE_TOL_MM)), len(excess), float(excess.max()),
                                         r["frame_numbers"][k] if "frame_numbers" in r else None)
    return out


def confidence_rank(rows: dict) -> dict:
    """Spearman ρ between ``1 − confidence`` and the mean face vertex error of each frame
    (issue 17's target: ≥ 0.6 out of range), per method, per input range (its frames of every
    marker condition pooled) and over all of them: {method: {range or "all": (ρ, frames)}}."""
    from scipy.stats import spearmanr

    pooled: dict = {}
    for (rname, _, name), r in rows.items():
        if "confidence" in r:
            for key in (rname, "all"):
                c, e = pooled.setdefault(name, {}).setdefault(key, ([], []))
                c += r["confidence"]
                e += r["frame_error"]
    out = {}
    for name, ranges in pooled.items():
        out[name] = {}
        for key, (c, e) in ranges.items():
            c, e = np.asarray(c), np.asarray(e)
            rho = (float(spearmanr(1.0 - c, e).statistic)
                   if len(c) > 2 and np.ptp(c) > 0 and np.ptp(e) > 0 else float("nan"))
            out[name][key] = (rho, len(c))
    return out


def report(results: dict, frames: int | None, seconds: float, settings: str = "") -> str:
    lines = ["# Generalization report (issue 17)", "",
             f"Face region; {frames or 'all'} held-out map frames per performance; "
             "rel err = detail RMS error / detail RMS of the ground truth." + (f" {settings}" if settings else ""), ""]
    for family, res in results.items():
        m = res["meta"]
        w = res["worst"]
        lines += [f"## Family {family} ({m['vertices']} vertices, {m['markers']} markers)", "",
                  "| input | markers | method | mean mm | p95 mm | max mm | detail corr | detail rel err |",
                  "|---|---|---|---|---|---|---|---|"]
        for (rname, cname, name), r in res["rows"].items():
            if "failed" in r:
                lines.append(f"| {rname} | {cname} | {name} | failed: {r['failed']} | | | | |")
                continue
            lines.append(f"| {rname} | {cname} | {name} | {_n(r['mean'])} | {_n(r['p95'])} | {_n(r['max'], 2)} "
                         f"| {_n(r['corr'], 2)} | {_n(r['rel'], 2)} |")
        timed = {k: r["synth_ms_per_frame"] for k, r in res["rows"].items() if "synth_ms_per_frame" in r}
        if timed or res.get("pose_space_training"):
            lines += ["", "Pose space, level 0 as run here (load at the end of the run below): training wall / CPU "
                          "s, and median synthesis ms per frame (mesh + displacement, one call a performance):", ""]
            for name, rec in res.get("pose_space_training", {}).items():
                ms = [v for (_, _, k), v in timed.items() if k == name]
                lines.append(f"- {name}: training {rec['train_s']:.0f} s / {rec.get('train_cpu_s', float('nan')):.0f} s "
                             f"CPU" + (f", synthesis {np.median(ms):.1f} ms/frame" if ms else ""))
        worse = worse_frames(res["rows"])
        if worse:
            lines += ["", "Frames whose max face vertex error exceeds the thin shell's (*no detail*) by more "
                          f"than {WORSE_TOL_MM * 1000:g} µm (issue 17: none), of the frames scored:", ""]
            lines += [f"- {name}, {rname}, {cname}: {n} of {k}" + (
                          f" (by up to {by:.2f} mm" + (f", frame {f})" if f is not None else ")") if n else "")
                      for (rname, cname, name), (n, k, by, f) in worse.items()]
        ranks = confidence_rank(res["rows"])
        if ranks:
            keys = list(RANGES) + ["all"]
            lines += ["", "Per-frame confidence against per-frame error: Spearman ρ of 1 − confidence "
                          "and the frame's mean face vertex error (frames of every marker condition "
                          "pooled; target ≥ 0.6 out of range; — where the confidence is constant)", "",
                      "| method | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
            for name, by in ranks.items():
                lines.append(f"| {name} confidence | " + " | ".join(
                    f"{_n(by[k][0], 2)} ({by[k][1]} frames)" if k in by else "" for k in keys) + " |")
        if w is not None:
            lines += ["", f"Worst {WORST_OF} frame: {w['performance']} frame {w['frame']} "
                          f"({w['range']}, {w['condition']}), max {w['max']:.2f} mm: "
                          f"`benchmarks/out/generalization/worst_family_{family}.png`", ""]
    lines.append(f"Total run {seconds:.0f} s on {os.cpu_count()} CPUs (load {os.getloadavg()[0]:.1f}).")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", action="append", default=[], metavar="FAMILY=DIR",
                        help="actor directory per family; only the families given are run "
                             "(default: both, built under benchmarks/out/generalization)")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                        help=f"held-out map frames per performance (default {DEFAULT_FRAMES}; 0 = all)")
    parser.add_argument("--retrain", action="store_true", help="rebuild the cached models")
    parser.add_argument("--marker-filter", type=pdm.noise_arg, default=0.0, metavar="S",
                        help="smooth every performance's markers in time first (σ = S frames, "
                             "or \"auto\": the windows chosen per frame in the modes of each "
                             "model's marker prior; the synthesis job's marker_filter_frames; "
                             "default 0: off)")
    parser.add_argument("--marker-noise", type=pdm.noise_arg, default=0.0, metavar="SIGMA",
                        help="train the PDMs and the shape-space model with marker_noise_mm = "
                             "SIGMA (soft marker constraints; \"auto\": σ estimated per request; "
                             "default 0: exact interpolation)")
    parser.add_argument("--methods", nargs="+", default=None, metavar="NAME",
                        help="only these rows' methods (e.g. 'PDM biquadratic' 'shape space (markers)'); "
                             "no worst-frame figure")
    parser.add_argument("--ranges", nargs="+", default=None, choices=list(RANGES),
                        help="only these input ranges (no worst-frame figure)")
    parser.add_argument("--conditions", nargs="+", default=None, choices=list(CONDITIONS),
                        help="only these marker conditions (no worst-frame figure)")
    parser.add_argument("--pdm-only", action="store_true",
                        help="only the baselines and the PDM rows (no shape-space model)")
    parser.add_argument("--pdm-params", type=json.loads, default=None, metavar="JSON",
                        help="other PdmParams fields of both PDMs, e.g. '{\"neutral_anchor\": false}' "
                             "(cached apart from the defaults)")
    parser.add_argument("--regression", type=regression_arg, nargs="+", default=list(DEFAULT_REGRESSION),
                        metavar="S[:R]",
                        help="a 'WPSD + marker regression' row per value: marker_regression = S (median marker "
                             "spacings), marker_regression_ridge = R (default the field's); default the recommended "
                             f"{RECOMMENDED_MARKER_REGRESSION:g}:{MARKER_REGRESSION_RIDGE:g}")
    parser.add_argument("--pose-space-params", type=json.loads, default=None, metavar="JSON",
                        help="other WpsdParams fields, e.g. '{\"posterior_noise\": \"frame\"}': every "
                             "pose-space row also with them (named with the fields appended; cached apart)")
    parser.add_argument("--split", action="store_true",
                        help="beside each PDM, pose-space and shape-space row, the detail error of its mesh "
                             "with the truth's map and of the truth's mesh with its map")
    parser.add_argument("--out", type=Path, default=OUT, metavar="DIR",
                        help=f"where the report and figures go (default {OUT}; the models stay cached there)")
    args = parser.parse_args()
    defaults = {"a": pdm.actor_dir("a", 0), "b": pdm.actor_dir("b", 0)}
    actors = {} if args.actor else defaults
    for item in args.actor:                      # given: only those families
        family, _, path = item.partition("=")
        if family not in defaults or not path:
            parser.error(f"--actor wants a=DIR or b=DIR, got {item!r}")
        actors[family] = Path(path)
    t0 = time.perf_counter()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    MODELS.mkdir(parents=True, exist_ok=True)
    pdm.SHAPE_SPACE_MODELS.mkdir(parents=True, exist_ok=True)
    frames = args.frames or None
    results = {}
    for family, actor_dir in actors.items():
        actor_dir = actor_dir.resolve()
        pdm.ensure_actor(actor_dir, level=0, family=family, with_tracking=False)
        print(f"family {family}: {actor_dir}", file=sys.stderr)
        only = None if args.methods is None else set(args.methods)
        results[family] = evaluate_family(family, actor_dir, frames, args.retrain, args.marker_filter,
                                          args.marker_noise, not args.pdm_only and (
                                              only is None or SS_MARKERS in only or SS_RIG in only),
                                          args.pdm_params, only, args.ranges, args.conditions,
                                          None if args.pdm_only else pose_space_variants(args.regression,
                                                                                         args.pose_space_params),
                                          args.split)
        if results[family]["worst"] is not None:
            plot_worst(results[family], family, out / f"worst_family_{family}.png")
    settings = [f"Markers filtered in time: {args.marker_filter}." if args.marker_filter else "",
                f"PDMs and shape space trained with marker_noise_mm {args.marker_noise}." if args.marker_noise else "",
                f"PDM params {json.dumps(args.pdm_params)}." if args.pdm_params else ""]
    text = report(results, frames, time.perf_counter() - t0, " ".join(x for x in settings if x))
    print(text)
    (out / "report.md").write_text(text)
    (out / "report.json").write_text(json.dumps(
        {f: {" / ".join(k): v for k, v in r["rows"].items()} for f, r in results.items()}, indent=1))


if __name__ == "__main__":
    main()

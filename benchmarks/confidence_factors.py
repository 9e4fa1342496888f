"""Confidence factors (issue 17): which per-frame input terms make the PDM's confidence rank its error.

For each actor family, the PDM biquadratic of ``generalization_report.py`` (trained with
``--marker-noise`` 0 or ``auto``, cached in the same place) synthesizes the held-out map
frames of every input range × marker condition (clean, σ = 0.3 mm noisy, occluded) once,
mesh only, and the *no detail* fallback (the thin shell of the detailed neutral driven by
the same denoised handles, the PDM's medium fallback). Per frame it records

* the face-region mean and max vertex error of the PDM and of the fallback;
* the *range* confidence (the validity's, :meth:`service.methods.pdm.validity.Validity.confidence`)
  and the confidence the model reports;
* the *noise factor* ``n`` (:func:`service.geometry.marker_prior.noise_confidence` of the
  frame's σ̂, :func:`~service.geometry.marker_prior.frame_noise`);
* the *size factor* ``g`` of the frame's handle displacements u_H
  (:meth:`service.methods.confidence.MarkerEvidence.size_factor`; with ``size_mm`` ‖u_H‖
  and ``scale_mm`` the prior's RMS size s);
* occlusion candidates: ``visible`` (the fraction of markers seen), ``energy`` (1 − the
  share of the frame's completed displacement energy Σ‖u_m‖² that lies on occluded markers,
  the prior's conditional mean filling them), ``variance`` (1 − the prior's conditional
  variance of the occluded coordinates given the visible ones over the prior's total
  variance).

It prints Spearman ρ of ``1 − confidence`` against the per-frame mean error per range (the
three marker conditions pooled) for each candidate product, and the mean / max error of the
PDM when its detail is additionally faded toward the fallback by a candidate factor
``g`` (``V_fb + g (V_pdm − V_fb)``: what the fade would do if it used the factor too;
it multiplies the validity's per-point weights, so this is exact for the mesh).

Run: ``python benchmarks/confidence_factors.py [--actor a=DIR] [--actor b=DIR] [--frames 8]
[--marker-noise 0|auto] [--json PATH] [--models DIR]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import harness as pdm  # noqa: E402  (the generalization report's models, ranges and markers)

DEFAULT_FRAMES = 8        # as generalization_report.py

CANDIDATES = {            # name → factor of (range r, noise n, occlusion terms o) per frame
    "range": lambda r, n, o: r,
    "range·noise": lambda r, n, o: r * n,
    "range·noise·visible": lambda r, n, o: r * n * o["visible"],
    "range·noise·energy": lambda r, n, o: r * n * o["energy"],
    "range·noise·variance": lambda r, n, o: r * n * o["variance"],
    "range·noise·size": lambda r, n, o: r * n * o["size"],
    "reported (this tree)": lambda r, n, o: o["reported"],
}
BOOTSTRAP = 2000          # paired bootstrap resamples of the frames (Δρ of a candidate)
FADES = {                 # extra fade factor g of the detail toward the fallback
    "none": lambda n, o: np.ones_like(n),
    "noise": lambda n, o: n,
    "noise·energy": lambda n, o: n * o["energy"],
    "noise·visible": lambda n, o: n * o["visible"],
}


def occlusion_terms(prior, eigen, u: np.ndarray) -> dict:
    """Per-frame occlusion candidates (F,) of aligned displacements u (F,M,3), NaN occluded."""
    from service.geometry.marker_prior import FILL_NOISE_MM

    seen = np.isfinite(u).all(axis=2)                                        # (F,M)
    x = eigen.map(u, FILL_NOISE_MM) if not seen.all() else u
    e = (x ** 2).sum(axis=2)                                                  # (F,M)
    energy = 1.0 - (e * ~seen).sum(axis=1) / np.maximum(e.sum(axis=1), 1e-300)
    C = prior.covariance
    var = np.ones(len(u))
    for f in np.flatnonzero(~seen.all(axis=1)):
        occ = np.repeat(~seen[f], 3)
        Cuu, Cuv, Cvv = C[np.ix_(occ, occ)], C[np.ix_(occ, ~occ)], C[np.ix_(~occ, ~occ)]
        cond = Cuu - Cuv @ np.linalg.solve(Cvv, Cuv.T)
        var[f] = 1.0 - np.trace(cond) / np.trace(C)
    return {"visible": seen.mean(axis=1), "energy": energy, "variance": var}


def family_frames(family: str, actor_dir: Path, frames: int | None, noise,
                  models_dir: Path = pdm.GENERALIZATION_MODELS) -> list[dict]:
    from service.geometry.marker_prior import PriorEigen, frame_noise, noise_confidence
    from service.methods.confidence import MarkerEvidence
    from service.methods.pdm.base_surface import BaseSurface, head_alignment
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    model = pdm.generalization_pdm_models(actor_dir, False, noise, None, ["biquadratic"], models_dir)["biquadratic"]
    ev = model.evaluator
    prior = ev.base.marker_prior
    eigen = PriorEigen.of(prior)
    evidence = MarkerEvidence.of(prior, eigen)
    det = BaseSurface.from_smooth(actor.vertices, actor.faces, actor.uv, actor.uv_faces, ev.base.handles,
                                  ev.base.rest_markers)
    face = np.asarray(actor.regions[pdm.FACE])
    rows = []
    for rname, perf in pdm.HELDOUT_RANGES.items():
        gt = pdm.heldout_frames(actor_dir, perf, frames)
        for cname, suffix in pdm.MARKER_CONDITIONS.items():
            markers = pdm.variant_markers(actor_dir, perf + suffix, gt.frames)
            out = model.synthesize(markers, ("mesh",))
            base, _ = ev.request_base(markers)
            pose, u_H, S = ev.deformation(markers, base)
            d1, d2, _ = ev.vertex_band.parameters(S, None)
            r = ev.validity.confidence(ev.validity.gauge(d1, d2))[0].astype(np.float64)   # the range's
            V_fb = pose.restore(det.deform(u_H))
            V = out["vertices"].astype(np.float64)
            p = head_alignment(markers, ev.base.rest_markers, model.data.pose_weights)
            u = p.remove(markers) - ev.base.rest_markers
            sigma = frame_noise(prior, u)
            n = noise_confidence(prior, sigma)
            reported = out["confidence"].astype(np.float64)
            o = occlusion_terms(prior, eigen, u)
            o["size"] = evidence.size_factor(u_H)
            err = lambda W: np.linalg.norm(W - gt.vertices, axis=-1)[:, face]          # noqa: E731
            fades = {}
            for g_name, g in FADES.items():
                gv = g(n, o)[:, None, None]
                e = err(V_fb + gv * (V - V_fb))
                fades[g_name] = {"mean": e.mean(axis=1).tolist(), "max": e.max(axis=1).tolist()}
            rows.append({"family": family, "range": rname, "condition": cname, "range_conf": r.tolist(), "reported": reported.tolist(),
                         "noise": n.tolist(), "sigma": sigma.tolist(),
                         "size_mm": np.sqrt((u_H ** 2).sum(axis=(1, 2))).tolist(), "scale_mm": evidence.scale_mm, **{k: v.tolist() for k, v in o.items()},
                         "fallback_mean": err(V_fb).mean(axis=1).tolist(), "fades": fades})
            print(f"  {family} {rname} {cname}: σ̂ {np.median(sigma):.3f}, error "
                  f"{np.mean(fades['none']['mean']):.3f} mm", file=sys.stderr, flush=True)
    return rows


def spearman(c: np.ndarray, e: np.ndarray) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(1.0 - c, e).statistic) if np.ptp(c) > 0 and np.ptp(e) > 0 else float("nan")


def paired_bootstrap(c: np.ndarray, c0: np.ndarray, e: np.ndarray, draws: int = BOOTSTRAP,
                     seed: int = 0) -> tuple[float, float]:
    """5 % and 95 % quantiles of ρ(c) − ρ(c0) over ``draws`` resamples of the frames (paired)."""
    rng = np.random.default_rng(seed)
    d = []
    for _ in range(draws):
        k = rng.integers(0, len(e), len(e))
        d.append(spearman(c[k], e[k]) - spearman(c0[k], e[k]))
    return tuple(np.nanpercentile(d, [5, 95]))


def summary(rows: list[dict]) -> str:
    lines = []
    for family in dict.fromkeys(r["family"] for r in rows):
        fr = [r for r in rows if r["family"] == family]
        ranges = list(dict.fromkeys(r["range"] for r in fr)) + ["all"]
        lines += [f"## family {family}: Spearman ρ(1 − confidence, frame mean error), conditions pooled "
                  f"[paired bootstrap 5–95 % of Δρ against range·noise]", "",
                  "| confidence | " + " | ".join(ranges) + " |", "|---|" + "---|" * len(ranges)]

        def pooled(cand, rn):
            sel = [r for r in fr if rn in ("all", r["range"])]
            c = np.concatenate([cand(np.asarray(r["range_conf"]), np.asarray(r["noise"]),
                                     {k: np.asarray(r[k]) for k in ("visible", "energy", "variance", "reported", "size")})
                                for r in sel])
            return c, np.concatenate([r["fades"]["none"]["mean"] for r in sel])

        for name, cand in CANDIDATES.items():
            vals = []
            for rn in ranges:
                c, e = pooled(cand, rn)
                cell = f"{spearman(c, e):.2f} ({len(e)})"
                if name not in ("range", "range·noise", "reported (this tree)"):
                    lo, hi = paired_bootstrap(c, pooled(CANDIDATES["range·noise"], rn)[0], e)
                    cell += f" [{lo:+.2f}, {hi:+.2f}]"
                vals.append(cell)
            lines.append(f"| {name} | " + " | ".join(vals) + " |")
        lines += ["", f"## family {family}: PDM mean / max error (mm) with the detail also faded by g", "",
                  "| range | condition | fallback | " + " | ".join(FADES) + " |", "|---|---|---|" + "---|" * len(FADES)]
        for r in fr:
            lines.append(f"| {r['range']} | {r['condition']} | {np.mean(r['fallback_mean']):.3f} | " + " | ".join(
                f"{np.mean(r['fades'][g]['mean']):.3f} / {np.max(r['fades'][g]['max']):.2f}" for g in FADES) + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", action="append", default=[], metavar="FAMILY=DIR")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES)
    parser.add_argument("--marker-noise", type=pdm.noise_arg, default=0.0)
    parser.add_argument("--json", type=Path, default=None, help="also write the per-frame rows here")
    parser.add_argument("--models", type=Path, default=pdm.GENERALIZATION_MODELS,
                        help="the PDMs' cache (default the generalization report's)")
    args = parser.parse_args()
    actors = {"a": pdm.actor_dir("a", 0), "b": pdm.actor_dir("b", 0)}
    if args.actor:
        actors = {f: Path(p) for f, _, p in (a.partition("=") for a in args.actor)}
    rows = []
    for family, actor_dir in actors.items():
        pdm.ensure_actor(actor_dir.resolve(), level=0, family=family, with_tracking=False)
        rows += family_frames(family, actor_dir.resolve(), args.frames or None, args.marker_noise, args.models)
    if args.json:
        args.json.write_text(json.dumps(rows))
    print(f"# marker_noise_mm = {args.marker_noise}\n")
    print(summary(rows))


if __name__ == "__main__":
    main()

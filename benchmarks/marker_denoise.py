"""Marker denoising (issue 17, failure mode 4): how much marker noise reaches the thin shell.

For each actor family and held-out performance (clean and σ = 0.3 mm noisy markers), the
detailed neutral is deformed to the markers by the thin shell (the *no detail* row of the
generalization report) with

* the soft marker constraints of :func:`service.geometry.thin_shell.soft_handles`, the MAP
  weight from an assumed noise ``σ_param`` (mm) and the shell prior's scale τ estimated on
  the family's training frames (:func:`~service.geometry.thin_shell.shell_prior_scale`);
* optionally the temporal filter of :mod:`service.geometry.marker_filter` over the whole
  performance (window s frames) before it.

It prints the face-region mean vertex error against the ground truth (``vs truth``) and
against the same shell driven by the clean markers with exact interpolation (``vs clean
shell``: the noise that reaches the surface), averaged over the in-range, combination and
out-of-range performances. It needs no trained model, so it runs in a minute per family:
the place to choose ``marker_noise_mm``'s default (on family a, confirmed on family b).

Run: ``python benchmarks/marker_denoise.py --actor a=benchmarks/out/actor-a-l0 [--actor b=DIR]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PERFORMANCES = ("heldout_in_range", "heldout_combinations", "heldout_amplified")
SIGMAS = (0.0, 0.1, 0.2, 0.3, 0.45)
WINDOWS = (0.0, 1.0, 2.0, 3.0)


def family_table(actor_dir: Path, sigmas=SIGMAS, windows=WINDOWS) -> list[tuple]:
    from service.geometry.marker_filter import filter_performance
    from service.geometry.thin_shell import marker_noise_ratio, shell_prior_scale, soft_handle_operator, soft_handles
    from service.methods.pdm.base_surface import BaseSurface, handle_vertices, head_alignment, training_head_pose
    from service.samples.dataset import load_actor, performance_names

    actor = load_actor(actor_dir)
    F = np.asarray(actor.faces, np.int64)
    rest = actor.marker_positions()
    train = np.concatenate([np.load(actor_dir / "performances" / f"{n}.npz")["markers"]
                            for n in performance_names(actor_dir, "train_")]).astype(np.float64)
    pose, weights = training_head_pose(train, rest, ["frame"] * len(train))
    handles = handle_vertices(F, actor.marker_triangle, actor.marker_barycentric)
    base = BaseSurface.from_smooth(actor.vertices, F, actor.uv, actor.uv_faces, handles, rest)
    G = base.energy
    tau = shell_prior_scale(G, base.handle_displacements(pose.remove(train)))
    face = np.asarray(actor.regions["face"])
    rows = []
    acc: dict = {}
    for perf in PERFORMANCES:
        with np.load(actor_dir / "performances" / f"{perf}.npz") as d:
            clean, truth = d["markers"].astype(np.float64), d["vertices"].astype(np.float64)
        noisy = np.load(actor_dir / "performances" / f"{perf}_noisy.npz")["markers"].astype(np.float64)
        p_clean = head_alignment(clean, rest, weights)
        ref = base.deform(base.handle_displacements(p_clean.remove(clean)))
        gt = p_clean.remove(truth)
        for cname, m in (("clean", clean), ("noisy", noisy)):
            for s in windows:
                mf = filter_performance(m, s) if s else m
                p = head_alignment(mf, rest, weights)
                a = p.remove(mf) - rest
                for sig in sigmas:
                    lam = marker_noise_ratio(sig, tau)
                    X = base.deform(soft_handles(G, a, lam, soft_handle_operator(G, lam)))
                    X = p_clean.remove(p.restore(X))      # same frame as the truth
                    e_gt = np.linalg.norm(X - gt, axis=-1)[:, face].mean()
                    e_ref = np.linalg.norm(X - ref, axis=-1)[:, face].mean()
                    acc.setdefault((cname, s, sig), []).append((e_gt, e_ref))
    for (cname, s, sig), v in acc.items():
        v = np.asarray(v)
        rows.append((cname, s, sig, *v.mean(axis=0), *v[:, 0]))
    return tau, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", action="append", required=True, metavar="FAMILY=DIR")
    parser.add_argument("--sigmas", type=float, nargs="+", default=SIGMAS, help="σ_param values, mm")
    parser.add_argument("--windows", type=float, nargs="+", default=WINDOWS, help="temporal s values, frames")
    args = parser.parse_args()
    for item in args.actor:
        family, _, path = item.partition("=")
        tau, rows = family_table(Path(path), args.sigmas, args.windows)
        print(f"\n## family {family} ({path}); shell prior scale τ = {tau:.4f} mm\n")
        print("| markers | temporal s (frames) | σ_param mm | vs truth mm | vs clean shell mm | "
              + " | ".join(PERFORMANCES) + " |")
        print("|---|---|---|---|---|" + "---|" * len(PERFORMANCES))
        for r in rows:
            print(f"| {r[0]} | {r[1]:g} | {r[2]:g} | {r[3]:.3f} | {r[4]:.3f} | "
                  + " | ".join(f"{x:.3f}" for x in r[5:]) + " |", flush=True)


if __name__ == "__main__":
    main()

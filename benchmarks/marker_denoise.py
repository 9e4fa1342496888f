"""Marker denoising (issue 17, failure mode 4): how much marker noise reaches the thin shell.

For each actor family and held-out performance (clean and σ = 0.3 mm noisy markers), the
detailed neutral is deformed to the markers by the thin shell (the *no detail* row of the
generalization report) with

* the soft marker constraints of :func:`service.geometry.thin_shell.soft_handles`, the MAP
  weight from an assumed noise ``σ_param`` (mm) and the shell prior's scale τ estimated on
  the family's training frames (:func:`~service.geometry.thin_shell.shell_prior_scale`);
* optionally the temporal filter of :mod:`service.geometry.marker_filter` over the whole
  performance (window s frames) before it;
* the learned marker priors of :mod:`service.geometry.marker_prior`, fitted on the
  family's head-aligned training displacements, alone (β = 0) or with the shell prior
  (β = 1): probabilistic PCA with its isotropic variance floored at a fraction f of the
  mean per-coordinate variance (rows ``ppca f=… β=…``), and the tapered covariance
  (the service's prior; length ℓ × the rest markers' RMS radius, diagonal floor f; rows
  ``tapered ℓ=… f=… β=…``).

Marker sets: clean, σ = 0.3 mm noisy, and occluded (the performances' ``_occluded`` files,
clean markers with NaN bursts). It prints the face-region mean vertex error against the ground truth (``vs truth``) and
against the same shell driven by the clean markers with exact interpolation (``vs clean
shell``: the noise that reaches the surface), averaged over the in-range, combination and
out-of-range performances. It needs no trained model, so it runs in a minute per family:
the place to choose ``marker_noise_mm``'s default (on family a, confirmed on family b).

``--auto-filter`` prints instead the table of :mod:`service.geometry.marker_filter`'s
docstring: the job's ``marker_filter_frames: "auto"`` per marker coordinate against per mode
of the learned prior, each followed by the methods' own head alignment and per-frame MAP at
the take's σ̂ (``marker_noise_mm: "auto"``), against the shell of the clean markers; and,
on the noisy takes, the same per mode with each window chosen by its true error instead of
SURE (``truth=``, the clean markers): how far any choice among these windows could go.

Run: ``python benchmarks/marker_denoise.py --actor a=benchmarks/out/actor-a-l0 [--actor b=DIR]
[--prior-source train|database] [--auto-filter]`` (``database``: the priors fitted on the ``database``
performance, as shape space fits its own).
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
FLOORS = (0.03, 0.1)
LENGTHS = (0.5, 0.75, 1.0, 1.5)
TAPER_FLOORS = (0.003, 0.01, 0.03)
BETAS = (0.0, 1.0)


def _family(actor_dir: Path, prior_source: str = "train"):
    """(actor, the thin shell of its neutral (``BaseSurface``), rest markers (M,3), the
    training clips' head-alignment weights (M,), their head-aligned markers (T,M,3), the
    displacements the learned priors are fitted on (the training clips' or, for
    ``prior_source="database"``, the database performance's) (T',M,3))."""
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
    aligned = pose.remove(train)
    d_train = aligned - rest
    if prior_source == "database":
        db = np.load(actor_dir / "performances" / "database.npz")["markers"].astype(np.float64)
        d_train = head_alignment(db, rest, weights).remove(db) - rest
    elif prior_source != "train":
        raise ValueError(f"prior_source must be 'train' or 'database', got {prior_source!r}")
    return actor, base, rest, weights, aligned, d_train


def auto_filter_table(actor_dir: Path, prior_source: str = "train") -> list[tuple]:
    """``marker_filter_frames: "auto"`` per marker coordinate against per mode of the learned
    tapered prior (:func:`~service.geometry.marker_filter.filter_modes`, with the default
    windows and with :data:`~service.geometry.marker_filter.MODE_BANDWIDTHS`), each followed
    by what every method does with ``marker_noise_mm: "auto"``: its own head alignment and
    the prior's per-frame MAP at the take's σ̂. Rows ``(markers, filter, vs clean shell mm
    averaged over the performances, per performance …)``."""
    from service.geometry import marker_filter
    from service.geometry.marker_prior import AdaptiveDenoiser, MarkerPrior
    from service.methods.pdm.base_surface import head_alignment

    actor, base, rest, weights, _, d_train = _family(actor_dir, prior_source)
    denoiser = AdaptiveDenoiser.build(MarkerPrior.fit_tapered(d_train, rest), base.energy)
    modes = marker_filter.MarkerModes.of(rest, denoiser.prior, weights, denoiser.eigen)
    face = np.asarray(actor.regions["face"])
    filters = {
        "per coordinate": lambda m: marker_filter.filter_performance(m, "auto"),
        "per mode, default windows": lambda m: marker_filter.filter_performance(
            m, "auto", modes=modes, mode_bandwidths=marker_filter.AUTO_BANDWIDTHS),
        "per mode, MODE_BANDWIDTHS": lambda m: marker_filter.filter_performance(m, "auto", modes=modes),
        # the bound of any window choice: the true error in place of SURE (noisy takes)
        "per mode, oracle windows": lambda m: marker_filter.filter_performance(m, "auto", modes=modes,
                                                                               truth=clean)}
    acc: dict = {}
    for perf in PERFORMANCES:
        clean = np.load(actor_dir / "performances" / f"{perf}.npz")["markers"].astype(np.float64)
        truth_pose = head_alignment(clean, rest, weights)
        ref = base.deform(base.handle_displacements(truth_pose.remove(clean)))
        for cname in ("noisy", "clean", "occluded"):
            path = actor_dir / "performances" / (f"{perf}.npz" if cname == "clean" else f"{perf}_{cname}.npz")
            if not path.exists():
                continue
            markers = np.load(path)["markers"].astype(np.float64)
            for fname, fn in filters.items():
                if fname.endswith("oracle windows") and cname != "noisy":
                    continue
                filtered = fn(markers)
                p = head_alignment(filtered, rest, weights)
                X = p.restore(base.deform(denoiser(p.remove(filtered) - rest)))
                err = np.linalg.norm(truth_pose.remove(X) - ref, axis=-1)[:, face].mean()
                acc.setdefault((cname, fname), []).append(err)
    return [(*key, float(np.mean(v)), *v) for key, v in acc.items()]


def family_table(actor_dir: Path, sigmas=SIGMAS, windows=WINDOWS, floors=FLOORS, betas=BETAS,
                 occluded: bool = True, lengths=LENGTHS, taper_floors=TAPER_FLOORS,
                 prior_source: str = "train") -> list[tuple]:
    """(τ, rows, prior info): rows ``(markers, denoiser, s, σ, vs truth, vs clean shell,
    per performance vs truth …, per performance vs clean shell …)``. The learned priors
    are fitted on the ``train_*`` clips (``prior_source="train"``, the PDM's and pose
    space's) or on the ``database`` performance (``"database"``, shape space's), head-aligned
    with the training clips' stability weights."""
    from service.geometry.marker_filter import filter_performance
    from service.geometry.marker_prior import MarkerDenoiser, MarkerPrior
    from service.geometry.thin_shell import marker_noise_ratio, shell_prior_scale, soft_handle_operator, soft_handles
    from service.methods.pdm.base_surface import head_alignment

    actor, base, rest, weights, train_aligned, d_train = _family(actor_dir, prior_source)
    G = base.energy
    tau = shell_prior_scale(G, base.handle_displacements(train_aligned))
    priors = {f"ppca f={f:g}": MarkerPrior.fit_ppca(d_train, f) for f in floors}
    priors.update({f"tapered ℓ={ell:g} f={f:g}": MarkerPrior.fit_tapered(d_train, rest, ell, f)
                   for ell in lengths for f in taper_floors})
    denoisers = {}
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
        sets = [("clean", clean), ("noisy", noisy)]
        occ = actor_dir / "performances" / f"{perf}_occluded.npz"
        if occluded and occ.exists():
            sets.append(("occluded", np.load(occ)["markers"].astype(np.float64)))

        def score(key, X, p):
            X = p_clean.remove(p.restore(X))      # same frame as the truth
            e_gt = np.linalg.norm(X - gt, axis=-1)[:, face].mean()
            e_ref = np.linalg.norm(X - ref, axis=-1)[:, face].mean()
            acc.setdefault(key, []).append((e_gt, e_ref))

        for cname, m in sets:
            for s in windows:
                mf = filter_performance(m, s) if s else m
                p = head_alignment(mf, rest, weights)
                a = p.remove(mf) - rest
                for sig in sigmas:
                    lam = marker_noise_ratio(sig, tau)
                    score((cname, "shell", s, sig), base.deform(soft_handles(G, a, lam, soft_handle_operator(G, lam))), p)
                    if s:
                        continue
                    for name, prior in priors.items():
                        for beta in betas:
                            key = (name, beta, sig)
                            if key not in denoisers:
                                denoisers[key] = MarkerDenoiser.build(prior, G, sig, tau, beta)
                            score((cname, f"{name} β={beta:g}", s, sig), base.deform(denoisers[key](a)), p)
    for key, v in acc.items():
        v = np.asarray(v)
        rows.append((*key, *v.mean(axis=0), *v[:, 0], *v[:, 1]))
    return tau, rows, {}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", action="append", required=True, metavar="FAMILY=DIR")
    parser.add_argument("--sigmas", type=float, nargs="+", default=SIGMAS, help="σ_param values, mm")
    parser.add_argument("--windows", type=float, nargs="+", default=WINDOWS, help="temporal s values, frames")
    parser.add_argument("--floors", type=float, nargs="*", default=FLOORS,
                        help="learned prior's eigenvalue floor, fractions of the mean variance (none: no prior rows)")
    parser.add_argument("--lengths", type=float, nargs="*", default=LENGTHS,
                        help="tapered prior's length, fractions of the rest markers' RMS radius")
    parser.add_argument("--taper-floors", type=float, nargs="*", default=TAPER_FLOORS,
                        help="tapered prior's diagonal floor, fractions of the mean variance")
    parser.add_argument("--betas", type=float, nargs="+", default=BETAS, help="shell prior weights beside the learned prior")
    parser.add_argument("--no-occluded", action="store_true", help="skip the occluded marker sets")
    parser.add_argument("--prior-source", choices=("train", "database"), default="train",
                        help="fit the learned priors on the train_* clips (PDM, pose space; default) "
                             "or on the database performance (shape space)")
    parser.add_argument("--auto-filter", action="store_true",
                        help="only the table of marker_filter_frames \"auto\" per coordinate against "
                             "per mode of the learned prior (service/geometry/marker_filter.py)")
    args = parser.parse_args()
    for item in args.actor:
        family, _, path = item.partition("=")
        if args.auto_filter:
            short = [p.removeprefix("heldout_") for p in PERFORMANCES]
            print(f"\n## family {family} ({path}): \"auto\" filter, then σ̂ MAP; prior fitted on "
                  f"{args.prior_source}; vs clean shell, face mean mm\n")
            print("| markers | filter | mean | " + " | ".join(short) + " |")
            print("|---|---|---|" + "---|" * len(short))
            for r in auto_filter_table(Path(path), args.prior_source):
                print(f"| {r[0]} | {r[1]} | {r[2]:.4f} | " + " | ".join(f"{x:.4f}" for x in r[3:]) + " |", flush=True)
            continue
        tau, rows, info = family_table(Path(path), args.sigmas, args.windows, args.floors, args.betas,
                                       not args.no_occluded, args.lengths, args.taper_floors, args.prior_source)
        print(f"\n## family {family} ({path}); shell prior scale τ = {tau:.4f} mm; learned priors "
              f"fitted on {args.prior_source}\n")
        short = [p.removeprefix("heldout_") for p in PERFORMANCES]
        print("\n| markers | denoiser | temporal s (frames) | σ_param mm | vs truth mm | vs clean shell mm | "
              + " | ".join(f"{p} vs truth" for p in short) + " | " + " | ".join(f"{p} vs clean" for p in short) + " |")
        print("|---|---|---|---|---|---|" + "---|" * (2 * len(PERFORMANCES)))
        for r in rows:
            print(f"| {r[0]} | {r[1]} | {r[2]:g} | {r[3]:g} | {r[4]:.3f} | {r[5]:.3f} | "
                  + " | ".join(f"{x:.3f}" for x in r[6:]) + " |", flush=True)


if __name__ == "__main__":
    main()

"""Before/after check of the PDM's data/evaluator split (issue 15): bit identity of every
synthesized array on a small seeded model, load time and ms/frame of a level-0 model.

Subcommands (each runs the library of the current directory: run it from the source tree
to measure, e.g. a ``git archive`` of the commit before the change for "before"):

* ``bits OUT_DIR``: builds a seeded level-0 sample actor (seed 2, 128² maps, as the test
  fixture), trains two PDMs (medium 256², fine 512², with albedo; validity on, the default,
  and off), saves them under ``OUT_DIR/model-{on,off}``, and writes ``OUT_DIR/outputs.npz``:
  every array of ``synthesize`` for mesh + mesh_detailed + displacement + normal_map + albedo,
  clamp on and off, of held-out frames, the same frames exaggerated 3× (outside the
  validity region) and with occluded (NaN) markers. ``--load DIR`` instead loads the models
  saved by an earlier run (an older library's model directories) and synthesizes from them;
  ``--block N`` sets the blocked evaluation's points per block (many blocks on small maps).
* ``compare A.npz B.npz``: ``np.array_equal`` per array (and the max abs difference of any
  that differ); exit status 1 when any differs.
* ``timing MODEL_DIR ACTOR_DIR``: load time (median of ``--loads``) and in-process ms/frame
  (median of ``--calls`` one-frame calls, after 3 warm-up calls) for ``mesh`` and
  ``mesh + displacement + normal_map`` on the first 50 frames of ``heldout_in_range``.
* ``train ACTOR_DIR MODEL_DIR``: the default-parameter PDM of an actor (for ``timing``).
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
import harness  # noqa: E402

sys.path.insert(0, os.getcwd())      # the library measured: the current directory's

TRAINING = ("train_brow_raise", "train_brow_furrow", "train_smile", "train_surprise",
            "train_sneer", "train_pucker")
OUTPUTS = ("mesh", "mesh_detailed", "displacement", "normal_map", "albedo")
OUTPUT_SETS = {"mesh": ("mesh",), "mesh + displacement + normal_map": ("mesh", "displacement", "normal_map")}


def check_markers(actor_dir: Path, actor) -> np.ndarray:
    """(18,M,3): 6 held-out frames, the same exaggerated 3× about the rest markers, and the
    same with a third of the markers occluded (NaN) in a frame-dependent pattern."""
    from service.samples import dataset

    m = dataset.load_clip(actor_dir, "heldout_out_of_range", actor).markers[::7][:6].astype(np.float64)
    rest = actor.marker_positions()
    far = rest + 3.0 * (m - rest)
    occ = m.copy()
    rng = np.random.default_rng(5)
    for f in range(len(occ)):
        occ[f, rng.choice(occ.shape[1], occ.shape[1] // 3, replace=False)] = np.nan
    return np.concatenate([m, far, occ])


def bits(out: Path, load: Path | None, block: int | None) -> int:
    from service.methods.pdm import texel_band
    from service.methods.pdm.model import PdmModel, PdmParams, train

    if block:
        texel_band.BLOCK_POINTS = block
    from service.samples import dataset
    from service.samples.actor import build_sample_actor

    out.mkdir(parents=True, exist_ok=True)
    actor_dir = out / "actor"
    if not (actor_dir / "manifest.json").is_file():
        build_sample_actor(actor_dir, seed=2, level=0, with_tracking=False, map_resolution=128,
                           performance_names=TRAINING + ("heldout_out_of_range",))
    actor = dataset.load_actor(actor_dir)
    markers = check_markers(actor_dir, actor)
    arrays = {}
    for name, width in (("on", PdmParams().validity_width), ("off", None)):
        if load is not None:
            t0 = time.perf_counter()
            model = PdmModel.load(load / f"model-{name}")
            print(f"loaded {name} in {time.perf_counter() - t0:.2f} s", file=sys.stderr)
        else:
            clips = [dataset.load_clip(actor_dir, c, actor) for c in TRAINING]
            model = train(actor, clips, PdmParams(medium_resolution=256, fine_resolution=512,
                                                  validity_width=width))
            model.save(out / f"model-{name}")
        for clamp in (True, False):
            res = model.synthesize(markers, OUTPUTS, clamp=clamp)
            for key, value in res.items():
                arrays[f"{name}/clamp={clamp}/{key}"] = value
    np.savez(out / "outputs.npz", **arrays)
    print(f"{len(arrays)} arrays -> {out / 'outputs.npz'}", file=sys.stderr)
    return 0


def compare(a: Path, b: Path) -> int:
    A, B = np.load(a), np.load(b)
    bad = 0
    for key in sorted(set(A.files) | set(B.files)):
        if key not in A.files or key not in B.files:
            print(f"| {key} | missing in {'A' if key not in A.files else 'B'} |")
            bad += 1
            continue
        x, y = A[key], B[key]
        same = x.shape == y.shape and np.array_equal(x, y, equal_nan=True)
        diff = "" if same or x.shape != y.shape else f"{np.nanmax(np.abs(x.astype(np.float64) - y)):.3g}"
        print(f"| {key} | {x.shape} | {'equal' if same else 'DIFFERENT'} | {diff} |")
        bad += not same
    print(f"{len(A.files)} arrays, {bad} differ")
    return 1 if bad else 0


def timing(model_dir: Path, actor_dir: Path, loads: int, calls: int) -> int:
    from service.methods.pdm.model import PdmModel

    with np.load(actor_dir / "performances" / "heldout_in_range.npz") as d:
        markers = d["markers"][:50].astype(np.float32)
    load_s = []
    for _ in range(loads):
        t0 = time.perf_counter()
        model = PdmModel.load(model_dir)
        load_s.append(time.perf_counter() - t0)
    rec = {"load_s": float(np.median(load_s)), "loads": load_s, "loadavg": os.getloadavg()}
    for name, outputs in OUTPUT_SETS.items():
        rec[name] = harness.median_ms(lambda k: model.synthesize(markers[k % len(markers)][None], outputs), calls)
    print(json.dumps(rec))
    return 0


def train_default(actor_dir: Path, model_dir: Path) -> int:
    print(json.dumps(harness.train_pdm(actor_dir, "biquadratic", model_dir)))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("bits")
    b.add_argument("out", type=Path)
    b.add_argument("--load", type=Path, default=None)
    b.add_argument("--block", type=int, default=None, help="texel_band.BLOCK_POINTS (default: the library's)")
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    t = sub.add_parser("timing")
    t.add_argument("model", type=Path)
    t.add_argument("actor", type=Path)
    t.add_argument("--loads", type=int, default=3)
    t.add_argument("--calls", type=int, default=30)
    r = sub.add_parser("train")
    r.add_argument("actor", type=Path)
    r.add_argument("model", type=Path)
    a = p.parse_args(argv)
    if a.cmd == "bits":
        return bits(a.out, a.load, a.block)
    if a.cmd == "compare":
        return compare(a.a, a.b)
    if a.cmd == "timing":
        return timing(a.model, a.actor, a.loads, a.calls)
    return train_default(a.actor, a.model)


if __name__ == "__main__":
    sys.exit(main())

"""Shape-space ``/enhance`` speed (issue 23): a 30-frame request batched vs frame by frame.

A trained shape-space model (default parameters) of a sample actor enhances ``--frames``
held-out frames (``vertices_medium`` of ``heldout_in_range``, vertex input) two ways,
alternating ``--rounds`` times in one process:

* **batched**: one ``ShapeSpaceModel.enhance(frames)`` call (the per-triangle work of up
  to ``ENHANCE_BATCH_TRIANGLES`` triangles × frames at a time, solves frame by frame);
* **per frame**: ``enhance(frames[f:f+1])`` for every frame.

With ``--against REV`` the same model directory is also enhanced by commit REV's code
(``harness.renamed_package``: its ``service`` imported beside this tree's), paired: each
round's two batched calls in alternating order, the per-frame calls interleaved frame by
frame (the machine is shared: only such pairs compare), and both trees' batched outputs
compared bit for bit. Per-frame answers are kept until the round ends, as a batch's are (a
caller holds what it asked for: both pay the first touch of their outputs' memory).

Reported per output set: seconds per frame of CPU (``time.process_time``) and wall time,
the load average beside each, the rate in vertices per second against bermano2014 §7
(30 s/frame at 500k vertices: 16,667 vertices/s; issue 23's target ≥ 15× that, i.e.
≤ 0.2 s/frame at level 1), and whether the batched arrays equal the per-frame ones bit for
bit. Also the model's load time and its cache weight (``footprint.nbytes``) against the
service's default budget.

Run: ``python benchmarks/enhance_speed.py [--model DIR] [--actor DIR] [--frames 30]
[--rounds 2] [--against REV]`` (``make bench``); without ``--model`` the model is harness.py's cached build
(minutes and ~8 GB at level 1 the first time). BLAS threads: ``facesynth serve``'s, set
before NumPy loads (cores ÷ synthesis slots, ``service.app.threads``: 1 on 2 cores; an
``OPENBLAS_NUM_THREADS`` already set is kept). With OpenBLAS's default of one per core the
idle second thread's spin-wait billed 0.32 against 0.20 s CPU per frame (mesh +
displacement, level 1, load 5.4). Writes the
table to stdout and ``benchmarks/out/enhance_speed.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from service.app.threads import apply_blas_threads  # noqa: E402

#: serve's BLAS threads, set before NumPy loads (module docstring)
BLAS_THREADS = apply_blas_threads(None, None)
OUT = ROOT / "benchmarks" / "out"

import numpy as np  # noqa: E402

PAPER_VERTICES_PER_S = 500_000 / 30.0          # bermano2014 §7
TARGET_FACTOR = 15.0
OUTPUT_SETS = {"mesh": ("mesh",), "mesh + displacement": ("mesh", "displacement")}


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def timed(fn):
    c, w = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c, time.perf_counter() - w


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None,
                        help="shape-space model directory (default: harness.py's cached build of "
                             "the actor's default-parameter model, built in a fresh process if missing)")
    parser.add_argument("--actor", type=Path, default=OUT / "actor-l1")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--against", metavar="REV", default=None,
                        help="also the model of this older commit's code, paired: batches alternating, "
                             "per-frame calls interleaved frame by frame (module docstring)")
    args = parser.parse_args(argv)

    import importlib

    from service.config import Settings
    from service.methods.footprint import nbytes
    from service.methods.kinds import get_kind
    from service.methods.shape_space import ShapeSpaceModel, ShapeSpaceParams

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import harness

    if args.model is None:
        args.model = harness.shape_space_model(args.actor.resolve(), ShapeSpaceParams(), False)[0]

    model, load_cpu, load_wall = timed(lambda: ShapeSpaceModel.load(args.model))
    weight = nbytes(model, mapped=get_kind("shape_space").weighs_mapped)  # as the service weighs it
    models = {"this tree": model}
    if args.against:
        old = importlib.import_module(harness.renamed_package(args.against) + ".methods.shape_space.model")
        models = {args.against: old.ShapeSpaceModel.load(args.model), **models}
    with np.load(args.actor / "performances" / "heldout_in_range.npz") as d:
        frames = d["vertices_medium"][:args.frames].astype(np.float64)
    n, F = model.n_vertices, len(frames)
    for m in models.values():
        m.enhance(frames[:1])                                   # warm-up
    rows, identical = [], []
    for name, outputs in OUTPUT_SETS.items():
        equal = {tree: True for tree in models}
        same_trees = True
        for r in range(args.rounds):
            order = list(models) if r % 2 == 0 else list(reversed(models))
            batched = {}
            for tree in order:
                batched[tree], c, w = timed(lambda: models[tree].enhance(frames, outputs))
                rows.append((name, tree, "batched", c / F, w / F, load()))
            cpu, wall = dict.fromkeys(models, 0.0), dict.fromkeys(models, 0.0)
            single = {tree: [] for tree in models}
            for f in range(F):                  # frame by frame, the trees alternating
                for tree in (order if f % 2 == 0 else order[::-1]):
                    out, c, w = timed(lambda: models[tree].enhance(frames[f:f + 1], outputs))
                    single[tree].append(out)
                    cpu[tree] += c
                    wall[tree] += w
            for tree in order:
                rows.append((name, tree, "per frame", cpu[tree] / F, wall[tree] / F, load()))
            for tree in models:
                for key, value in batched[tree].items():
                    if key in ("faces", "region_names"):
                        continue
                    equal[tree] &= all(np.array_equal(value[f], s[key][0]) for f, s in enumerate(single[tree]))
                    same_trees &= all(np.array_equal(value, b[key]) for b in batched.values())
            del batched, single
        identical += [(name, f"{tree}: batched = per frame", equal[tree]) for tree in models]
        if len(models) > 1:
            identical.append((name, "both trees' batched outputs", same_trees))
        print(rows[-2 * len(models):], file=sys.stderr, flush=True)
    budget = Settings().model_cache_bytes
    lines = [f"## Shape-space enhancement, {args.actor.name} ({n:,} vertices, {model.n_frames} database "
             f"frames), {F}-frame request, {harness.git_state()}", "",
             f"{os.cpu_count()} cores, {BLAS_THREADS} BLAS thread(s) (serve's sizing). "
             f"Model load {load_wall:.1f} s wall ({load_cpu:.1f} s CPU); cache weight "
             f"{weight / 2**20:,.0f} MiB against the default budget {budget / 2**20:,.0f} MiB"
             f"{' (larger: never kept in the cache)' if weight > budget else ''}. "
             f"Target ≤ {n / (TARGET_FACTOR * PAPER_VERTICES_PER_S):.2f} s/frame "
             f"(≥ {TARGET_FACTOR:g}× bermano2014's {PAPER_VERTICES_PER_S:,.0f} vertices/s).", "",
             "| outputs | tree | how | CPU s/frame | wall s/frame | × paper's rate (CPU) | load average |",
             "|---|---|---|---:|---:|---:|---|"]
    for name, tree, how, c, w, ld in rows:
        lines.append(f"| {name} | {tree} | {how} | {c:.3f} | {w:.3f} | {n / c / PAPER_VERTICES_PER_S:.1f}× | {ld} |")
    lines += ["", "| outputs | bit for bit | |", "|---|---|---|"]
    lines += [f"| {name} | {what} | {'yes' if ok else 'NO'} |" for name, what, ok in identical]
    text = "\n".join(lines) + "\n"
    print(text)
    (OUT / "enhance_speed.md").write_text("# Shape-space enhancement speed (benchmarks/enhance_speed.py)\n\n" + text)
    return 0

if __name__ == "__main__":
    sys.exit(main())

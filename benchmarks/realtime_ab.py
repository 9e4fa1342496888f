"""One in-process PDM frame of an older commit against this tree's, in ONE process (issue 23).

The machine these benchmarks run on is shared, and its load moves the timings of separate
runs by ±30 %; so the two implementations are measured side by side: ``git archive REV
service`` is unpacked into ``benchmarks/out/realtime_ab/<rev>/service_<rev>`` with its
imports renamed (``service.`` → ``service_<rev>.``; ``models_store`` is shared), both load the
same model directory, and the frames alternate old, new, new, old, … Timings are process CPU
time (``time.process_time``: what the frame costs, not what the scheduler gave it) and wall
time, medians over ``--calls`` frames of ``heldout_in_range``; ``--profile`` adds a cProfile
breakdown (CPU clock) of each, on separate frames (also interleaved frame by frame).
The outputs of both are compared on every fifth frame (largest |old − new| and how many
frames are bit-identical). ``--stream`` adds the gRPC server's whole work per frame of each
(``grpc mesh``, ``grpc maps half``: its ``_Stream.reply`` — the marker frame decoded,
synthesized, the reply's bytes written — without the network), half-precision maps
included (issue 23).

Run: ``python benchmarks/realtime_ab.py [--rev 7543b2b] [--actor DIR] [--calls 30]
[--profile] [--stream]``, with the model of ``benchmarks/realtime.py`` (trained there, reused here).
BLAS threads: ``serve``'s sizing, as in ``realtime.py``. Writes JSON to stdout.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service.app.threads import apply_blas_threads  # noqa: E402

BLAS_THREADS = apply_blas_threads(None, int(os.environ["FACESYNTH_BLAS_THREADS"])
                                  if os.environ.get("FACESYNTH_BLAS_THREADS") else None)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import harness  # noqa: E402

ROOT = harness.ROOT
COMPARED = ("vertices", "displacement", "normal_map", "clamped", "confidence", "confidence_vertices")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", default="7543b2b", help="the older commit (default 7543b2b)")
    parser.add_argument("--actor", type=Path, default=None, help="sample actor (default level 1)")
    parser.add_argument("--calls", type=int, default=30)
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--stream", action="store_true", help="also the gRPC server's work per frame")
    args = parser.parse_args(argv)
    actor_dir = args.actor or harness.sample_actor("a", 1)
    model_dir = harness.ensure_realtime_model(actor_dir)
    markers = harness.heldout_markers(actor_dir)
    import importlib

    from service.methods.pdm.model import PdmModel as New
    packages = {"before": harness.renamed_package(args.rev), "after": "service"}
    Old = importlib.import_module(packages["before"] + ".methods.pdm.model").PdmModel
    models = {"before": Old.load(model_dir), "after": New.load(model_dir)}
    res: dict = {"rev": args.rev, "actor": str(actor_dir), "blas_threads": BLAS_THREADS,
                 "calls": args.calls, "load_start": harness.load_average()}
    sets = {"mesh": ("mesh",), "maps": ("mesh", "displacement", "normal_map")}
    frame_calls = {name: {tag: (lambda k, m=models[tag], o=outs: m.synthesize(markers[k % len(markers)][None], o))
                          for tag in models} for name, outs in sets.items()}
    if args.stream:
        for name, outs, half in (("grpc mesh", sets["mesh"], False), ("grpc maps half", sets["maps"], True)):
            frame_calls[name] = {tag: stream_frames(packages[tag], models[tag], markers, outs, half)
                                 for tag in models}
    for name, calls in frame_calls.items():
        cpu = {k: [] for k in models}
        wall = {k: [] for k in models}
        for k in range(args.calls + harness.WARMUP):
            for tag in alternating(k):
                c0, w0 = time.process_time(), time.perf_counter()
                calls[tag](k)
                if k >= harness.WARMUP:
                    cpu[tag].append(time.process_time() - c0)
                    wall[tag].append(time.perf_counter() - w0)
        for tag in models:
            res[f"{name} {tag}"] = {"cpu_ms": round(1e3 * float(np.median(cpu[tag])), 2),
                                   "wall_ms": round(1e3 * float(np.median(wall[tag])), 2)}
        res[f"{name} after/before"] = round(float(np.median(np.array(cpu["after"]) / np.array(cpu["before"]))), 3)
        if args.profile:                  # separate frames: the profiler's overhead is not timed
            prof = {k: cProfile.Profile(time.process_time) for k in models}
            for k in range(args.calls):
                for tag in alternating(k):
                    prof[tag].enable()
                    calls[tag](k)
                    prof[tag].disable()
            res[f"{name} profile"] = {tag: profile_rows(p, args.calls) for tag, p in prof.items()}
    diff: dict = {}
    for k in range(0, len(markers), 5):
        a, b = (models[t].synthesize(markers[k][None], sets["maps"]) for t in ("before", "after"))
        for key in COMPARED:
            e = diff.setdefault(key, {"max_abs_diff": 0.0, "frames_bit_identical": 0, "frames": 0})
            e["max_abs_diff"] = max(e["max_abs_diff"], float(np.abs(a[key].astype(np.float64) - b[key]).max()))
            e["frames_bit_identical"] += int(np.array_equal(a[key], b[key]))
            e["frames"] += 1
    res["outputs before vs after"] = diff
    res["load_end"] = harness.load_average()
    print(json.dumps(res, indent=1))
    return 0


def stream_frames(package: str, model, markers: np.ndarray, outputs, half: bool):
    """frame k → the gRPC server's work on frame k of a stream of ``outputs`` (``half``: maps
    in half precision), by ``package``'s own server (``service`` or an old one): its stream
    opened from a first MarkerFrame, then ``_Stream.reply`` of each MarkerFrame (decoding,
    synthesis, the reply's bytes), as the server's synthesis threads run it."""
    import importlib

    server = importlib.import_module(package + ".grpc.server")
    codec = importlib.import_module(package + ".grpc.codec")
    first = codec.encode_markers(markers[0], 0, model_id="model", outputs=list(outputs), half=half)
    stream = server.SynthesisServicer(lambda _: model, synthesis_threads=1)._open(first)
    messages = [codec.encode_markers(m, i) for i, m in enumerate(markers)]
    return lambda k: stream.reply(messages[k % len(messages)], f"frame {k}", time.perf_counter(), False)


def alternating(k: int) -> tuple[str, str]:
    """The order of frame k: before first on even frames, after first on odd ones."""
    return ("before", "after") if k % 2 == 0 else ("after", "before")


def profile_rows(prof: cProfile.Profile, calls: int, top: int = 14) -> list[str]:
    """The ``top`` functions by own CPU time: ``"where own_ms cumulative_ms calls"`` per frame."""
    rows = sorted(((tt, ct, nc, f"{Path(f).name}:{line}({fn})")
                   for (f, line, fn), (_, nc, tt, ct, _) in pstats.Stats(prof).stats.items()), reverse=True)
    total = sum(r[0] for r in rows)
    return [f"total {1e3 * total / calls:.1f} ms"] + [
        f"{where} {1e3 * tt / calls:.2f} {1e3 * ct / calls:.2f} {nc / calls:.0f}" for tt, ct, nc, where in rows[:top]]


if __name__ == "__main__":
    sys.exit(main())

"""Throughput of the SDK's gRPC stream against a running server, by pipeline depth.

Streams a sample actor's held-out performance through ``facesynth_client.StreamingClient``
with ``max_in_flight`` 1 (one frame at a time: send, wait, send), 2, 3, 4 and 8, and prints a
table of frames per second and the client-side round trip per frame (time from a frame
being taken to its reply) beside the server's own time per frame (``latency_ms``).

    python benchmarks/grpc_stream.py --grpc 127.0.0.1:50051 --model mdl_... \\
        --actor /path/to/sample-actor [--outputs mesh,displacement] [--frames 154]

The model must be a ready marker-driven model (e.g. a PDM) of that actor.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from facesynth_client import StreamingClient

DEPTHS = (1, 2, 3, 4, 8)


def run(target: str, model: str, markers: np.ndarray, outputs: tuple[str, ...],
        depth: int, token: str | None = None) -> dict[str, float]:
    """One stream of ``markers`` (F,M,3) at pipeline depth ``depth``: throughput and
    per-frame times (ms)."""
    taken: list[float] = []
    round_trip: list[float] = []
    server: list[float] = []

    def frames():
        for frame in markers:
            taken.append(time.perf_counter())
            yield frame

    with StreamingClient(target, token) as stream:
        start = time.perf_counter()
        for k, out in enumerate(stream.synthesize(model, frames(), outputs,
                                                  max_in_flight=depth)):
            round_trip.append(1e3 * (time.perf_counter() - taken[k]))
            server.append(out["latency_ms"])
        seconds = time.perf_counter() - start
    return {"depth": depth, "fps": len(markers) / seconds,
            "round_trip_ms": float(np.median(round_trip)),
            "server_ms": float(np.median(server))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grpc", required=True, help="the server's gRPC address, host:port")
    parser.add_argument("--model", required=True, help="a ready PDM model id")
    parser.add_argument("--actor", required=True, type=Path, help="the model's sample actor")
    parser.add_argument("--performance", default="heldout_in_range")
    parser.add_argument("--frames", type=int, default=154)
    parser.add_argument("--outputs", default="mesh,displacement")
    parser.add_argument("--token")
    args = parser.parse_args(argv)
    with np.load(args.actor / "performances" / f"{args.performance}.npz") as data:
        markers = data["markers"][:args.frames].astype(np.float32)
    outputs = tuple(args.outputs.split(","))
    run(args.grpc, args.model, markers[:4], outputs, 1, args.token)       # warm the model cache
    print(f"{len(markers)} frames of {args.performance}, outputs {','.join(outputs)}")
    print("| max_in_flight | frames/s | round trip per frame (median, ms) | server per frame (median, ms) |")
    print("|---:|---:|---:|---:|")
    for depth in DEPTHS:
        row = run(args.grpc, args.model, markers, outputs, depth, args.token)
        print(f"| {depth} | {row['fps']:.1f} | {row['round_trip_ms']:.1f} | {row['server_ms']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

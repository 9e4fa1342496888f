"""Load benchmark of the HTTP API (issue 16): concurrent synchronous synthesis and slow
connections against a real ``facesynth serve``.

1. **Synthesis under load.** A level-1 sample actor (seed 1, ~45k vertices, 256² maps, two
   training clips) is uploaded and a PDM trained through the API (medium 128², fine 256²).
   Then ``POST /v1/models/{id}/synthesize`` with one frame of held-out markers
   (``outputs=mesh,displacement``) is sent 50 times by 1 client, and 50 times by each of 16
   concurrent clients (httpx, one keep-alive connection each). Reported per run: requests,
   errors (anything but 200 and 503), 503s, latency p50/p95 and frames per second. The
   server queues syntheses beyond ``max_concurrent_syntheses`` for up to
   ``synthesis_queue_seconds`` before answering 503, so 16 clients should see no errors.
2. **Slow connections.** 100 connections that send their request headers one byte every
   5 s and 100 that send a declared 1 MB body one byte every 5 s (the probe of issue 16),
   from one address: the per-client bound refuses the excess at once (503) and the header
   deadline / minimum body rate close the rest. Reported: how many were refused, how many
   closed by the server, and the longest any stayed open (the bound is
   ``header_timeout_seconds`` for headers, ``body_rate_grace_seconds`` + a check interval
   for bodies).

``--sizings auto,2x2,1x2`` repeats part 1 in one server per sizing of synthesis slots x BLAS
threads per synthesis (issue 23: sized together, ``auto``, they fill the cores without
oversubscribing them; 2x2 on 2 cores is the sizing before it).

Run: ``python benchmarks/load.py`` (``make bench``); ``--work DIR`` keeps the actor and the
data directory between runs (default ``benchmarks/out/load-work``). Writes the tables to
stdout and ``benchmarks/out/load.md``. The server runs with SQLite and the embedded queue in
the work directory, with one embedded worker (for the training job).
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np

from harness import free_port, start_server, stop_server

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "benchmarks" / "out"

CLIPS = ("train_smile", "train_brow_raise")
PARAMS = {"order": "biquadratic", "medium_resolution": 128, "fine_resolution": 256}
REQUESTS = 50
CLIENTS = 16
SLOW = 100
SLOW_EVERY = 5.0
NPZ = {"Content-Type": "application/x-npz"}


def prepare(work: Path, base: str) -> tuple[str, np.ndarray]:
    """Upload the actor and train the model once (reused from the work directory)."""
    import httpx

    from service.samples.actor import build_sample_actor

    actor_dir = work / "actor"
    if not (actor_dir / "manifest.json").exists():
        print("building the level-1 sample actor (256² maps) ...", flush=True)
        build_sample_actor(actor_dir, seed=1, level=1, with_tracking=False, map_resolution=256,
                           performance_names=CLIPS + ("heldout_in_range",))
    with np.load(actor_dir / "performances" / "heldout_in_range.npz") as d:
        markers = d["markers"][40:41].astype(np.float32)
    model_file = work / "model_id"
    with httpx.Client(base_url=base, timeout=600) as client:
        if model_file.exists():
            model_id = model_file.read_text().strip()
            if client.get(f"/v1/models/{model_id}").status_code == 200:
                return model_id, markers
        from service.samples.uploads import sample_actor_uploads

        neutral, layout, clips = sample_actor_uploads(actor_dir, CLIPS)
        import json

        canonical = json.loads(layout)
        body = {"markers": [{"name": n, "triangle": t, "barycentric": b} for n, t, b in
                            zip(canonical["names"], canonical["triangle"],
                                canonical["barycentric"])]}
        actor_id = client.post("/v1/actors", json={"name": "load"}).json()["id"]
        client.put(f"/v1/actors/{actor_id}/neutral", content=neutral, headers=NPZ).raise_for_status()
        client.put(f"/v1/actors/{actor_id}/markers", json=body).raise_for_status()
        clip_ids = [client.post(f"/v1/actors/{actor_id}/clips", content=clips[n], headers=NPZ,
                                params={"name": n}).json()["clip_id"] for n in CLIPS]
        accepted = client.post(f"/v1/actors/{actor_id}/models",
                               json={"kind": "pdm", "clips": clip_ids, "params": PARAMS}).json()
        print(f"training {accepted['model_id']} ...", flush=True)
        while True:
            job = client.get(f"/v1/jobs/{accepted['job_id']}").json()
            if job["status"] in ("succeeded", "failed", "cancelled"):
                break
            time.sleep(1)
        if job["status"] != "succeeded":
            raise RuntimeError(f"training failed: {job}")
        model_file.write_text(accepted["model_id"])
        return accepted["model_id"], markers


def synthesis_run(base: str, model_id: str, markers: np.ndarray, clients: int) -> dict:
    """``clients`` concurrent clients × REQUESTS single-frame syntheses."""
    import httpx

    from service.io.npz import npz_bytes

    body = npz_bytes(markers=markers)
    latencies: list[float] = []
    statuses: list[int] = []
    lock = threading.Lock()
    start_all = threading.Barrier(clients + 1)

    def client_loop() -> None:
        with httpx.Client(base_url=base, timeout=300) as client:
            start_all.wait()
            for _ in range(REQUESTS):
                t0 = time.perf_counter()
                try:
                    status = client.post(f"/v1/models/{model_id}/synthesize", content=body,
                                         headers=NPZ,
                                         params={"outputs": "mesh,displacement"}).status_code
                except httpx.HTTPError:
                    status = -1
                with lock:
                    latencies.append(time.perf_counter() - t0)
                    statuses.append(status)

    threads = [threading.Thread(target=client_loop) for _ in range(clients)]
    for t in threads:
        t.start()
    start_all.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    ok = [lat for lat, s in zip(latencies, statuses) if s == 200]
    return {"clients": clients, "requests": len(statuses),
            "errors": sum(s not in (200, 503) for s in statuses),
            "503": statuses.count(503),
            "p50_ms": 1000 * float(np.percentile(ok, 50)) if ok else float("nan"),
            "p95_ms": 1000 * float(np.percentile(ok, 95)) if ok else float("nan"),
            "frames_per_s": len(ok) / wall, "wall_s": wall}


def slow_run(port: int, kind: str, count: int) -> dict:
    """``count`` connections trickling their headers (or body) one byte every SLOW_EVERY s."""
    results: list[tuple[str, float]] = []
    lock = threading.Lock()

    def one() -> None:
        start = time.monotonic()
        outcome = "open"
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
                if kind == "body":
                    s.sendall(b"POST /v1/actors HTTP/1.1\r\nhost: x\r\ncontent-type: "
                              b"application/json\r\ncontent-length: 1000000\r\n\r\n")
                    trickle = b"{" + b" " * 100
                else:
                    trickle = b"GET /v1/actors HTTP/1.1\r\nhost: x\r\n" + b"x" * 100
                s.settimeout(SLOW_EVERY)
                for byte in trickle:
                    try:
                        s.sendall(bytes([byte]))
                        reply = s.recv(4096)
                        outcome = "503" if reply.startswith(b"HTTP/1.1 503") else "closed"
                        break
                    except socket.timeout:
                        continue
                    except OSError:
                        outcome = "closed"
                        break
                    finally:
                        if time.monotonic() - start > 120:
                            break
        except OSError:
            outcome = "closed"
        with lock:
            results.append((outcome, time.monotonic() - start))

    threads = [threading.Thread(target=one) for _ in range(count)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(180)
    closed = [t for o, t in results if o == "closed"]
    return {"kind": kind, "connections": count,
            "refused_503": sum(o == "503" for o, _ in results), "closed": len(closed),
            "still_open": sum(o == "open" for o, _ in results),
            "longest_open_s": max((t for _, t in results), default=0.0)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=OUT / "load-work")
    parser.add_argument("--skip-slow", action="store_true")
    parser.add_argument("--sizings", default="auto",
                        help="comma-separated synthesis slot x BLAS thread sizings, each in its "
                             "own server: 'auto' (slots = cores, BLAS threads = cores // slots: "
                             "service.app.threads) or SxT, e.g. 2x2 (the oversubscribed sizing "
                             "of a 2-core machine before issue 23), 1x2 (default auto); "
                             "+share after one: the kernels share the cores among the running "
                             "syntheses (auto+share)")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    OUT.mkdir(parents=True, exist_ok=True)
    port = free_port()
    env = {"FACESYNTH_HEADER_TIMEOUT_SECONDS": "10", "FACESYNTH_BODY_RATE_GRACE_SECONDS": "10"}
    base = f"http://127.0.0.1:{port}"
    lines = ["## Single-frame synthesis, level-1 PDM (44,786 vertices, 128²/256² maps)", "",
             f"{os.cpu_count()} cores; slots x BLAS threads per synthesis "
             "(`max_concurrent_syntheses` x `blas_threads`; auto: service.app.threads); "
             "× 1 client: the throughput against one client of the same server", "",
             "| slots x BLAS threads | clients | requests | errors | 503 | p50 ms | p95 ms | "
             "frames/s | × 1 client | load average |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    sizings = args.sizings.split(",")
    server = None
    try:
        for k, sizing in enumerate(sizings):
            sized = dict(env)
            slots_threads, _, kernels = sizing.partition("+")
            if kernels:                 # e.g. auto+share: Settings.synthesis_kernel_threads
                sized["FACESYNTH_SYNTHESIS_KERNEL_THREADS"] = kernels
            if slots_threads != "auto":
                slots, threads = slots_threads.split("x")
                sized.update({"FACESYNTH_MAX_CONCURRENT_SYNTHESES": slots,
                              "FACESYNTH_BLAS_THREADS": threads})
            server = start_server(args.work, port, sized)
            model_id, markers = prepare(args.work, base)
            synthesis_run(base, model_id, markers, 1)          # warm the model cache
            runs = []
            for n in (1, CLIENTS):
                runs.append(synthesis_run(base, model_id, markers, n))
                runs[-1]["load"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
            for r in runs:
                lines.append(f"| {sizing} | {r['clients']} | {r['requests']} | {r['errors']} | "
                             f"{r['503']} | {r['p50_ms']:.0f} | {r['p95_ms']:.0f} | "
                             f"{r['frames_per_s']:.1f} | "
                             f"{r['frames_per_s'] / runs[0]['frames_per_s']:.2f}× | {r['load']} |")
            print("\n".join(lines), flush=True)
            if k < len(sizings) - 1:
                stop_server(server)
                server = None
        if not args.skip_slow:
            slow = [slow_run(port, kind, SLOW) for kind in ("headers", "body")]
            lines += ["", f"## Slow connections ({SLOW} each, one byte every {SLOW_EVERY:g} s, "
                          "one client address)", "",
                      "| trickling | connections | refused (503) | closed by the server | "
                      "still open | longest open s |", "|---|---:|---:|---:|---:|---:|"]
            for r in slow:
                lines.append(f"| {r['kind']} | {r['connections']} | {r['refused_503']} | "
                             f"{r['closed']} | {r['still_open']} | {r['longest_open_s']:.1f} |")
    finally:
        if server is not None:
            stop_server(server)
    text = "\n".join(lines) + "\n"
    print(text)
    (OUT / "load.md").write_text("# Load benchmark (benchmarks/load.py)\n\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

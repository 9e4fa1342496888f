"""Wall time of one tracking job (``POST /v1/actors/{id}/tracking-jobs``) with 1 and with 2
worker processes: the fan-out of one ``track_span`` job per in-between span (fyffe,
digital_ira_course2014 §5.7) must cut it.

Data: :func:`service.samples.tracking.build_tracking_sample` of the family-a sample actor at
level 0 (``harness.sample_actor("a", 0)``): 120 frames, ``--size``² images, ``--views``
views, the neutral plus ``--scans`` training peaks as static scans (cached in
``benchmarks/out/tracking_job/``). For each worker count a fresh deployment (SQLite database,
queue and blobs in a temporary data directory) runs ``facesynth serve --workers 0`` (the
API) and N separate ``facesynth worker --workers 1`` processes — the compose topology's
``--scale worker=N`` on one machine — with ``--threads`` BLAS/OpenMP threads each (default
1, so the two runs use the same per-process compute and the ratio measures the fan-out).
The job is submitted through the SDK (``client.tracking.submit``) and timed from the
request to ``succeeded``; the table gives the parent's stage seconds (from its result's
metrics) and the span jobs' total solve seconds.

    python benchmarks/tracking_job.py [--quick] [--frames 120] [--size 256] [--views 1]

writes ``benchmarks/out/tracking_job/report.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "clients" / "python" / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))

import harness  # noqa: E402

OUT = harness.OUT / "tracking_job"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def sample_for(args):
    from service.samples.tracking import TrackingSample, build_tracking_sample

    actor = Path(args.actor) if args.actor else harness.sample_actor("a", 0)
    OUT.mkdir(parents=True, exist_ok=True)
    cache = OUT / f"sample_{args.size}_{args.frames}_{args.views}_{args.scans}.npz"
    if cache.exists():
        return actor, TrackingSample.load(cache)
    manifest = json.loads((actor / "manifest.json").read_text())
    training = sorted(k for k, v in manifest["performances"].items() if v["kind"] == "training")
    return actor, build_tracking_sample(actor, size=args.size, frames=args.frames,
                                        views=args.views, scans=tuple(training[:args.scans]),
                                        out=cache)


def run_deployment(workers: int, actor_dir: Path, parts, params: dict, threads: int) -> dict:
    """One fresh deployment with ``workers`` worker processes; the job's wall time and
    result."""
    from facesynth_client import Client

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "clients/python/src"),
                                                        os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": str(threads), "OPENBLAS_NUM_THREADS": str(threads),
           "MKL_NUM_THREADS": str(threads), "FACESYNTH_TOKENS": ""}
    python = [sys.executable, "-m", "service.cli"]
    with tempfile.TemporaryDirectory(prefix="tracking-job-", dir=OUT) as data:
        port = free_port()
        procs = [subprocess.Popen(python + ["serve", "--workers", "0", "--port", str(port),
                                            "--grpc-port", str(free_port()), "--data-dir", data],
                                  env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                                  stderr=open(Path(data) / "serve.log", "w"))]
        try:
            url = f"http://127.0.0.1:{port}"
            with Client(url) as client:
                deadline = time.monotonic() + 60
                while True:
                    try:
                        client.actors.list()
                        break
                    except Exception:
                        if time.monotonic() > deadline:
                            raise RuntimeError((Path(data) / "serve.log").read_text()[-2000:])
                        time.sleep(0.3)
                for k in range(workers):
                    procs.append(subprocess.Popen(
                        python + ["worker", "--workers", "1", "--data-dir", data], env=env,
                        cwd=ROOT, stdout=subprocess.DEVNULL,
                        stderr=open(Path(data) / f"worker{k}.log", "w")))
                time.sleep(3.0)                               # workers migrated and polling
                actor = client.actors.create("tracking-bench")
                with np.load(actor_dir / "neutral.npz") as d:
                    client.actors.upload_neutral(actor.id, vertices=d["vertices"],
                                                 faces=d["faces"].astype(np.int32), uv=d["uv"],
                                                 uv_faces=d["uv_faces"].astype(np.int32),
                                                 region_face=d["region"] == 0)
                t0 = time.perf_counter()
                accepted = client.tracking.submit(actor.id, parts, params=params)
                job = client.wait(accepted, timeout=7200)
                wall = time.perf_counter() - t0
                spans = [client.jobs.get(j) for j in job.raw["result"]["span_job_ids"]]
        finally:
            for proc in reversed(procs):
                proc.terminate()
            for proc in procs:
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    proc.kill()
    result = job.raw["result"]
    span_seconds = [float((s.raw.get("result") or {}).get("seconds", 0.0)) for s in spans]
    workers_seen = {(s.raw.get("result") or {}).get("worker", "").rsplit(":", 1)[0] for s in spans}
    return {"workers": workers, "wall_s": wall, "status": job.status,
            "metrics": result["metrics"], "span_seconds": span_seconds,
            "span_workers": len(workers_seen - {""})}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--scans", type=int, default=4, help="training clips used as static scans")
    ap.add_argument("--threads", type=int, default=1, help="BLAS/OpenMP threads per process")
    ap.add_argument("--actor", help="a built family-a level-0 sample actor directory "
                                    "(default harness.sample_actor('a', 0))")
    ap.add_argument("--quick", action="store_true", help="24 frames at 128² (a smoke run)")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.size, args.scans = 24, 128, 2
    from service.samples.tracking_scene import tracking_uploads

    t0 = time.perf_counter()
    actor_dir, sample = sample_for(args)
    build_s = time.perf_counter() - t0
    parts = tracking_uploads(sample)
    upload_mb = sum(len(p[1][1]) for p in parts) / 2**20
    params = {}
    runs = [run_deployment(n, actor_dir, parts, params, args.threads) for n in (1, 2)]
    base = runs[0]["wall_s"]
    n = len(sample.artist_vertices)
    lines = [f"# Tracking job: {len(sample.frame_images)} frames, 1 vs 2 worker processes", "",
             f"Family a, level 0 ({n} vertices), {args.size}² images, {args.views} view(s), "
             f"{len(sample.scan_names)} static scans ({', '.join(map(str, sample.scan_names))}); "
             f"upload {upload_mb:.1f} MiB; sample built/loaded in {build_s:.0f} s; "
             f"{args.threads} BLAS thread(s) per process; `os.getloadavg()` at the end "
             f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (shared machine).", "",
             "| workers | wall s | ratio to 1 worker | graph s | keyframes s | span jobs | "
             "span solve s (sum) | workers that ran spans | maps s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for run in runs:
        m = run["metrics"]
        sec = m["seconds"]
        lines.append(f"| {run['workers']} | {run['wall_s']:.1f} | {run['wall_s'] / base:.2f} | "
                     f"{sec.get('graph', 0):.1f} | {sec.get('keyframes', 0):.1f} | {m['spans']} | "
                     f"{sum(run['span_seconds']):.1f} | {run['span_workers']} | "
                     f"{sec.get('maps', 0):.1f} |")
    lines += ["", f"keyframes {runs[0]['metrics']['keyframes']}, static edges "
              f"{runs[0]['metrics']['static_edges']} of {runs[0]['metrics']['candidates']} "
              "candidates. The graph, the keyframe solve and the maps run in the parent (one "
              "worker); only the spans fan out, so the ratio is bounded by their share "
              "(Amdahl)."]
    report = "\n".join(lines) + "\n"
    (OUT / "report.md").write_text(report)
    (OUT / "runs.json").write_text(json.dumps(runs, indent=1))
    print(report)


if __name__ == "__main__":
    main()

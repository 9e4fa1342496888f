"""Peak memory of the API process for large uploads (issue 16, defect 11).

A real ``facesynth serve`` (SQLite, embedded queue, no worker) on a scratch data directory
gets an actor on a 100×100 vertex grid, then clip uploads of ``--mib`` MiB each
(``vertices`` (F,10000,3) float32 + ``markers`` (F,3,3), streamed from a file by httpx, so
the client holds none of it): first one, then ``--concurrent`` at once. For each the
server's peak resident set (``VmHWM`` of ``/proc/<pid>/status``, reset before each run by
writing 5 to ``/proc/<pid>/clear_refs``) is reported against its resident set just before.

Run ``python benchmarks/upload_memory.py`` (in ``make bench``). ``--repo DIR`` serves the
code of another checkout (e.g. an export of the commit before the fix, for the "before"
column); ``--work DIR`` is the scratch directory (default ``benchmarks/out/upload-memory``,
removed afterwards unless ``--keep``). Prints a markdown table and writes it to
``benchmarks/out/upload_memory.md``. Bounded: every request has a 600 s timeout, the server
is stopped however the run ends.
"""

from __future__ import annotations

import argparse
import io
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np

from harness import free_port, start_server, stop_server

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "benchmarks" / "out"
NPZ = {"Content-Type": "application/x-npz"}
SIDE = 100                      # grid side: 10 000 vertices
MiB = 1 << 20


def status_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def reset_peak(pid: int) -> int:
    """Reset the server's high-water mark; its resident kB now."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    return status_kb(pid, "VmRSS")


def grid_mesh(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An n×n grid on a gentle bump: vertices (n²,3) mm, faces (2(n-1)²,3), uv (n²,2)."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    V = np.stack([100 * u, 100 * v, 5 * np.sin(np.pi * u) * np.sin(np.pi * v)], -1).reshape(-1, 3)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, 1:].ravel(), k[1:, :-1].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return V, F, np.stack([u, v], -1).reshape(-1, 2)


def write_clip(path: Path, V: np.ndarray, mib: int) -> int:
    """An uploaded clip of about ``mib`` MiB at ``path`` (written frame block by frame block
    through an open_memmap, so this script stays small too); its size in bytes."""
    frames = mib * MiB // (V.size * 4)
    raw = path.with_suffix(".vertices.npy")
    out = np.lib.format.open_memmap(raw, mode="w+", dtype=np.float32, shape=(frames, len(V), 3))
    rng = np.random.default_rng(1)
    for start in range(0, frames, 64):
        n = min(64, frames - start)
        out[start:start + n] = V[None] + rng.normal(0, 0.05, (n, len(V), 3))
    out.flush()
    markers = np.asarray(out[:, [0, 1, 2]])
    np.savez(path, vertices=out, markers=markers, fps=np.float64(30))
    del out
    raw.unlink()
    return path.stat().st_size


def upload(base: str, actor: str, body: Path, results: list) -> None:
    import httpx

    t0 = time.perf_counter()
    with open(body, "rb") as f, httpx.Client(base_url=base, timeout=600) as client:
        headers = {**NPZ, "Content-Length": str(body.stat().st_size)}
        response = client.post(f"/v1/actors/{actor}/clips", content=f, headers=headers)
    results.append((response.status_code, time.perf_counter() - t0,
                    "" if response.status_code == 201 else response.text[:120]))


def run(repo: Path, work: Path, mib: int, concurrent: int) -> list[dict]:
    import httpx

    V, F, uv = grid_mesh(SIDE)
    bodies = [work / f"clip{k}.npz" for k in range(concurrent)]
    size = write_clip(bodies[0], V, mib)
    for extra in bodies[1:]:
        shutil.copyfile(bodies[0], extra)
    neutral = io.BytesIO()
    np.savez(neutral, vertices=V, faces=F, uv=uv)
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(work, port, {"FACESYNTH_WORKERS": "0"}, repo)
    rows = []
    try:
        with httpx.Client(base_url=base, timeout=120) as client:
            actor = client.post("/v1/actors", json={"name": "upload-memory"}).json()["id"]
            client.put(f"/v1/actors/{actor}/neutral", content=neutral.getvalue(),
                       headers=NPZ).raise_for_status()
            client.put(f"/v1/actors/{actor}/markers", json={"markers": [
                {"name": f"M{k}", "vertex": k} for k in range(3)]}).raise_for_status()
        for n in (1, concurrent):
            time.sleep(1.0)
            before = reset_peak(server.pid)
            results: list = []
            threads = [threading.Thread(target=upload, args=(base, actor, bodies[k], results))
                       for k in range(n)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            peak = status_kb(server.pid, "VmHWM")
            rows.append({"uploads": n, "body_mib": size / MiB, "rss_before": before / 1024,
                         "peak": peak / 1024, "growth": (peak - before) / 1024,
                         "status": ",".join(str(r[0]) for r in sorted(results)),
                         "seconds": max(r[1] for r in results),
                         "errors": "; ".join(r[2] for r in results if r[2])})
    finally:
        stop_server(server)
    return rows


def table(label: str, rows: list[dict]) -> str:
    lines = [f"**{label}**", "",
             "| uploads at once | body MiB each | API RSS before (MiB) | peak RSS (MiB) | "
             "growth (MiB) | status | wall s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['uploads']} | {r['body_mib']:.0f} | {r['rss_before']:.0f} | "
                     f"{r['peak']:.0f} | {r['growth']:.0f} | {r['status']} | {r['seconds']:.1f} |")
        if r["errors"]:
            lines.append(f"|  | errors: {r['errors']} | | | | | |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repo", type=Path, default=ROOT, help="checkout whose server runs")
    parser.add_argument("--work", type=Path, default=OUT / "upload-memory")
    parser.add_argument("--mib", type=int, default=250)
    parser.add_argument("--concurrent", type=int, default=2)
    parser.add_argument("--label", default="")
    parser.add_argument("--keep", action="store_true")
    args = parser.parse_args()
    work = args.work.absolute()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    try:
        rows = run(args.repo.absolute(), work, args.mib, args.concurrent)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    text = table(args.label or f"server: {args.repo}", rows)
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    with open(OUT / "upload_memory.md", "a") as f:
        f.write(text + "\n\n")


if __name__ == "__main__":
    main()

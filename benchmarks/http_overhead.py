"""The HTTP path's own cost per synthesis request (issue 23), without a model.

``POST /v1/models/{id}/synthesize`` is answered by servers whose synthesis is stubbed to a
fixed answer of the size of a level-1 frame (``mesh``: ``vertices`` (1,44786,3) float32 and
``clamped``, 538 kB; ``maps``: plus half-precision ``displacement`` (1,1024,1024) and
``normal_map`` (1,1024,1024,3), 8.9 MB), so what is measured is everything but the
synthesis: parsing, routing, dependencies, middleware, the thread-pool hand-off, sending,
and the client's sending and receiving. Servers (each ``uvicorn`` with the project's guarded
protocol, ``--impl`` httptools on uvloop by default, in its own process):

* ``app, lean path`` — ``create_app`` as served (``service/api/lean.py`` takes the route);
* ``app, FastAPI route`` — the same app with ``lean_synthesis=False``;
* ``bare ASGI`` — a plain ASGI function reading the body, one thread-pool hand-off, and
  sending the same answer: the floor of uvicorn + the parser.

With ``--busy MS`` the stubbed synthesis (in the bare server, its thread-pool call) spends
``MS`` ms of its thread's CPU streaming through :data:`BUSY_BYTES` of float32 data in 1 MiB
pieces, as a frame streams through a model's arrays, so that the request's own Python code
runs in the caches a real synthesis leaves it; the table then adds ``wall − busy``, the
overhead per call.

Clients, each with one keep-alive connection: ``httpx`` (its own transport, httpcore on h11),
``SDK transport`` (httpx with ``facesynth_client.transport.OnePieceTransport``, the SDK's
default), and the standard library's ``http.client``. Each call sends a one-frame marker
NPZ with ``outputs=mesh&half=true&topology=false`` and reads the whole answer. Calls take
turns across every (server, client) pair (in order, then reversed), and each records its
wall time, this process's CPU time and the server process's CPU time (all its threads,
/proc schedstat): medians in ms, with the load average.

Run: ``python benchmarks/http_overhead.py [--calls 300] [--answer mesh|maps] [--impl
httptools|h11] [--busy MS]``; writes ``benchmarks/out/http_overhead-<answer>.md``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients" / "python" / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402

import harness  # noqa: E402

SERVERS = {"app, lean path": "lean", "app, FastAPI route": "fastapi", "bare ASGI": "bare"}
QUERY = "outputs=mesh&half=true&topology=false"
VERTICES = 44_786
MAP = 1024
#: what ``--busy`` streams through (a level-1 PDM frame reads ~44 MB of coefficients)
BUSY_BYTES = 48 << 20


def answer(kind: str) -> bytes:
    """The stubbed synthesis answer (seeded values, the sizes of a level-1 frame)."""
    from service.io.npz import npz_bytes

    rng = np.random.default_rng(0)
    arrays = {"vertices": rng.random((1, VERTICES, 3), dtype=np.float32),
              "clamped": np.zeros(1, np.float32)}
    if kind == "maps":
        arrays["displacement"] = rng.random((1, MAP, MAP), dtype=np.float32).astype(np.float16)
        arrays["normal_map"] = rng.random((1, MAP, MAP, 3), dtype=np.float32).astype(np.float16)
    return npz_bytes(**arrays)


def busy(ms: float) -> "callable":
    """A function spending ``ms`` ms of its thread's CPU time summing 1 MiB pieces of
    :data:`BUSY_BYTES` of float32 in turn (0: returns at once)."""
    if ms <= 0:
        return lambda: None
    data = np.ones(BUSY_BYTES // 4, np.float32).reshape(-1, 1 << 18)
    where = [0]

    def run() -> None:
        end = time.thread_time() + ms * 1e-3
        while time.thread_time() < end:
            data[where[0]].sum()
            where[0] = (where[0] + 1) % len(data)
    return run


def serve(mode: str, port: int, kind: str, impl: str, data_dir: str, busy_ms: float) -> None:
    """Run one stub server (in its own process)."""
    import uvicorn

    from service.api import create_app
    from service.api.connections import protocol_class
    from service.app import operations
    from service.config import Settings

    body = answer(kind)
    work = busy(busy_ms)

    def stub(*args, **kwargs):
        work()
        return operations.Synthesized("application/x-npz", body, 1, None)
    operations.synthesize = stub
    settings = Settings(data_dir=Path(data_dir), tokens=[], lean_synthesis=mode == "lean")
    http = protocol_class(settings.header_timeout_seconds, settings.min_body_rate_bytes,
                          settings.body_rate_grace_seconds, settings.max_connections_per_client,
                          http=impl)

    async def bare(scope, receive, send):
        from starlette.concurrency import run_in_threadpool

        if scope["type"] == "lifespan":
            while (await receive())["type"] != "lifespan.shutdown":
                await send({"type": "lifespan.startup.complete"})
            await send({"type": "lifespan.shutdown.complete"})
            return
        more = True
        while more:
            more = (await receive()).get("more_body", False)
        await run_in_threadpool(work)
        await send({"type": "http.response.start", "status": 200, "headers": [
            (b"content-type", b"application/x-npz"),
            (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})

    app = bare if mode == "bare" else create_app(settings)
    uvicorn.run(app, host="127.0.0.1", port=port, log_config=None, access_log=False, http=http,
                loop="uvloop" if impl == "httptools" else "asyncio")


def server_cpu_seconds(pid: int) -> float:
    """CPU seconds of every thread of process ``pid`` (/proc schedstat)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            total += int((task / "schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            pass
    return total * 1e-9


def start(mode: str, kind: str, impl: str, work: Path, busy_ms: float = 0.0
          ) -> tuple[subprocess.Popen, str]:
    import httpx

    port = harness.free_port()
    data = work / mode
    data.mkdir(parents=True, exist_ok=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    proc = subprocess.Popen([sys.executable, __file__, "--serve", mode, str(port), kind, impl,
                             str(data), str(busy_ms)], env=env, stdout=subprocess.DEVNULL,
                            stderr=open(work / f"{mode}.log", "wb"))
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            httpx.post(f"{url}/v1/models/m/synthesize?{QUERY}", content=b"x", timeout=2,
                       headers={"Content-Type": "application/x-npz"}).raise_for_status()
            return proc, url
        except (httpx.TransportError, httpx.HTTPStatusError):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the {mode} server did not start; see {work}")
            time.sleep(0.2)


def clients(url: str):
    """name → call() reading one whole answer."""
    import http.client

    import httpx

    from facesynth_client.transport import OnePieceTransport
    from service.io.npz import npz_bytes

    body = npz_bytes(markers=np.zeros((1, 150, 3)))
    headers = {"Content-Type": "application/x-npz"}
    path = f"/v1/models/m/synthesize?{QUERY}"
    plain = httpx.Client(base_url=url, timeout=60)
    sdk = httpx.Client(base_url=url, timeout=60, transport=OnePieceTransport())
    host, port = url.rsplit("/", 1)[1].split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=60)

    def stdlib() -> int:
        conn.request("POST", path, body=body, headers=headers)
        response = conn.getresponse()
        return len(response.read())
    return {"httpx": lambda: len(plain.post(path, content=body, headers=headers).content),
            "SDK transport": lambda: len(sdk.post(path, content=body, headers=headers).content),
            "http.client": stdlib}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=300)
    parser.add_argument("--answer", choices=("mesh", "maps"), default="mesh")
    parser.add_argument("--impl", choices=("httptools", "h11"), default="httptools")
    parser.add_argument("--busy", type=float, default=0.0, metavar="MS",
                        help="the stubbed synthesis spends MS ms of CPU streaming memory")
    parser.add_argument("--serve", nargs=6, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        mode, port, kind, impl, data, busy_ms = args.serve
        serve(mode, int(port), kind, impl, data, float(busy_ms))
        return 0
    work = harness.OUT / "http_overhead"
    load_start = harness.load_average()
    procs, calls = [], {}
    try:
        for label, mode in SERVERS.items():
            proc, url = start(mode, args.answer, args.impl, work, args.busy)
            procs.append(proc)
            for client, call in clients(url).items():
                calls[(label, client)] = (call, proc.pid)
        for call, _ in calls.values():
            for _ in range(harness.WARMUP * 5):
                size = call()
        names = list(calls)
        times: dict = {name: [] for name in names}
        for k in range(args.calls):
            for name in names if k % 2 == 0 else names[::-1]:
                call, pid = calls[name]
                s0, c0, t0 = server_cpu_seconds(pid), time.process_time(), time.perf_counter()
                call()
                t1, c1, s1 = time.perf_counter(), time.process_time(), server_cpu_seconds(pid)
                times[name].append((t1 - t0, c1 - c0, s1 - s0))
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(30)
    lines = [f"# The HTTP path's own cost per synthesis request ({args.answer} answer, "
             f"{size:,} bytes, {args.impl})", "",
             f"Medians over {args.calls} interleaved calls, ms; load average {load_start} at "
             f"the start, {harness.load_average()} at the end; {os.cpu_count()} CPUs.", "",
             f"The stubbed synthesis spends {args.busy:g} ms of CPU streaming memory (`--busy`); "
             "`− busy`: the column less that.", "",
             "| server | client | wall ms | wall − busy | client CPU ms | server CPU ms | "
             "server CPU − busy |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for (server, client), rows in times.items():
        wall, client_cpu, server_cpu = (1e3 * float(np.median(c)) for c in zip(*rows))
        lines.append(f"| {server} | {client} | {wall:.3f} | {wall - args.busy:.3f} | "
                     f"{client_cpu:.3f} | {server_cpu:.3f} | {server_cpu - args.busy:.3f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    harness.OUT.mkdir(parents=True, exist_ok=True)
    (harness.OUT / f"http_overhead-{args.answer}.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

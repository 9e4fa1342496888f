"""The real-time path (issue 23): one PDM frame in-process, over HTTP and over the gRPC stream.

The same trained PDM model (default parameters: medium 512², fine 1024², biquadratic) of a
sample actor answers one frame of held-out markers at a time, for two output sets:

* ``mesh`` — the medium-scale mesh only;
* ``mesh + displacement + normal map`` — the mesh and both fine-scale maps.

Paths, each a median over ``--calls`` calls (frames cycle through the first 50 of
``heldout_in_range``):

1. **in-process**: ``PdmModel.synthesize(markers, outputs)`` on a loaded model, with the
   servers' sizing (one synthesis slot per core, so one kernel and BLAS thread each: the
   reference of every ratio) and, on a machine of several cores, again with the kernels on
   every core (``service.geometry.ranges.frame_threads``; one BLAS thread still), as a
   caller computing one frame at a time in-process would;
2. **HTTP**: ``POST /v1/models/{id}/synthesize`` (one frame, NPZ body, keep-alive httpx
   client) against a real ``facesynth serve`` — the round trip includes the server's
   encoding and the client's ``np.load`` of every array; variants: float32 with the
   triangles (the contract's default), and ``half=true&topology=false`` (half-precision
   maps, triangles left out: the client fetched them once), and the same through the SDK
   (``facesynth_client.Client`` with its default transport, ``copy=False``: the answer
   decoded as views of its body; this tree's SDK with ``PYTHONPATH=clients/python/src``); with
   uvicorn's pure-Python h11
   parser and, when installed, its httptools parser on uvloop (``FACESYNTH_HTTP``), each
   in its own server of the same run;
3. **gRPC stream**: ``StreamSynthesize`` through the SDK's ``StreamingClient`` with
   ``max_in_flight`` 4, time per frame = wall time / frames (the reciprocal of the
   throughput), float32 and half-precision maps.

Every row is also a ratio against in-process measured in the same run, and the load
average (``os.getloadavg()``) is recorded beside each row: the machine is shared, so only
ratios within one run compare. An HTTP row's calls take turns with in-process frames, frame
by frame (:func:`interleaved_ms`), and its ratio is against those: measured one block after
the other, the ratio moved with the host's speed between the blocks (the SDK's mesh frame
1.09-1.21× in four runs of one hour). ``--profile`` adds a cProfile breakdown of the in-process
frame (top functions by own time) per output set.

With ``--against REV`` the HTTP and gRPC rows come instead from a server of commit ``REV``
(``git archive``, as ``cold_start.py --against``) and one of this tree, started side by
side, their requests interleaved frame by frame with the in-process frame (a, b, c, c, b,
a, …), so that old and new compare within the same seconds on a shared machine; these rows
add each frame's CPU time, medians over the frames, of this process (the client; for
in-process, the synthesis) and of the server process (every thread, from /proc schedstat):
what a frame costs whatever the scheduler gave it (on a loaded VM, CPU time inflates too).
``--impls`` and ``--outputs`` restrict the run (e.g. ``--impls httptools --outputs mesh``).
gRPC streams of ``--calls`` frames take turns (a, b, c, c, b, a, ``--rounds`` each; c: this
tree with one synthesis slot, ``FACESYNTH_MAX_CONCURRENT_SYNTHESES=1``), with the CPU time per
frame of the server process and of the client (the SDK's receiving and decoding).

Run: ``python benchmarks/realtime.py [--actor DIR] [--calls 100] [--paths inproc,http,grpc]
[--profile] [--against REV] [--impls h11,httptools] [--outputs mesh,maps]`` (``make bench``). The model is trained once into
``benchmarks/out/realtime/model-<actor>-<defaults key>`` (a fresh process, minutes at level 1) and
reused; the server's data directory is ``benchmarks/out/realtime/work-<model directory>``. Writes the
table to stdout and ``benchmarks/out/realtime.md``.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service.app.threads import apply_blas_threads, cores  # noqa: E402

#: BLAS threads of the in-process reference and of the servers: ``serve``'s own sizing
#: (cores ÷ synthesis slots, or FACESYNTH_BLAS_THREADS), set before NumPy loads. Measured on
#: the level-1 actor with the machine loaded (load average 10 on 2 cores): 2 threads cost
#: 2-3× the CPU time of 1 per mesh frame (OpenBLAS's waiting threads), so the reference
#: must not run with more BLAS threads than the service does.
BLAS_THREADS = apply_blas_threads(None, int(os.environ["FACESYNTH_BLAS_THREADS"])
                                  if os.environ.get("FACESYNTH_BLAS_THREADS") else None)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import harness  # noqa: E402

ROOT = harness.ROOT
OUT = ROOT / "benchmarks" / "out"
WORK = harness.REALTIME
WARMUP = harness.WARMUP
IN_FLIGHT = 4
OUTPUT_SETS = {"mesh": ("mesh",),
               "mesh + displacement + normal map": ("mesh", "displacement", "normal_map")}
#: issue 23's targets at level 1: ms per in-process frame, and HTTP / in-process ratios
TARGET_MS = {"mesh": 15.0, "mesh + displacement + normal map": 40.0}
TARGET_HTTP = {"mesh": 1.15, "mesh + displacement + normal map": 1.25}
TARGET_FPS = {"mesh": 60.0, "mesh + displacement + normal map": 30.0}
NPZ = harness.NPZ_TYPE


def median_ms(fn, calls: int) -> float:
    return harness.median_ms(fn, calls, WARMUP)


# ---------------------------------------------------------------------- in-process
def in_process(model, markers: np.ndarray, outputs, calls: int) -> float:
    return median_ms(lambda k: model.synthesize(markers[k % len(markers)][None], outputs), calls)


def profile(model, markers: np.ndarray, outputs, calls: int, top: int = 14) -> str:
    """cProfile of ``calls`` in-process frames: the functions with the most own time."""
    prof = cProfile.Profile()
    prof.enable()
    for k in range(calls):
        model.synthesize(markers[k % len(markers)][None], outputs)
    prof.disable()
    buf = io.StringIO()
    stats = pstats.Stats(prof, stream=buf)
    rows = []
    for (file, line, name), (_, ncalls, tottime, cumtime, _) in stats.stats.items():
        rows.append((tottime, cumtime, ncalls, f"{Path(file).name}:{line}({name})"))
    rows.sort(reverse=True)
    lines = ["| function | own ms/frame | cumulative ms/frame | calls/frame |", "|---|---:|---:|---:|"]
    for tottime, cumtime, ncalls, where in rows[:top]:
        lines.append(f"| `{where}` | {1e3 * tottime / calls:.2f} | {1e3 * cumtime / calls:.2f} | "
                     f"{ncalls / calls:.0f} |")
    return "\n".join(lines)


# ---------------------------------------------------------------------- server
def start_server(work: Path, http_impl: str, repo: Path = ROOT,
                 settings: dict[str, str] | None = None) -> tuple[subprocess.Popen, str, str]:
    """A ``facesynth serve`` of the source tree ``repo`` on free ports (no job workers), with
    ``settings`` (``FACESYNTH_*`` variables) beside the benchmark's; its HTTP base URL and
    gRPC address."""
    port, grpc_port = harness.free_port(), harness.free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    env.update({"FACESYNTH_DATA_DIR": str(work / "data"), "FACESYNTH_PORT": str(port),
                "FACESYNTH_GRPC_PORT": str(grpc_port), "FACESYNTH_WORKERS": "0",
                "FACESYNTH_HTTP": http_impl,
                # h11 on the plain asyncio loop (uvicorn without extras); httptools on uvloop
                "FACESYNTH_LOOP": "asyncio" if http_impl == "h11" else "uvloop",
                # the in-process reference's BLAS threads (BLAS_THREADS: serve's sizing)
                "FACESYNTH_BLAS_THREADS": str(BLAS_THREADS), "PYTHONPATH": str(repo),
                **(settings or {})})
    log = open(work / "server.log", "ab")
    server = subprocess.Popen([sys.executable, "-m", "service.cli", "serve"], cwd=repo, env=env,
                              stdout=log, stderr=log, stdin=subprocess.DEVNULL)
    import httpx

    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while True:
        try:
            if httpx.get(f"{base}/readyz", timeout=2).status_code == 200:
                return server, base, f"127.0.0.1:{grpc_port}"
        except httpx.TransportError:
            pass
        if server.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"the server did not start; see {work / 'server.log'}")
        time.sleep(0.3)


def stop_server(server: subprocess.Popen) -> None:
    server.terminate()
    try:
        server.wait(60)
    except subprocess.TimeoutExpired:
        server.kill()


#: the variant that calls through the SDK (``facesynth_client.Client`` with its default
#: transport, one keep-alive connection per server): triangles fetched once (``topology=false`` after the first answer), half maps,
#: the answer decoded as views of the body (``copy=False``)
SDK_VARIANT = ("SDK: half maps, topology once, copy=False", {"sdk": "true"})
#: the same through httpx's own transport (httpcore), the SDK's default before its
#: ``OnePieceTransport``
SDK_HTTPX_VARIANT = ("SDK over httpx's own transport", {"sdk": "httpx"})


def http_variants() -> list[tuple[str, dict]]:
    """The HTTP rows' variants that this tree's server (and SDK) support: (label, query)."""
    variants = [("float32, with faces", {})]
    if supports("topology"):
        variants.append(("half maps, topology=false", {"half": "true", "topology": "false"}))
    if sdk_supports_copy():
        variants.append(SDK_VARIANT)
    if sdk_has_transport():
        variants.append(SDK_HTTPX_VARIANT)
    return variants


def http_call(client, model_id: str, markers: np.ndarray, outputs, params: dict, size: list):
    """``call(k)``: one one-frame synthesis of ``markers[k]`` through the httpx ``client``,
    the response decoded with ``np.load`` (every array read); its body bytes into ``size``.
    ``params`` of :data:`SDK_VARIANT`: through the SDK instead (``size`` left at 0)."""
    from service.io.npz import npz_bytes

    if params.get("sdk"):
        from facesynth_client import Client

        import httpx

        sdk = Client(str(client.base_url), timeout=300,   # its own transport (the default)
                     transport=httpx.HTTPTransport() if params["sdk"] == "httpx" else None)

        def sdk_call(k: int) -> None:
            sdk.synthesis.synthesize(model_id, markers[k % len(markers)][None],
                                     outputs=list(outputs), half=True, copy=False)
        return sdk_call
    bodies = [npz_bytes(markers=m[None]) for m in markers]

    def call(k: int) -> None:
        r = client.post(f"/v1/models/{model_id}/synthesize", content=bodies[k % len(bodies)],
                        headers=NPZ, params={"outputs": ",".join(outputs), **params})
        r.raise_for_status()
        with np.load(io.BytesIO(r.content)) as d:
            for key in d.files:
                d[key]
        size[0] = len(r.content)
    return call


def http_ms(base: str, model, model_id: str, markers: np.ndarray, outputs, calls: int,
            params: dict) -> tuple[float, float, int]:
    """Median round trip (ms) of one-frame syntheses, the response decoded, and of the
    in-process frame, the two taking turns frame by frame (:func:`interleaved_ms`); body
    bytes."""
    import httpx

    size = [0]
    with httpx.Client(base_url=base, timeout=300) as client:
        got = interleaved_ms({
            "in-process": lambda k: model.synthesize(markers[k % len(markers)][None], outputs),
            "HTTP": http_call(client, model_id, markers, outputs, params, size)}, calls)
    return got["HTTP"]["ms"], got["in-process"]["ms"], size[0]


def server_cpu_seconds(pid: int) -> float:
    """CPU time (s) that the threads of process ``pid`` have run so far (Linux: the sum of
    ``/proc/<pid>/task/*/schedstat``, nanoseconds; NaN elsewhere)."""
    total = 0
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                total += int((task / "schedstat").read_text().split()[0])
            except (OSError, ValueError, IndexError):   # a thread that just ended
                pass
    except OSError:
        return float("nan")
    return total * 1e-9


def interleaved_ms(calls_by_path: dict, calls: int, pids: dict | None = None
                   ) -> dict[str, dict[str, float]]:
    """Per path, medians (ms) over its ``call(k)``s of the wall time (``ms``), of this
    process's CPU time (``client_cpu``: ``time.process_time``) and, for the paths named in
    ``pids`` (path → server process id), of that server's CPU time (``server_cpu``, NaN
    without), the paths taking turns frame by frame (in order, then reversed: a, b, c, c, b,
    a, …) after ``WARMUP`` calls each: on a shared machine only such interleaved timings
    compare, and the CPU times are what a frame costs whatever the scheduler gave it."""
    names = list(calls_by_path)
    pids = pids or {}
    for k in range(WARMUP):
        for name in names:
            calls_by_path[name](k)
    times: dict[str, list[tuple[float, float, float]]] = {name: [] for name in names}
    for k in range(calls):
        for name in names if k % 2 == 0 else names[::-1]:
            pid = pids.get(name)
            s0 = server_cpu_seconds(pid) if pid else float("nan")
            c0, t0 = time.process_time(), time.perf_counter()
            calls_by_path[name](k)
            t1, c1 = time.perf_counter(), time.process_time()
            s1 = server_cpu_seconds(pid) if pid else float("nan")
            times[name].append((t1 - t0, c1 - c0, s1 - s0))
    return {name: dict(zip(("ms", "client_cpu", "server_cpu"),
                           (1e3 * float(np.median(column)) for column in zip(*t))))
            for name, t in times.items()}


def against_rows(rev: str, work: Path, model, model_dir: Path, actor_dir: Path,
                 markers: np.ndarray, calls: int) -> list[dict]:
    """HTTP of commit ``rev``'s server against this tree's, interleaved frame by frame with
    the in-process frame (:func:`interleaved_ms`), per parser, output set and variant."""
    import httpx

    old_tree = harness.source_tree(rev, harness.OUT / "cold_start")
    rows = []
    variants = http_variants()
    for impl in http_impls():
        servers = {}
        try:
            for label, repo in ((rev, old_tree), ("this tree", ROOT)):
                servers[label] = start_server(work, impl, repo)
            model_id = harness.register_model(servers["this tree"][1], work, actor_dir, model_dir)
            clients = {label: httpx.Client(base_url=base, timeout=300)
                       for label, (_, base, _) in servers.items()}
            for name, outputs in OUTPUT_SETS.items():
                for variant, params in variants:
                    sizes = {label: [0] for label in clients}
                    paths = {"in-process": lambda k, o=outputs: model.synthesize(
                        markers[k % len(markers)][None], o)}
                    for label, client in clients.items():
                        paths[label] = http_call(client, model_id, markers, outputs, params,
                                                 sizes[label])
                    ms = interleaved_ms(paths, calls, {label: servers[label][0].pid
                                                       for label in clients})
                    for label in clients:
                        rows.append({"outputs": name, "path": f"HTTP {impl}, {variant}, {label}",
                                     "ms": ms[label]["ms"], "ref": ms["in-process"]["ms"],
                                     "client_cpu": ms[label]["client_cpu"],
                                     "server_cpu": ms[label]["server_cpu"],
                                     "ref_cpu": ms["in-process"]["client_cpu"],
                                     "bytes": sizes[label][0] or "–",
                                     "load": harness.load_average()})
                        print(rows[-1], file=sys.stderr, flush=True)
            for client in clients.values():
                client.close()
        finally:
            for server, _, _ in servers.values():
                stop_server(server)
    return rows


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (``/proc/<pid>/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def grpc_stream(target: str, model_id: str, markers: np.ndarray, outputs, calls: int,
                half: bool, pid: int | None = None) -> dict[str, float]:
    """One ``calls``-frame stream at ``IN_FLIGHT`` frames ahead (after ``WARMUP`` frames one
    at a time): ``ms`` wall time per frame, ``server_cpu`` CPU ms per frame of the server
    process ``pid`` (if given) and ``client_cpu`` of this process (the SDK's sending,
    receiving and decoding)."""
    from facesynth_client import StreamingClient

    frames = [markers[k % len(markers)] for k in range(calls)]
    kwargs = {"half": True} if half else {}
    with StreamingClient(target) as stream:
        for _ in stream.synthesize(model_id, frames[:WARMUP], outputs, max_in_flight=1, **kwargs):
            pass
        server0 = cpu_seconds(pid) if pid else 0.0
        client0 = time.process_time()
        t0 = time.perf_counter()
        n = sum(1 for _ in stream.synthesize(model_id, frames, outputs, max_in_flight=IN_FLIGHT,
                                             **kwargs))
        seconds = time.perf_counter() - t0
        client = time.process_time() - client0
        server = cpu_seconds(pid) - server0 if pid else float("nan")
    assert n == calls
    return {"ms": 1e3 * seconds / calls, "server_cpu": 1e3 * server / calls,
            "client_cpu": 1e3 * client / calls}


def against_grpc_rows(rev: str, work: Path, base_ms: dict, model_dir: Path, actor_dir: Path,
                      markers: np.ndarray, calls: int, rounds: int = 4) -> list[dict]:
    """gRPC streams of commit ``rev``'s server against this tree's, and this tree's with one
    synthesis slot (``FACESYNTH_MAX_CONCURRENT_SYNTHESES=1``, BLAS threads as the others),
    started side by side, whole streams taking turns (a, b, c, c, b, a, … ``rounds`` each)
    per output set and map precision: medians of the wall time per frame, and the CPU per
    frame of each server and of the client, over the rounds."""
    old_tree = harness.source_tree(rev, harness.OUT / "cold_start")
    servers = {}
    rows = []
    try:
        for label, repo, settings in ((rev, old_tree, None), ("this tree", ROOT, None),
                                      ("this tree, 1 synthesis slot", ROOT,
                                       {"FACESYNTH_MAX_CONCURRENT_SYNTHESES": "1"})):
            servers[label] = start_server(work, "h11", repo, settings)
        model_id = harness.register_model(servers["this tree"][1], work, actor_dir, model_dir)
        labels = list(servers)
        for name, outputs in OUTPUT_SETS.items():
            maps = len(outputs) > 1
            for half in (False, True) if maps and grpc_supports_half() else (False,):
                got: dict[str, list[dict]] = {label: [] for label in labels}
                for r in range(rounds):
                    for label in labels if r % 2 == 0 else labels[::-1]:
                        proc, _, target = servers[label]
                        got[label].append(grpc_stream(target, model_id, markers, outputs, calls,
                                                      half, proc.pid))
                for label in labels:
                    med = {k: float(np.median([g[k] for g in got[label]])) for k in got[label][0]}
                    rows.append({"outputs": name, "path": f"gRPC stream, {IN_FLIGHT} in flight"
                                 + (", half maps" if half else "") + f", {label}",
                                 "ref": base_ms[name], "load": harness.load_average(), **med,
                                 "fps_rounds": [round(1e3 / g["ms"], 1) for g in got[label]]})
                    print(rows[-1], file=sys.stderr, flush=True)
    finally:
        for server, _, _ in servers.values():
            stop_server(server)
    return rows


#: the HTTP implementations to measure (``--impls``; default every installed one)
IMPLS: list[str] | None = None


def http_impls() -> list[str]:
    if IMPLS is not None:
        return IMPLS
    impls = ["h11"]
    try:
        import httptools  # noqa: F401
        import uvloop  # noqa: F401
        impls.append("httptools")
    except ImportError:
        print("httptools/uvloop not installed: HTTP with h11 only", file=sys.stderr)
    return impls


def supports(flag: str) -> bool:
    """Whether this tree's HTTP route has the query flag (rows of older trees are skipped)."""
    from service.api.routes import synthesis

    import inspect
    return flag in inspect.signature(synthesis.synthesize).parameters


def sdk_supports_copy() -> bool:
    """Whether the SDK on the path decodes answers as views (``synthesize(copy=False)``; run
    with ``PYTHONPATH=clients/python/src`` for this tree's SDK)."""
    import inspect

    from facesynth_client.resources.synthesis import Synthesis
    return "copy" in inspect.signature(Synthesis.synthesize).parameters


def sdk_has_transport() -> bool:
    """Whether the SDK on the path has its own transport (``facesynth_client.transport``)."""
    import importlib.util

    return importlib.util.find_spec("facesynth_client.transport") is not None


def grpc_supports_half() -> bool:
    import inspect

    from facesynth_client import StreamingClient
    return "half" in inspect.signature(StreamingClient.synthesize).parameters


# ---------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", type=Path, default=None,
                        help="sample actor directory (default "
                             "benchmarks/out/actor-l1, built if missing)")
    parser.add_argument("--calls", type=int, default=100, help="calls per median (default 100)")
    parser.add_argument("--paths", default="inproc,http,grpc")
    parser.add_argument("--profile", action="store_true", help="add a cProfile breakdown")
    parser.add_argument("--against", metavar="REV", default=None,
                        help="a server of commit REV and one of this tree: HTTP frames "
                             "interleaved with the in-process one, gRPC streams taking turns "
                             "(cold_start.py's unpacked tree; REV must read the same database "
                             "schema)")
    parser.add_argument("--impls", default=None,
                        help="HTTP implementations, comma-separated (h11, httptools; default "
                             "every installed one)")
    parser.add_argument("--outputs", default=None,
                        help="output sets by name, comma-separated (mesh, maps; default both)")
    parser.add_argument("--rounds", type=int, default=4,
                        help="with --against: streams per server and output set (default 4)")
    args = parser.parse_args(argv)
    global IMPLS
    if args.impls:
        IMPLS = args.impls.split(",")
    if args.outputs:
        wanted = {"mesh": "mesh", "maps": "mesh + displacement + normal map"}
        for key in set(OUTPUT_SETS) - {wanted[o] for o in args.outputs.split(",")}:
            del OUTPUT_SETS[key]
    actor_dir = args.actor
    if actor_dir is None:
        actor_dir = harness.sample_actor("a", 1)
    paths = set(args.paths.split(","))
    WORK.mkdir(parents=True, exist_ok=True)
    model_dir = harness.ensure_realtime_model(actor_dir)
    markers = harness.heldout_markers(actor_dir)

    from service.methods.pdm.model import PdmModel

    meta = {"load_start": harness.load_average(), "cpus": os.cpu_count(), "blas": BLAS_THREADS}
    t0 = time.perf_counter()
    model = PdmModel.load(model_dir)
    meta["load_s"] = time.perf_counter() - t0
    meta["vertices"], meta["fine"] = model.n_vertices, model.data.fine.resolution
    rows: list[dict] = []
    base_ms: dict[str, float] = {}
    profiles: dict[str, str] = {}
    from service.geometry import ranges

    every_core = cores()
    for name, outputs in OUTPUT_SETS.items():
        base_ms[name] = in_process(model, markers, outputs, args.calls)
        rows.append({"outputs": name, "path": "in-process", "ms": base_ms[name], "load": harness.load_average()})
        print(rows[-1], file=sys.stderr, flush=True)
        if every_core > 1:  # one frame at a time on every core (ranges.frame_threads)
            with ranges.frame_threads(every_core):
                ms = in_process(model, markers, outputs, args.calls)
            rows.append({"outputs": name, "path": f"in-process, {every_core} kernel threads",
                         "ms": ms, "every_core": True, "load": harness.load_average()})
            print(rows[-1], file=sys.stderr, flush=True)
        if args.profile:
            profiles[name] = profile(model, markers, outputs, min(args.calls, 30))

    if args.against:
        work = WORK / f"work-{model_dir.name}"      # per model: its registered id is reused
        work.mkdir(parents=True, exist_ok=True)
        if "http" in paths:
            rows += against_rows(args.against, work, model, model_dir, actor_dir, markers, args.calls)
        if "grpc" in paths:
            rows += against_grpc_rows(args.against, work, base_ms, model_dir, actor_dir, markers,
                                      args.calls, args.rounds)
        paths -= {"http", "grpc"}
    if paths & {"http", "grpc"}:
        work = WORK / f"work-{model_dir.name}"      # per model: its registered id is reused
        work.mkdir(parents=True, exist_ok=True)
        variants = http_variants()
        for impl in http_impls():
            server, base, target = start_server(work, impl)
            try:
                model_id = harness.register_model(base, work, actor_dir, model_dir)
                for name, outputs in OUTPUT_SETS.items():
                    if "http" in paths:
                        for label, params in variants:
                            ms, ref, size = http_ms(base, model, model_id, markers, outputs,
                                                    args.calls, params)
                            rows.append({"outputs": name, "path": f"HTTP {impl}, {label}", "ms": ms,
                                         "ref": ref, "bytes": size or "–",
                                         "load": harness.load_average()})
                            print(rows[-1], file=sys.stderr, flush=True)
                    if "grpc" in paths and impl == "h11":
                        # in-process again beside the server: the ratio is within the same minute
                        ref = in_process(model, markers, outputs, args.calls)
                        for half in (False, True) if grpc_supports_half() else (False,):
                            got = grpc_stream(target, model_id, markers, outputs, args.calls, half,
                                              server.pid)
                            rows.append({"outputs": name, "path": f"gRPC stream, {IN_FLIGHT} in flight"
                                         + (", half maps" if half else ""), **got, "ref": ref,
                                         "load": harness.load_average()})
                            print(rows[-1], file=sys.stderr, flush=True)
            finally:
                stop_server(server)
    meta["load_end"] = harness.load_average()
    text = report(rows, base_ms, meta, actor_dir, args.calls, profiles)
    print(text)
    (OUT / "realtime.md").write_text(text)
    return 0


def report(rows, base_ms, meta, actor_dir, calls, profiles) -> str:
    import numpy
    cpu = any("server_cpu" in r for r in rows)   # --against: CPU medians per frame too
    lines = [
        "# The real-time path (issue 23): one PDM frame in-process, over HTTP, over gRPC",
        "",
        f"Actor {actor_dir} ({meta['vertices']:,} vertices, fine map {meta['fine']}²), the same "
        f"model on every path (loaded in {meta['load_s']:.1f} s). Medians over {calls} calls; "
        f"gRPC: wall time per frame of a {calls}-frame stream. {meta['cpus']} CPUs, "
        f"{meta['blas']} BLAS thread(s) in-process and in the servers, NumPy "
        f"{numpy.__version__}; load average (1, 5, 15 min) {meta['load_start']} at the start, "
        f"{meta['load_end']} at the end. Ratio: against in-process in the same run (HTTP: "
        "the in-process frames taking turns with its calls; gRPC: measured again beside the "
        "server)."
        + (" CPU columns (`--against`): medians per frame of this process's CPU time (the "
           "client's; for in-process the synthesis itself) and of the server process's (all "
           "its threads, /proc schedstat)." if cpu else ""),
        "",
        "| outputs | path | ms/frame | frames/s | × in-process | body bytes | load average |"
        + (" client CPU ms | server CPU ms | in-process CPU ms |" if cpu else ""),
        "|---|---|---:|---:|---:|---:|---|" + ("---:|---:|---:|" if cpu else ""),
    ]
    for r in rows:
        ref = r.get("ref", base_ms[r["outputs"]])
        lines.append(f"| {r['outputs']} | {r['path']} | {r['ms']:.1f} | {1e3 / r['ms']:.1f} | "
                     f"{r['ms'] / ref:.2f}× | {r.get('bytes', '–')} | {r['load']} |"
                     + ("".join(f" {r[k]:.1f} |" if k in r else " – |"
                                for k in ("client_cpu", "server_cpu", "ref_cpu")) if cpu else ""))
    lines += ["", "Targets (level 1):", ""]
    for name in OUTPUT_SETS:
        got = base_ms[name]
        every = [r["ms"] for r in rows if r["outputs"] == name and r.get("every_core")]
        best = min([got, *every])
        lines.append(f"- in-process {name} ≤ {TARGET_MS[name]:g} ms: "
                     f"**{'met' if best <= TARGET_MS[name] else 'missed'}** ({got:.1f} ms as "
                     "the servers size it" + (f", {every[0]:.1f} ms on every core" if every else "")
                     + ")")
        http = [r for r in rows if r["outputs"] == name and r["path"].startswith("HTTP")]
        if http:
            best = min(http, key=lambda r: r["ms"] / r["ref"])
            ratio = best["ms"] / best["ref"]
            lines.append(f"- HTTP {name} ≤ {TARGET_HTTP[name]:g}× in-process: "
                         f"**{'met' if ratio <= TARGET_HTTP[name] else 'missed'}** "
                         f"({ratio:.2f}×, {best['path']})")
        grpc = [r for r in rows if r["outputs"] == name and r["path"].startswith("gRPC")]
        if grpc:
            fps = 1e3 / min(r["ms"] for r in grpc)
            lines.append(f"- gRPC {name} ≥ {TARGET_FPS[name]:g} frames/s: "
                         f"**{'met' if fps >= TARGET_FPS[name] else 'missed'}** ({fps:.1f} frames/s)")
    for name, table in profiles.items():
        lines += ["", f"cProfile, in-process, {name} (top functions by own time):", "", table]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())

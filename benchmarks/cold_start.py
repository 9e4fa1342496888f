"""Cold start of a real ``facesynth serve`` (issue 23): how long until the first frame.

The same trained PDM (default parameters: medium 512², fine 1024²) of the level-1 sample
actor is registered once as a ready model in a data directory (as ``realtime.py`` does:
actor and one clip uploaded through the API, the model row marked ready with the trained
directory). Then, alternating, fresh server processes are started

* **without preload**: the first request loads the model (what issue 23 measured: 7.7 s);
* **with preload** (``FACESYNTH_PRELOAD=<model id>``): the model loads in the background
  while the server already answers; ``/readyz`` is 503 (check ``models``) until it is in
  the cache.

For each server: seconds from spawn until ``/healthz`` answers (imports, database), until
``/readyz`` answers 200, the latency of the first frame sent once it is ready (one frame of
held-out markers, ``outputs=mesh``), of the first frame with the maps
(``mesh,displacement,normal_map``: the normal mapper is built at load, so this frame does
not build it), and the median of the next ``--calls`` mesh frames (steady state); also the
server's resident memory (VmRSS) once the model is loaded, and the server's CPU seconds
until ready and for the first frame (``/proc/<pid>/stat``: what the load costs whatever
else the machine runs). A preload also synthesizes one neutral frame
(``Services.warm_up``) before the server reports ready. The target is the first frame
after ``serve`` is ready ≤ 2 s.

The model cache's weight of the model is checked against its resident cost (issue 23:
within 10 %) in a fresh process (``--footprint``): the model is loaded and synthesizes a
frame of every output once and is dropped (imports, compiled kernels, lazily built state
all in place), then loaded again the way the service loads it and synthesizes one maps
frame; the resident memory that second load added (VmRSS, file pages of the mapped arrays
included, the free heap handed back as ``Services`` does) against ``footprint.nbytes``, the
cache's weight; then every output of that frame and of the out-of-range performance's
farthest frame (where the detail fades: what a cached model serving any request holds).

Run: ``python benchmarks/cold_start.py [--actor DIR] [--model DIR] [--rounds 2]
[--against REV] [--footprint]``. The model is trained once into ``benchmarks/out/realtime/model-<actor>``
(shared with realtime.py) unless ``--model`` names one. Writes the table to stdout and
``benchmarks/out/cold_start.md`` (``--out DIR``: ``DIR/cold_start.md``, work under
``DIR/cold_start``). The machine is shared: the load average is recorded beside
every row. With ``--against REV`` every round starts a server of the commit REV
(``git archive REV service models_store``, unpacked once into
``benchmarks/out/cold_start/rev-<REV>``) and one of this tree, in alternating order, on the
same data directory and model: on a loaded machine only such pairs compare (REV must read
the same database schema).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import harness  # noqa: E402

ROOT = harness.ROOT
OUT = ROOT / "benchmarks" / "out"
NPZ = harness.NPZ_TYPE
TARGET_S = 2.0
MESH = "mesh"
MAPS = "mesh,displacement,normal_map"


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) the process ``pid`` has used."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def spawn(work: Path, port: int, preload: str | None, repo: Path = ROOT) -> subprocess.Popen:
    """``facesynth serve`` of the source tree ``repo`` on ``port`` (data in ``work/data``)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    env.update({"FACESYNTH_DATA_DIR": str(work / "data"), "FACESYNTH_PORT": str(port),
                "FACESYNTH_GRPC_PORT": str(harness.free_port()), "FACESYNTH_WORKERS": "0",
                "PYTHONPATH": str(repo)})
    if preload:
        env["FACESYNTH_PRELOAD"] = preload
    log = open(work / "server.log", "ab")
    return subprocess.Popen([sys.executable, "-m", "service.cli", "serve"], cwd=repo, env=env,
                            stdout=log, stderr=log, stdin=subprocess.DEVNULL)


def wait_for(url: str, server: subprocess.Popen, t0: float, timeout: float = 600) -> float:
    """Seconds from ``t0`` until ``url`` answers 200."""
    import httpx

    while True:
        try:
            if httpx.get(url, timeout=2).status_code == 200:
                return time.perf_counter() - t0
        except httpx.TransportError:
            pass
        if server.poll() is not None or time.perf_counter() - t0 > timeout:
            raise RuntimeError("the server did not get ready; see server.log in its work directory")
        time.sleep(0.05)


def one_server(work: Path, model_id: str, markers: np.ndarray, preload: bool, calls: int,
               repo: Path = ROOT) -> dict:
    import httpx

    from service.io.npz import npz_bytes

    port = harness.free_port()
    base = f"http://127.0.0.1:{port}"
    t0 = time.perf_counter()
    server = spawn(work, port, model_id if preload else None, repo)
    try:
        row = {"preload": preload, "healthz_s": wait_for(f"{base}/healthz", server, t0)}
        row["ready_s"] = wait_for(f"{base}/readyz", server, t0)
        row["cpu_ready_s"] = cpu_s(server.pid)
        with httpx.Client(base_url=base, timeout=600) as client:
            def frame(k: int, outputs: str) -> float:
                t = time.perf_counter()
                r = client.post(f"/v1/models/{model_id}/synthesize", headers=NPZ,
                                content=npz_bytes(markers=markers[k % len(markers)][None]),
                                params={"outputs": outputs})
                r.raise_for_status()
                return time.perf_counter() - t

            cpu = cpu_s(server.pid)
            row["first_s"] = frame(0, MESH)
            row["first_cpu_s"] = cpu_s(server.pid) - cpu
            row["first_after_spawn_s"] = time.perf_counter() - t0
            row["first_maps_s"] = frame(1, MAPS)
            row["steady_ms"] = 1e3 * float(np.median([frame(2 + k, MESH) for k in range(calls)]))
        row["rss_mb"] = rss_mb(server.pid)
        row["load"] = harness.load_average()
        return row
    finally:
        harness.stop_server(server)


def footprint(model_dir: Path, actor: Path) -> dict:
    """The cache's weight of the model against the resident memory a load adds (module
    docstring; run in a fresh process: ``--footprint-worker``)."""
    import gc

    from service.app.memory import release_free_heap
    from service.methods.footprint import nbytes
    from service.methods.kinds import get_kind

    kind = get_kind("pdm")
    markers = harness.heldout_markers(actor)[:1].astype(np.float64)
    outputs = [o for o in ("mesh", "displacement", "normal_map") if o in kind.outputs]
    model = kind.load(model_dir)
    model.synthesize(markers, outputs)
    del model
    gc.collect()
    release_free_heap()
    before = harness.status_kb("VmRSS")
    t = time.process_time()
    model = kind.load(model_dir)
    load_cpu = time.process_time() - t
    release_free_heap()
    loaded = harness.status_kb("VmRSS")
    model.synthesize(markers, outputs)
    release_free_heap()
    after = harness.status_kb("VmRSS")
    # then every output, on that frame and on the out-of-range performance's farthest (faded)
    with np.load(actor / "performances" / "heldout_out_of_range.npz") as d:
        far = d["markers"].astype(np.float64)
    far = far[np.argmax(np.linalg.norm(far - far[:1], axis=-1).sum(axis=1))][None]
    model.synthesize(np.concatenate([markers, far]), list(kind.outputs))
    release_free_heap()
    every = harness.status_kb("VmRSS")
    weight = nbytes(model, mapped=kind.weighs_mapped)
    files = sum(f.stat().st_size for f in model_dir.rglob("*") if f.is_file())
    return {"weight_mb": weight / 2**20, "heap_weight_mb": nbytes(model, mapped=False) / 2**20,
            "resident_loaded_mb": (loaded - before) / 1024,
            "resident_mb": (after - before) / 1024, "resident_every_mb": (every - before) / 1024,
            "files_mb": files / 2**20,
            "load_cpu_s": load_cpu, "load": harness.load_average()}


def footprint_table(model_dir: Path, actor: Path) -> str:
    """:func:`footprint` in a fresh process, as a table."""
    from service.app.threads import apply_blas_threads

    env = dict(os.environ)
    apply_blas_threads(None, None, env)           # serve's BLAS threads (before NumPy loads)
    code = subprocess.run([sys.executable, __file__, "--footprint-worker", "--model", str(model_dir),
                           "--actor", str(actor)], cwd=ROOT, check=True, capture_output=True,
                          text=True, env=env).stdout.strip().splitlines()[-1]
    import json

    r = json.loads(code)
    return "\n".join([
        "Cache weight against resident cost (fresh process, second load; target within 10 %; then "
        "every output on that frame and on the out-of-range performance's farthest, where the detail fades):", "",
        "| files MB | cache weight MB (mapped + heap) | heap part MB | resident after load MB | "
        "resident after a maps frame MB | weight / it | resident after every output MB | weight / it "
        "| load CPU s | load average |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        f"| {r['files_mb']:.0f} | {r['weight_mb']:.0f} | {r['heap_weight_mb']:.0f} | "
        f"{r['resident_loaded_mb']:.0f} | {r['resident_mb']:.0f} | {r['weight_mb'] / r['resident_mb']:.3f} | "
        f"{r['resident_every_mb']:.0f} | {r['weight_mb'] / r['resident_every_mb']:.3f} | "
        f"{r['load_cpu_s']:.2f} | {r['load']} |"]) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actor", type=Path, default=OUT / "actor-l1")
    parser.add_argument("--model", type=Path, default=None,
                        help="a trained PDM model directory (default: realtime.py's, trained once)")
    parser.add_argument("--rounds", type=int, default=2, help="servers per setting (default 2)")
    parser.add_argument("--calls", type=int, default=10, help="steady-state frames per server")
    parser.add_argument("--against", metavar="REV", default=None,
                        help="also start servers of this older commit, paired and alternating")
    parser.add_argument("--out", type=Path, default=OUT,
                        help="where cold_start.md and the cold_start/ work directory go "
                             "(default benchmarks/out)")
    parser.add_argument("--footprint", action="store_true",
                        help="also the cache weight against the resident cost (fresh process)")
    parser.add_argument("--footprint-worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.footprint_worker:
        import json

        print(json.dumps(footprint(args.model.resolve(), args.actor.resolve())))
        return 0
    trees = {"this tree": ROOT}
    if args.against:
        trees = {args.against: harness.source_tree(args.against, args.out / "cold_start"), **trees}
    actor = args.actor.resolve()
    model_dir = (args.model or harness.ensure_realtime_model(actor)).resolve()
    work = args.out / "cold_start" / f"work-{model_dir.name}"      # per model: its registered id is reused
    work.mkdir(parents=True, exist_ok=True)
    markers = harness.heldout_markers(actor)
    port = harness.free_port()
    server = harness.start_server(work, port, {"FACESYNTH_WORKERS": "0"})
    try:
        model_id = harness.register_model(f"http://127.0.0.1:{port}", work, actor, model_dir)
    finally:
        harness.stop_server(server)
    rows = []
    for r in range(args.rounds):
        for preload in (False, True):
            order = list(trees) if r % 2 == 0 else list(reversed(trees))
            for tree in order:
                rows.append({"tree": tree, **one_server(work, model_id, markers, preload,
                                                        args.calls, trees[tree])})
                print(rows[-1], file=sys.stderr, flush=True)
    rows.sort(key=lambda r: (list(trees).index(r["tree"]), r["preload"]))
    lines = [f"## Cold start, {actor.name} (PDM {model_dir.name}), {harness.git_state()}", "",
             f"{os.cpu_count()} cores. Seconds from spawning `facesynth serve`; first frame = "
             "latency of the first request sent once /readyz is 200; target ≤ "
             f"{TARGET_S:g} s.", "",
             "| tree | preload | /healthz s | /readyz s | server CPU s until ready | first frame s (mesh) | "
             "its server CPU s | first frame after spawn s | first maps frame s | steady ms (mesh) | "
             "server RSS MB | load average |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['tree']} | {'yes' if r['preload'] else 'no'} | {r['healthz_s']:.1f} | {r['ready_s']:.1f} | "
                     f"{r['cpu_ready_s']:.1f} | {r['first_s']:.2f} | {r['first_cpu_s']:.2f} | "
                     f"{r['first_after_spawn_s']:.1f} | {r['first_maps_s']:.2f} | "
                     f"{r['steady_ms']:.0f} | {r['rss_mb']:.0f} | {r['load']} |")
    text = "\n".join(lines) + "\n"
    if args.footprint:
        text += "\n" + footprint_table(model_dir, actor)
    print(text)
    (args.out / "cold_start.md").write_text("# Cold start (benchmarks/cold_start.py)\n\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

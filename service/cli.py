"""The ``facesynth`` command line: one entry point, a subcommand per task.

    facesynth sample-actor --out DIR --seed N --level 0|1|2   build the sample actor
              [--family a|b] [--units mm|cm|m]              (family b: levels 0|1, any unit)
    facesynth sample-gallery --actor DIR --out DIR             render a built actor to PNGs
    facesynth demo [--out DIR] [--server URL]                  sample actor → upload → train → synthesize → PNG
    facesynth worker [--data-dir DIR] [--workers N]            run jobs (training, synthesis) from the queue
    facesynth actors|upload|train|jobs|synthesize|enhance|models ...
                                                               talk to a server through the SDK
                                                               (see service.client_cli)
    facesynth serve [--host H] [--port P] [--grpc-port G] [--data-dir DIR] [--workers N]
                                                               HTTP API + gRPC + embedded job workers
                                                               (--workers 0: API + gRPC only)
    facesynth store fsck [--remove] [--min-age S]             orphaned / missing blobs (and removal)
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Callable

from service.progress_bar import progress_bar as _progress_bar


def _summary(out: Path, manifest: dict) -> str:
    perf = manifest["performances"]
    lines = [
        f"sample actor (seed {manifest['seed']}, level {manifest['level']}) in {out}/ "
        f"built in {manifest['build_seconds']} s",
        f"  neutral: {manifest['vertices']} vertices, {manifest['triangles']} triangles, UVs in [0,1]², "
        f"{manifest['units']}",
        f"  markers: {manifest['markers']} (markers.json)",
        f"  maps: displacement {manifest['map_resolution']}², albedo {manifest['albedo_resolution']}²",
        f"  wrinkle sites: {', '.join(manifest['wrinkle_sites'])}",
        "  performances:",
    ]
    lines += [f"    {name:24s} {p['kind']:22s} {p['frames']:4d} frames" for name, p in perf.items()]
    total = sum(f["bytes"] for f in manifest["files"].values())
    lines.append(f"  {len(manifest['files'])} files, {total / 2**20:.0f} MiB, listed with sha256 in manifest.json")
    return "\n".join(lines)


def cmd_sample_actor(args: argparse.Namespace) -> int:
    from service.samples.actor import build_sample_actor

    if args.family == "b":
        from service.samples.family_b.actor import build_family_b

        if args.level not in (0, 1):
            print("family b has levels 0 and 1", file=sys.stderr)
            return 2
        if args.no_database_maps:
            print("family b always gives its database performance maps", file=sys.stderr)
            return 2
        manifest = build_family_b(args.out, seed=args.seed, level=args.level, units=args.units,
                                  progress=_progress_bar("sample actor (family b)"),
                                  with_tracking=False if args.no_tracking else None)
        print(_summary(Path(args.out), manifest))
        return 0
    if args.units != "mm":
        print("family a is written in mm only (--family b for other units)", file=sys.stderr)
        return 2
    manifest = build_sample_actor(args.out, seed=args.seed, level=args.level,
                                  progress=_progress_bar("sample actor"),
                                  with_tracking=not args.no_tracking,
                                  database_maps=False if args.no_database_maps else None)
    print(_summary(Path(args.out), manifest))
    return 0


def cmd_sample_gallery(args: argparse.Namespace) -> int:
    from service.samples.gallery import write_gallery

    for path in write_gallery(args.actor, args.out):
        print(path)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    import os

    from service.demo import run_demo

    run_demo(args.out, server=args.server or os.environ.get("FACESYNTH_URL"),
             token=args.token, seed=args.seed, level=args.level)
    return 0


def cmd_pdm_train(args: argparse.Namespace) -> int:
    from service.methods.pdm.model import PdmParams, train
    from service.samples import dataset

    actor = dataset.load_actor(args.actor)
    names = args.clips or dataset.performance_names(args.actor, "train_")
    clips = [dataset.load_clip(args.actor, name, actor) for name in names]
    given = {k: v for k, v in (("gamma", args.gamma), ("ridge", args.ridge))
             if v is not None}                                # else the method's defaults
    if args.margin is not None:
        given["extrapolation_margin"] = None if args.margin < 0 else args.margin
    params = PdmParams(order=args.order, medium_resolution=args.medium_resolution,
                       fine_resolution=args.fine_resolution, **given)
    model = train(actor, clips, params, progress=_progress_bar("pdm train"))
    manifest = model.save(args.out)
    m = model.metrics
    print(f"{args.out}: pdm ({params.order}), {m['training_frames']} frames from {len(clips)} clips, "
          f"{manifest['size_bytes'] / 2**20:.1f} MiB")
    print("  medium vertex RMS (mm): " + ", ".join(f"{k} {v:.3f}" for k, v in m["medium_vertex_rms_mm"].items()))
    print("  fine fit RMS (mm):      " + ", ".join(f"{k} {v:.4f}" for k, v in m["fine_fit_rms_mm"].items()))
    print("  PCA energy (Table 1):   " + " / ".join(f"{100 * e:.1f}%" for e in m["pca_energy"]))
    return 0


def cmd_pdm_synthesize(args: argparse.Namespace) -> int:
    import numpy as np

    from service.io.atomic import write_npz
    from service.io.markers import read_markers
    from service.methods.pdm.model import PdmModel

    model = PdmModel.load(args.model)
    if args.markers.suffix == ".npz":
        with np.load(args.markers, allow_pickle=False) as d:
            markers = d["markers"]
    else:
        markers = read_markers(args.markers).positions
    outputs = tuple(args.outputs.split(","))
    bar = _progress_bar("pdm synthesize")
    parts = []
    for s in range(0, len(markers), 8):
        parts.append(model.synthesize(markers[s:s + 8], outputs=outputs, clamp=not args.no_clamp))
        bar(min(s + 8, len(markers)) / len(markers), "synthesize")
    out = {k: parts[0][k] if k == "faces" else np.concatenate([p[k] for p in parts]) for k in parts[0]}
    write_npz(args.out, out)
    print(f"{args.out}: {len(markers)} frames, " + ", ".join(f"{k} {v.shape}" for k, v in out.items()))
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    from service.config import Settings
    from service.jobs.worker import run_worker
    from service.logs import configure_logging

    configure_logging()
    overrides = {name: getattr(args, name) for name in ("data_dir", "database_url", "queue_url",
                                                        "queue_name", "workers")
                 if getattr(args, name) is not None}
    run_worker(Settings(**overrides))
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    """Probe the database, the blob store and the job queue of the FACESYNTH_* settings
    (what ``/readyz`` checks, for a process that serves no HTTP: the worker's container
    healthcheck). Prints the checks as JSON; exit 0 when all are ok, 1 otherwise. The
    database is not migrated."""
    import json

    from models_store.cache import ByteLRUCache
    from service.app.services import Services
    from service.config import Settings
    from service.store.container import get_store

    overrides = {name: getattr(args, name) for name in ("data_dir", "database_url", "queue_url")
                 if getattr(args, name) is not None}
    settings = Settings(**overrides)
    services = Services(settings=settings, store=get_store(settings), models=ByteLRUCache(0))
    try:
        checks = services.check()
    finally:
        services.close()
    print(json.dumps(checks))
    return 0 if all(value == "ok" for value in checks.values()) else 1


def _listen(host: str, port: int):
    """A listening TCP socket on ``host:port`` (IPv6 for an address with a colon).

    Raises
    ------
    OSError   the address cannot be bound (e.g. ``EADDRINUSE``)
    """
    import socket

    bare = host.strip("[]")
    family = socket.AF_INET6 if ":" in bare else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT only, not sharing
        sock.bind((bare, port))
        sock.listen(2048)
    except OSError:
        sock.close()
        raise
    sock.set_inheritable(True)
    return sock


def _serve_error(message: str) -> int:
    """One line on stderr and exit status 2 (a usage or environment problem, no traceback)."""
    print(f"facesynth serve: {message}", file=sys.stderr)
    return 2


def cmd_serve(args: argparse.Namespace) -> int:
    """The HTTP API (uvicorn), the gRPC streaming server (same host) and embedded job
    workers, sharing one database, blob store and model cache, until SIGINT/SIGTERM.

    Both addresses are bound before anything is served: a port that cannot be bound is
    one line naming ``--port`` or ``--grpc-port`` and exit status 2, and so is a queue URL
    of an unsupported form (or ``memory://`` with workers). With ``--preload`` (setting
    ``preload``) the named models (or ``all`` ready ones) are checked at once (an unknown or
    unready one: exit status 2) and loaded into the cache in the background (started before
    the gRPC server, issue 23's cold start) while the process serves; /readyz answers 503
    until they are loaded, and the job threads (embedded workers, or the maintenance rounds
    with ``--workers 0``) start only 2 s after that, so that Huey's import and their first
    rounds compete neither with the load nor with the first frames (issue 23's cold start; :mod:`service.jobs.job_threads`: a start that
    fails then is logged and fails /readyz)."""
    from service.app.collection import pause_collection

    # until the server is ready: the start's imports and the preload allocate mostly live
    # objects, which the cyclic collector would scan for nothing (service.app.collection)
    resume_collection = pause_collection()
    try:
        return _serve(args, resume_collection)
    finally:
        resume_collection()


def _serve(args: argparse.Namespace, resume_collection: Callable[[], None]) -> int:
    """:func:`cmd_serve` with the collector paused; ``resume_collection`` turns it back on."""
    import logging
    import signal

    from service.app.collection import resume_when
    from service.app.threads import apply_blas_threads
    from service.config import Settings
    from service.jobs.queue_storage import queue_storage, worker_storage

    overrides = {name: getattr(args, name) for name in ("host", "port", "grpc_port", "data_dir",
                                                        "workers")
                 if getattr(args, name) is not None}
    settings = Settings(**overrides)
    try:  # the queue URL's form, before anything loads (/readyz probes the storage itself)
        (worker_storage if settings.workers > 0 else queue_storage)(settings)
    except ValueError as error:
        return _serve_error(f"FACESYNTH_QUEUE_URL: {error}")
    # before NumPy loads: BLAS threads sized with the synthesis slots (service.app.threads)
    blas_threads = apply_blas_threads(settings.max_concurrent_syntheses, settings.blas_threads)

    from service.logs import configure_logging
    from service.app.services import Services
    from service.errors import FacesynthError
    from service.grpc.server import is_loopback, serve
    from service.jobs.job_threads import AFTER_PRELOAD_SECONDS, JobThreads
    if not settings.tokens and not is_loopback(settings.host):
        print(f"facesynth serve: refusing to listen on {settings.host} without tokens; set "
              "FACESYNTH_TOKENS, or listen on loopback (127.0.0.1)", file=sys.stderr)
        return 2
    configure_logging()

    def stop(signum: int, frame: object) -> None:
        # uvicorn handles SIGTERM itself and re-raises it once the HTTP server has shut down:
        # with the default action the process died there, skipping the `finally` below (the
        # embedded workers' grace period, the gRPC drain); exit through it instead
        raise SystemExit(0)

    log = logging.getLogger("facesynth.serve")
    preload = ([m.strip() for part in args.preload for m in part.split(",") if m.strip()]
               if args.preload else settings.preload)
    try:
        http_socket = _listen(settings.host, settings.port)
    except OSError as error:
        return _serve_error(f"cannot listen on {settings.host}:{settings.port} for HTTP "
                            f"({error.strerror or error}); choose another --port "
                            "(FACESYNTH_PORT)")
    previous_sigterm = signal.signal(signal.SIGTERM, stop)
    services = Services.open(settings)
    jobs = services.job_threads = JobThreads(settings)
    grpc_server = preloading = None
    try:
        if preload:   # checked now, loaded in the background; /readyz waits for them. Started
            try:      # first: the gRPC server's start (~40 ms) and the API's imports overlap it
                preloading = services.start_preload(preload)
            except FacesynthError as error:
                return _serve_error(f"--preload: {error}")
        try:
            grpc_server = serve(services.load_model, settings.host, settings.grpc_port,
                                tokens=settings.tokens,
                                # the synthesis slots the BLAS threads were sized
                                # against, shared with the HTTP syntheses
                                synthesis=services.synthesis)
        except RuntimeError as error:
            return _serve_error(f"cannot listen on {settings.host}:{settings.grpc_port} for "
                                f"gRPC ({error}); choose another --grpc-port "
                                "(FACESYNTH_GRPC_PORT)")
        # imported only now, while the preload thread loads (issue 23: the API's imports,
        # ~0.5 s CPU, then overlap the model load instead of delaying its start)
        import uvicorn

        from service.api.app import create_app

        # embedded workers, or with --workers 0 (API only, jobs run on `facesynth worker`
        # processes) the maintenance rounds: expired leases reaped and lost messages
        # resubmitted even with no worker alive. After a preload, shortly after it is done
        if preloading is None:
            jobs.start()
        else:
            jobs.start_after(preloading.done, AFTER_PRELOAD_SECONDS)
        from service.api.connections import protocol_class

        try:
            http = protocol_class(settings.header_timeout_seconds, settings.min_body_rate_bytes,
                                  settings.body_rate_grace_seconds,
                                  settings.max_connections_per_client, http=settings.http)
            if settings.loop == "uvloop":
                import uvloop  # noqa: F401
        except (ValueError, ImportError) as error:
            return _serve_error(f"{error} (FACESYNTH_HTTP / FACESYNTH_LOOP)")
        log.info("facesynth serving HTTP on http://%s:%d (docs at /docs) and gRPC on %s:%d",
                 settings.host, settings.port, settings.host, settings.grpc_port,
                 extra={"http": f"{settings.host}:{settings.port}",
                        "grpc": f"{settings.host}:{settings.grpc_port}",
                        "workers": settings.workers, "http_parser": http.__name__,
                        "loop": settings.loop, "blas_threads": blas_threads})
        config = uvicorn.Config(create_app(settings, services=services), host=settings.host,
                                port=settings.port, log_config=None, access_log=False, http=http,
                                loop=settings.loop)
        # the imports are done; the preload (if any) may still be loading
        resume_when(resume_collection, preloading.done if preloading is not None else None)
        try:
            uvicorn.Server(config).run(sockets=[http_socket])
        except KeyboardInterrupt:  # as uvicorn.run: SIGINT after the graceful shutdown
            pass
    finally:
        http_socket.close()
        if grpc_server is not None:
            grpc_server.stop(grace=5).wait()
        jobs.stop(timeout=60)
        services.close()
        signal.signal(signal.SIGTERM, previous_sigterm)
    return 0


def cmd_store_fsck(args: argparse.Namespace) -> int:
    """Report (and with --remove delete) blobs no row references, and rows whose blob is
    missing; exit status 1 when something is inconsistent."""
    import json

    from models_store.db import make_engine, make_session_factory
    from models_store.blobs import BlobStore
    from models_store.fsck import fsck
    from service.config import Settings

    overrides = {name: getattr(args, name) for name in ("data_dir", "database_url")
                 if getattr(args, name) is not None}
    settings = Settings(**overrides)
    engine = make_engine(settings.database_url_resolved)
    try:
        with make_session_factory(engine)() as session:
            report = fsck(session, BlobStore(settings.blob_dir), remove=args.remove,
                          min_age=args.min_age)
    finally:
        engine.dispose()
    print(json.dumps({"referenced": report.referenced, "orphans": report.orphans,
                      "removed": report.removed, "kept_young": report.kept_young,
                      "missing": [dict(zip(("table", "id", "key"), m)) for m in report.missing]},
                     indent=2))
    return 0 if report.clean or (args.remove and not report.missing
                                 and len(report.removed) == len(report.orphans)) else 1


def build_parser() -> argparse.ArgumentParser:
    from service.client_cli import add_global_options

    parser = argparse.ArgumentParser(
        prog="facesynth", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="The facesynth command line: one entry point, a subcommand per task.",
        epilog="Run 'facesynth COMMAND --help' for a command's options. The server commands "
               "(actors, upload, train,\njobs, models, clips, synthesize, enhance) take --server "
               "and --token before or after the command.")
    add_global_options(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("sample-actor", help="build the synthetic sample actor (ICT rig based)")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--seed", type=int, default=1, help="identity/markers/performances seed (default 1)")
    p.add_argument("--level", type=int, choices=(0, 1, 2), default=1,
                   help="resolution: 0 rig (11k vertices), 1 (~45k), 2 (~179k); default 1")
    p.add_argument("--no-tracking", action="store_true", help="skip the camera renders")
    p.add_argument("--no-database-maps", action="store_true",
                   help="no maps for the 630-frame database performance (they are built at levels "
                        "0 and 1, about 3.6 GB at level 1)")
    p.add_argument("--family", choices=("a", "b"), default="a",
                   help="a: the sample actor (default); b: the independent evaluation family "
                        "(service/samples/family_b: other identity, mesh, detail, markers)")
    p.add_argument("--units", choices=("mm", "cm", "m"), default="mm",
                   help="unit of every length written (family b only; default mm)")
    p.set_defaults(func=cmd_sample_actor)

    p = sub.add_parser("sample-gallery", help="render a built sample actor to PNGs (shaded meshes, maps)")
    p.add_argument("--actor", required=True, type=Path, help="directory written by sample-actor")
    p.add_argument("--out", required=True, type=Path, help="directory for the PNGs")
    p.set_defaults(func=cmd_sample_gallery)

    p = sub.add_parser("pdm-train", help="train a polynomial displacement map model (Ma 2008) on a sample actor")
    p.add_argument("--actor", required=True, type=Path, help="directory written by sample-actor")
    p.add_argument("--out", required=True, type=Path, help="model directory to write")
    p.add_argument("--clips", nargs="*", help="performance names (default: every train_* clip)")
    p.add_argument("--order", choices=("linear", "biquadratic", "bicubic"), default="biquadratic")
    p.add_argument("--medium-resolution", type=int, default=512)
    p.add_argument("--fine-resolution", type=int, default=None,
                   help="texels per side of the fine band (default: the clips' map resolution)")
    # defaults: PdmParams' own (not imported here: the method's import would slow every command)
    p.add_argument("--gamma", type=float,
                   help="the paper's regularization γ of ma2008 §4.2 (rows γ/σ; overrides --ridge)")
    p.add_argument("--ridge", type=float,
                   help="dimensionless ridge, used without --gamma (default: PdmParams')")
    p.add_argument("--margin", type=float,
                   help="extrapolation limit: fraction of the training range (negative: none; "
                        "default: PdmParams')")
    p.set_defaults(func=cmd_pdm_train)

    p = sub.add_parser("pdm-synthesize", help="meshes and maps from markers with a trained pdm model")
    p.add_argument("--model", required=True, type=Path, help="model directory (pdm-train --out)")
    p.add_argument("--markers", required=True, type=Path,
                   help=".npz with 'markers' (F,M,3), or a .c3d/.trc/.csv/.json marker file")
    p.add_argument("--out", required=True, type=Path, help=".npz to write")
    p.add_argument("--outputs", default="mesh,displacement",
                   help="comma-separated: mesh, mesh_detailed, displacement, albedo, normal_map")
    p.add_argument("--no-clamp", action="store_true", help="let the polynomials extrapolate")
    p.set_defaults(func=cmd_pdm_synthesize)

    p = sub.add_parser("worker", help="run jobs from the queue until SIGINT/SIGTERM",
                       description="Run training and synthesis jobs. Every option defaults to its "
                                   "FACESYNTH_* environment variable (then to the built-in default).")
    p.add_argument("--data-dir", type=Path, help="data directory (FACESYNTH_DATA_DIR)")
    p.add_argument("--database-url", help="metadata database URL (FACESYNTH_DATABASE_URL)")
    p.add_argument("--queue-url", help="queue storage, e.g. redis://host:6379/0 (FACESYNTH_QUEUE_URL)")
    p.add_argument("--queue-name", help="queue name (FACESYNTH_QUEUE_NAME)")
    p.add_argument("--workers", type=int, help="job threads (FACESYNTH_WORKERS, default 1)")
    p.set_defaults(func=cmd_worker)

    p = sub.add_parser("check", help="probe the database, blob store and queue (exit 0 when "
                                     "all answer); the worker container's healthcheck",
                       description="Print the readiness checks (as /readyz) of the FACESYNTH_* "
                                   "settings as JSON; exit 0 when every check is ok, else 1.")
    p.add_argument("--data-dir", type=Path, help="data directory (FACESYNTH_DATA_DIR)")
    p.add_argument("--database-url", help="metadata database URL (FACESYNTH_DATABASE_URL)")
    p.add_argument("--queue-url", help="queue storage URL (FACESYNTH_QUEUE_URL)")
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("serve", help="run the HTTP API, the gRPC server and embedded job workers",
                       description="Serve the HTTP API (API.md), the gRPC synthesis stream and "
                                   "job workers in one process. Every option defaults to its "
                                   "FACESYNTH_* environment variable (then to the built-in "
                                   "default). Without FACESYNTH_TOKENS it only listens on "
                                   "loopback.")
    p.add_argument("--host", help="HTTP address (FACESYNTH_HOST, default 127.0.0.1)")
    p.add_argument("--port", type=int, help="HTTP port (FACESYNTH_PORT, default 8000)")
    p.add_argument("--grpc-port", type=int, help="gRPC port (FACESYNTH_GRPC_PORT, default 50051)")
    p.add_argument("--data-dir", type=Path, help="data directory (FACESYNTH_DATA_DIR)")
    p.add_argument("--workers", type=int, help="embedded job threads (FACESYNTH_WORKERS, default 1; "
                                               "0: no embedded worker, API only)")
    p.add_argument("--preload", action="append", metavar="MODELS",
                   help="load these models into the cache at start-up, in the background "
                        "(/readyz answers 503 until they are loaded): comma-separated model "
                        "ids, or 'all' for every ready model (FACESYNTH_PRELOAD; repeatable)")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("store", help="maintenance of the model store")
    store_sub = p.add_subparsers(dest="store_command", required=True)
    p = store_sub.add_parser("fsck", help="report blobs no row references (orphans) and rows whose "
                                          "blob is missing; --remove deletes old orphans")
    p.add_argument("--data-dir", type=Path, help="data directory (FACESYNTH_DATA_DIR)")
    p.add_argument("--database-url", help="metadata database URL (FACESYNTH_DATABASE_URL)")
    p.add_argument("--remove", action="store_true", help="delete the orphans older than --min-age")
    p.add_argument("--min-age", type=float, default=3600.0,
                   help="seconds; younger orphans may be about to be referenced (default 3600)")
    p.set_defaults(func=cmd_store_fsck)

    from service.client_cli import add_client_commands

    add_client_commands(sub)

    p = sub.add_parser("demo", help="the whole story against a server: sample actor, upload, train a "
                                    "PDM, synthesize a held-out performance, meshes + EXR maps + PNG",
                       description="Builds (or reuses) the sample actor in OUT/actor, starts an "
                                   "embedded server unless --server is given, and writes OUT/result "
                                   "(per-frame OBJ and EXR) and OUT/side_by_side.png.")
    p.add_argument("--out", type=Path, default=Path("facesynth-demo"), help="output directory")
    p.add_argument("--server", default=argparse.SUPPRESS,
                   help="URL of a running server (FACESYNTH_URL); default: start one")
    p.add_argument("--token", default=argparse.SUPPRESS, help="bearer token (FACESYNTH_TOKEN)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--level", type=int, choices=(0, 1, 2), default=1)
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

"""``facesynth`` subcommands that talk to a server through the client SDK (``facesynth_client``).

    facesynth actors create NAME [--metadata JSON] | list | delete ID [--cascade]
    facesynth upload neutral ACTOR mesh.obj|mesh.npz
    facesynth upload markers ACTOR layout.json
    facesynth upload clip ACTOR clip.npz | --markers take.c3d frame_0001.obj ... [--name N] [--fps F]
    facesynth upload rig ACTOR NAME rig.obj|rig.npz [--no-wait]
    facesynth train ACTOR --kind pdm --clips ID ... [--params JSON] [--set k=v ...] [--no-wait]
    facesynth jobs list [--status S] [--actor ID] [--kind K] | watch ID | cancel ID
    facesynth synthesize MODEL take.c3d|take.trc|take.csv|take.npz -o out/ [--format obj-exr|npz]
    facesynth enhance MODEL frames.npz -o out/ [--rig NAME] [--format obj-exr|npz]
    facesynth models list ACTOR | export MODEL -o DIR

Every command takes ``--server URL`` (``FACESYNTH_URL``, default http://127.0.0.1:8000) and
``--token T`` (``FACESYNTH_TOKEN``); listings take ``--json``. Long work (training, whole
performances) runs as a job whose progress bar is drawn on stderr; ``--no-wait`` prints the
job id and returns at once.

Exit codes, for scripts:

    0  done (a waited-for job succeeded)
    1  a waited-for job failed or was cancelled (its error is printed)
    2  bad command line (argparse)
    3  the server refused the request (4xx; its problem detail is printed)
    4  the server failed or could not be reached (5xx, connection errors, timeouts)
"""

from __future__ import annotations

import argparse
import json
import sys
import zipfile
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any, Callable

EXIT_OK, EXIT_JOB_FAILED, EXIT_USAGE, EXIT_REJECTED, EXIT_SERVER = 0, 1, 2, 3, 4
#: result formats of ``synthesize``/``enhance`` → the synthesis job's format
FORMATS = {"obj-exr": "obj-exr-zip", "npz": "npz"}


# ---------------------------------------------------------------------------- plumbing

def _client(args: argparse.Namespace):
    from facesynth_client import Client

    return Client(args.server, token=args.token)


def _print(args: argparse.Namespace, rows: list, columns: tuple[str, ...]) -> None:
    """Rows (SDK dataclasses) as JSON with ``--json``, else as an aligned table."""
    if args.json:                                  # the server's own JSON
        print(json.dumps([getattr(r, "raw", None) or asdict(r) for r in rows], indent=1, default=str))
        return
    data = [asdict(r) if is_dataclass(r) else dict(r) for r in rows]
    def cell(value: Any) -> str:
        if value is None:
            return ""
        return f"{value:.2f}" if isinstance(value, float) else str(value)

    table = [columns] + [tuple(cell(d.get(c)) for c in columns) for d in data]
    widths = [max(len(row[k]) for row in table) for k in range(len(columns))]
    for row in table:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())


def _wait(client, args: argparse.Namespace, accepted) -> int:
    """Follow a job with a progress bar unless ``--no-wait``; its exit code."""
    from facesynth_client import JobCancelled, JobFailed

    job_id = getattr(accepted, "job_id", accepted)
    if getattr(args, "no_wait", False):
        print(job_id)
        return EXIT_OK
    try:
        job = client.wait(accepted, progress=True)
    except (JobFailed, JobCancelled) as error:
        print(f"job {job_id}: {error}", file=sys.stderr)
        return EXIT_JOB_FAILED
    print(f"job {job.id} {job.status}", file=sys.stderr)
    return EXIT_OK


def _json_arg(text: str | None, what: str) -> dict:
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise SystemExit(f"{what} is not valid JSON: {error}") from None
    if not isinstance(value, dict):
        raise SystemExit(f"{what} must be a JSON object, got {type(value).__name__}")
    return value


def _assignments(items: list[str] | None) -> dict:
    """``k=v`` pairs, values parsed as JSON where they parse (numbers, booleans), else text."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--set takes name=value, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


# ---------------------------------------------------------------------------- commands

def actors_create(client, args) -> int:
    actor = client.actors.create(args.name, metadata=_json_arg(args.metadata, "--metadata") or None)
    print(actor.id)
    return EXIT_OK


def actors_list(client, args) -> int:
    _print(args, client.actors.list(), ("id", "name", "created_at"))
    return EXIT_OK


def actors_delete(client, args) -> int:
    client.actors.delete(args.actor, cascade=args.cascade)
    return EXIT_OK


def upload_neutral(client, args) -> int:
    info = client.actors.upload_neutral(args.actor, args.file)
    print(json.dumps(asdict(info), default=str))
    return EXIT_OK


def upload_markers(client, args) -> int:
    info = client.actors.set_markers(args.actor, args.file)
    print(json.dumps(asdict(info), default=str))
    return EXIT_OK


def upload_clip(client, args) -> int:
    files = [Path(f) for f in args.files]
    if args.markers:
        if not files or any(f.suffix.lower() != ".obj" for f in files):
            raise SystemExit("with --markers, give the clip's per-frame .obj files in order")
        clip = client.clips.upload_frames(args.actor, files, Path(args.markers), fps=args.fps, name=args.name)
    elif len(files) == 1 and files[0].suffix.lower() == ".npz":
        clip = client.clips.upload_file(args.actor, files[0], name=args.name)
    else:
        raise SystemExit("give one clip .npz, or --markers FILE and per-frame .obj files")
    print(clip.clip_id)
    return EXIT_OK


def upload_rig(client, args) -> int:
    accepted = client.rigs.upload(args.actor, args.rig, Path(args.file))
    return _wait(client, args, accepted)


def train(client, args) -> int:
    params = {**_json_arg(args.params, "--params"), **_assignments(args.set)}
    accepted = client.models.train(args.actor, args.kind, args.clips, params or None)
    print(accepted.model_id)
    return _wait(client, args, accepted)


def jobs_list(client, args) -> int:
    _print(args, client.jobs.list(status=args.status, actor_id=args.actor, kind=args.kind),
           ("id", "kind", "status", "progress", "stage", "created_at"))
    return EXIT_OK


def jobs_watch(client, args) -> int:
    return _wait(client, args, args.job)


def jobs_cancel(client, args) -> int:
    job = client.jobs.cancel(args.job)
    print(f"job {job.id} {job.status}", file=sys.stderr)
    return EXIT_OK


def _run_performance(client, args, **source: Any) -> int:
    """A synthesis job for a whole performance, waited for and unpacked into ``args.out``."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    accepted = client.synthesis.submit_job(args.model, outputs=args.outputs, format=FORMATS[args.format],
                                           **source)
    code = _wait(client, args, accepted)
    if code != EXIT_OK or args.no_wait:
        return code
    job = client.jobs.get(accepted)
    stem = Path(args.input).stem
    for artifact_id in job.artifact_ids:
        if args.format == "npz":
            path = client.download_artifact(artifact_id, out / f"{stem}.npz")
            print(path)
        else:
            archive = client.download_artifact(artifact_id, out / f".{stem}.zip")
            with zipfile.ZipFile(archive) as z:
                names = z.namelist()
                z.extractall(out)
            archive.unlink()
            print(f"{len(names)} files in {out}")
    return EXIT_OK


def synthesize(client, args) -> int:
    path = Path(args.input)
    if path.suffix.lower() not in (".c3d", ".trc", ".csv", ".npz", ".json"):
        raise SystemExit(f"{path}: give markers as .c3d, .trc, .csv, .json or .npz (markers (F,M,3))")
    return _run_performance(client, args, performance=path)


def enhance(client, args) -> int:
    import numpy as np

    path = Path(args.input)
    if path.suffix.lower() != ".npz":
        raise SystemExit(f"{path}: give the frames as .npz with 'vertices' (F,v,3) (or 'markers')")
    with np.load(path, allow_pickle=False) as data:
        if "vertices" in data:
            source = {"vertices": data["vertices"]}
        elif "markers" in data:
            source = {"markers": data["markers"]}
        else:
            raise SystemExit(f"{path} has neither 'vertices' nor 'markers' (it has {sorted(data.files)})")
        fps = float(data["fps"]) if "fps" in data else None
    return _run_performance(client, args, rig=args.rig, fps=fps, **source)


def models_list(client, args) -> int:
    _print(args, client.models.list(args.actor), ("id", "kind", "status", "size_bytes", "created_at"))
    return EXIT_OK


def models_export(client, args) -> int:
    """The model's description (params, metrics) as model.json and its UV maps as EXR."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model = client.models.get(args.model)
    (out / "model.json").write_text(json.dumps(asdict(model), indent=1, default=str))
    maps = client.models.maps(args.model)
    for info in maps:
        client.models.download_map(args.model, info.name, out / f"{info.name}.exr")
    print(f"model.json and {len(maps)} maps in {out}")
    return EXIT_OK


# ---------------------------------------------------------------------------- parser

def add_client_commands(sub: argparse._SubParsersAction) -> None:
    """Register the client subcommands on the ``facesynth`` parser's subparsers."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--server", help="server URL (FACESYNTH_URL, default http://127.0.0.1:8000)")
    common.add_argument("--token", help="bearer token (FACESYNTH_TOKEN)")
    listing = argparse.ArgumentParser(add_help=False)
    listing.add_argument("--json", action="store_true", help="print JSON instead of a table")
    waiting = argparse.ArgumentParser(add_help=False)
    waiting.add_argument("--no-wait", action="store_true", help="print the job id and return")

    def command(parent, name: str, func: Callable, help: str, parents=()) -> argparse.ArgumentParser:
        p = parent.add_parser(name, help=help, parents=[common, *parents])
        p.set_defaults(func=run(func))
        return p

    group = sub.add_parser("actors", help="create, list or delete actors on a server").add_subparsers(
        dest="action", required=True)
    p = command(group, "create", actors_create, "create an actor; prints its id")
    p.add_argument("name")
    p.add_argument("--metadata", help="JSON object stored with the actor")
    command(group, "list", actors_list, "list the actors", [listing])
    p = command(group, "delete", actors_delete, "delete an actor (with --cascade: its models too)")
    p.add_argument("actor")
    p.add_argument("--cascade", action="store_true")

    group = sub.add_parser("upload", help="upload an actor's neutral, markers, clips or input rigs"
                           ).add_subparsers(dest="what", required=True)
    p = command(group, "neutral", upload_neutral, "the high-resolution neutral (.obj or .npz with UVs)")
    p.add_argument("actor")
    p.add_argument("file")
    p = command(group, "markers", upload_markers, "the marker layout (.json, API.md format)")
    p.add_argument("actor")
    p.add_argument("file")
    p = command(group, "clip", upload_clip, "a clip: .npz, or per-frame .obj files with --markers")
    p.add_argument("actor")
    p.add_argument("files", nargs="+", help="clip.npz, or frame .obj files in order")
    p.add_argument("--markers", help=".c3d, .trc, .csv or .json marker file (with .obj frames)")
    p.add_argument("--name")
    p.add_argument("--fps", type=float)
    p = command(group, "rig", upload_rig, "an input rig's neutral (registered as a job)", [waiting])
    p.add_argument("actor")
    p.add_argument("rig", help="the rig's name")
    p.add_argument("file", help=".obj or .npz")

    p = command(sub, "train", train, "train a model from clips (a job); prints the model id", [waiting])
    p.add_argument("actor")
    p.add_argument("--kind", required=True, help="pdm, shape_space, ...")
    p.add_argument("--clips", nargs="+", required=True, help="clip ids")
    p.add_argument("--params", help="training parameters as a JSON object")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="one training parameter")

    group = sub.add_parser("jobs", help="list, watch or cancel jobs").add_subparsers(dest="action", required=True)
    p = command(group, "list", jobs_list, "list jobs", [listing])
    p.add_argument("--status")
    p.add_argument("--actor")
    p.add_argument("--kind")
    p = command(group, "watch", jobs_watch, "follow a job's progress until it ends")
    p.add_argument("job")
    p = command(group, "cancel", jobs_cancel, "cancel a job")
    p.add_argument("job")

    for name, func, what in (("synthesize", synthesize, "markers (.c3d/.trc/.csv/.json/.npz)"),
                             ("enhance", enhance, "frames (.npz with vertices (F,v,3))")):
        p = command(sub, name, func, f"run a model on a whole performance of {what} (a job) and "
                                     "write per-frame OBJ + EXR (or one NPZ)", [waiting])
        p.add_argument("model")
        p.add_argument("input")
        p.add_argument("-o", "--out", required=True, help="output directory")
        p.add_argument("--format", choices=tuple(FORMATS), default="obj-exr")
        p.add_argument("--outputs", help="comma-separated outputs (default: the model kind's)")
        if name == "enhance":
            p.add_argument("--rig", help="the registered input rig the frames are on")

    group = sub.add_parser("models", help="list or export models").add_subparsers(dest="action", required=True)
    p = command(group, "list", models_list, "list an actor's models", [listing])
    p.add_argument("actor")
    p = command(group, "export", models_export, "write a model's description and UV maps to a folder")
    p.add_argument("model")
    p.add_argument("-o", "--out", required=True)


def run(func: Callable) -> Callable[[argparse.Namespace], int]:
    """``func(client, args)`` with a client, SDK errors mapped to the exit codes above."""

    def main(args: argparse.Namespace) -> int:
        from facesynth_client import ApiError, FacesynthError

        try:
            with _client(args) as client:
                return func(client, args)
        except ApiError as error:
            print(f"error: {error.status} {error.title}: {error.detail}", file=sys.stderr)
            return EXIT_REJECTED if 400 <= error.status < 500 else EXIT_SERVER
        except FacesynthError as error:
            print(f"error: {error}", file=sys.stderr)
            return EXIT_SERVER

    return main

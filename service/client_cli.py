"""``facesynth`` subcommands that talk to a server through the client SDK (``facesynth_client``).

    facesynth actors create NAME [--metadata JSON] | list | get ACTOR | delete ACTOR [--cascade]
    facesynth upload actor DIR [--name N] [--clips GLOB ...] [--no-rigs] [--no-wait]
    facesynth upload neutral ACTOR mesh.obj|mesh.npz
    facesynth upload markers ACTOR layout.json
    facesynth upload clip ACTOR clip.npz | --markers take.c3d frame_0001.obj ... [--name N] [--fps F]
    facesynth upload rig ACTOR NAME rig.obj|rig.npz [--no-wait]
    facesynth clips list ACTOR
    facesynth train ACTOR --kind pdm --clips ID ... [--params JSON] [--set k=v ...] [--no-wait]
    facesynth jobs list [--status S] [--actor ID] [--kind K] | show JOB | watch JOB | cancel JOB
    facesynth synthesize MODEL take.c3d|take.trc|take.csv|take.npz -o OUT [--format obj-exr|npz|usd]
                         [--pattern 'shot_{frame:04d}'] [--start-frame N] [--marker-filter FRAMES]
    facesynth enhance MODEL frames.npz -o OUT [--rig NAME] [--format obj-exr|npz|usd] [...]
    facesynth models list ACTOR | show MODEL | delete MODEL | export MODEL -o DIR
    facesynth transfer MODEL --target ACTOR --landmarks FILE [--params JSON] [--set k=v ...]
                       [--no-wait]
    facesynth bone-rig ACTOR --clip ID | --artifact ID --out DIR [--params JSON]
                       [--set k=v ...] [--fps F] [--no-wait]
    facesynth track ACTOR --cameras cams.json --scan neutral.ply --scan smile.obj ...
                    --scan-images scans.zip --frames frames.zip | --frames v0.mp4 ...
                    -o OUT [--params JSON] [--set k=v ...] [--scan-maps maps.npz]
                    [--format npz|obj-exr|usd] [--map-resolution N] [--no-wait]

Every command takes --server URL (FACESYNTH_URL, default http://127.0.0.1:8000) and
--token T (FACESYNTH_TOKEN), before or after the command's name; every listing and show takes
--json (the server's JSON, one document on stdout). Long work (training, rig registration,
whole performances) runs as a job whose progress goes to stderr: a bar on a terminal, a plain
line every 10 % otherwise. --no-wait prints the job's id (one line, nothing else on stdout) and
returns at once. A command that fails leaves no output folder behind.

Exit codes, for scripts:

    0  done (a waited-for job succeeded)
    1  a waited-for job failed or was cancelled (its error is printed)
    2  bad command line: an unknown option, bad JSON, a local file that does not exist or
       cannot be read (one line on stderr)
    3  the server refused the request (4xx; its problem detail is printed)
    4  the server failed or could not be reached (5xx, connection errors, timeouts)
"""

from __future__ import annotations

import argparse
import contextlib
import fnmatch
import json
import os
import re
import shutil
import sys
import tempfile
import zipfile
from dataclasses import asdict, is_dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterator

EXIT_OK, EXIT_JOB_FAILED, EXIT_USAGE, EXIT_REJECTED, EXIT_SERVER = 0, 1, 2, 3, 4
#: result formats of ``synthesize``/``enhance`` → the synthesis job's format
FORMATS = {"obj-exr": "obj-exr-zip", "npz": "npz", "usd": "usd"}
#: the arrays the API takes in a neutral .npz (plus ``region_<name>``) and in a clip .npz
NEUTRAL_ARRAYS = ("vertices", "faces", "uv", "uv_faces", "quad_split")
REGION_PREFIX = "region_"
CLIP_ARRAYS = ("vertices", "markers", "displacement", "albedo", "fps")
#: the default name of frame ``{frame}``'s files (``<pattern><suffix>.<ext>``)
DEFAULT_PATTERN = "frame_{frame:04d}"
#: a member of a synthesis job's obj-exr zip: frame_<index><suffix>.<obj|exr>
_ZIP_MEMBER = re.compile(r"^frame_(\d+)((?:_[a-z_]+)?)\.(obj|exr)$")
#: the clips ``upload actor`` sends by default (performance file stems)
DEFAULT_ACTOR_CLIPS = ("train_*", "database")
#: the server's default request body limit (Settings.max_body_bytes), bytes
DEFAULT_MAX_CLIP_BYTES = 256 * 2**20
#: the sample actor's manifest kind (``facesynth sample-actor``)
SAMPLE_ACTOR_KIND = "facesynth.sample_actor"


class UsageError(Exception):
    """A bad command line or local file: one line on stderr, exit code 2."""


# ---------------------------------------------------------------------------- plumbing

def _client(args: argparse.Namespace):
    from facesynth_client import Client

    return Client(getattr(args, "server", None), token=getattr(args, "token", None))


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _without_raw(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_raw(v) for k, v in value.items() if k != "raw"}
    if isinstance(value, list):
        return [_without_raw(v) for v in value]
    return value


def _plain(row: Any) -> dict:
    """A result (an SDK dataclass or a dict) as a dict of its fields (without ``raw``)."""
    return _without_raw(asdict(row) if is_dataclass(row) else dict(row))


def _json_of(row: Any) -> Any:
    """The server's own JSON of an SDK result (its ``raw``), else its fields."""
    return getattr(row, "raw", None) or _plain(row)


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.2f}"
    if isinstance(value, datetime):
        return value.strftime("%Y-%m-%d %H:%M:%S")
    if isinstance(value, dict) and "code" in value:           # an ErrorInfo
        return f"{value['code']}: {value.get('message', '')}"[:60]
    return str(value)


def _print_rows(args: argparse.Namespace, rows: list, columns: tuple[str, ...],
                extra: Callable[[Any], dict] | None = None) -> None:
    """Rows as JSON with ``--json`` (a list of the server's objects), else an aligned table
    of ``columns`` (values from the row's fields, or from ``extra(row)``)."""
    if args.json:
        print(json.dumps([_json_of(r) for r in rows], indent=1, default=str))
        return
    data = [{**_plain(r), **(extra(r) if extra else {})} for r in rows]
    table = [columns] + [tuple(_cell(d.get(c)) for c in columns) for d in data]
    widths = [max(len(row[k]) for row in table) for k in range(len(columns))]
    for row in table:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())


def _print_one(args: argparse.Namespace, row: Any, extra: dict | None = None) -> None:
    """One resource as JSON with ``--json``, else ``field: value`` lines."""
    if args.json:
        print(json.dumps(_json_of(row), indent=1, default=str))
        return
    fields = {k: v for k, v in {**_plain(row), **(extra or {})}.items() if k != "raw"}
    width = max(len(k) for k in fields)
    for key, value in fields.items():
        text = json.dumps(value, default=str) if isinstance(value, (dict, list)) and not (
            isinstance(value, dict) and "code" in value) else _cell(value)
        print(f"{key.ljust(width)}  {text}")


def _wait(client, args: argparse.Namespace, accepted, label: str | None = None) -> int:
    """Follow a job with its progress on stderr unless ``--no-wait`` (then print its id, the
    one line on stdout); the exit code."""
    from facesynth_client import JobCancelled, JobFailed

    from service.progress_bar import job_progress

    job_id = getattr(accepted, "job_id", accepted)
    if getattr(args, "no_wait", False):
        print(job_id)
        return EXIT_OK
    try:
        job = client.wait(accepted, progress=job_progress(label or job_id))
    except (JobFailed, JobCancelled) as error:
        _say(f"job {job_id}: {error}")
        return EXIT_JOB_FAILED
    _say(f"job {job.id} {job.status}")
    return EXIT_OK


def _json_arg(text: str | None, what: str) -> dict:
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise UsageError(f"{what} is not valid JSON: {error}") from None
    if not isinstance(value, dict):
        raise UsageError(f"{what} must be a JSON object, got {type(value).__name__}")
    return value


def _assignments(items: list[str] | None) -> dict:
    """``k=v`` pairs, values parsed as JSON where they parse (numbers, booleans), else text."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UsageError(f"--set takes name=value, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _file(path: str | Path, what: str = "file") -> Path:
    """``path`` if it is a readable file, else a :class:`UsageError` naming it."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such {what}")
    if not path.is_file():
        raise UsageError(f"{path}: not a file")
    if not os.access(path, os.R_OK):
        raise UsageError(f"{path}: not readable")
    return path


def _filter_frames(text: str) -> float | str:
    """argparse type of ``--marker-filter``: σ in frames, a finite number ≥ 0 (the server
    refuses one above its limit), or ``auto``."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value >= 0 and value != float("inf")):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a number of frames >= 0 (e.g. 3; 0 is off) or 'auto'")
    return value


def _frame_pattern(text: str) -> str:
    """argparse type of ``--pattern``: a str.format pattern using ``{frame}``."""
    try:
        names = {text.format(frame=k) for k in (0, 1)}
    except (KeyError, IndexError, ValueError) as error:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a pattern of {{frame}} (e.g. 'shot_{{frame:04d}}'): {error}") from None
    if len(names) != 2 or any(("/" in n or n in ("", ".", "..")) for n in names):
        raise argparse.ArgumentTypeError(
            f"{text!r} must name each frame differently with {{frame}} and no '/' "
            "(e.g. 'shot_{frame:04d}')")
    return text


def _strip_npz(path: Path, allowed: tuple[str, ...], prefixes: tuple[str, ...] = ()
               ) -> tuple[dict, list[str]]:
    """The arrays of ``path`` the API takes (``allowed`` names and ``prefixes``), and the
    names of the others, left out."""
    import numpy as np

    with np.load(path, allow_pickle=False) as data:
        keep = {k: data[k] for k in data.files if k in allowed or k.startswith(prefixes)}
        dropped = [k for k in data.files if k not in keep]
    return keep, dropped


def _note_dropped(path: Path, dropped: list[str], why: str = "the API does not take them") -> None:
    if dropped:
        _say(f"{path.name}: left out {', '.join(repr(k) for k in dropped)} ({why})")


@contextlib.contextmanager
def _output_dir(out: Path) -> Iterator[Path]:
    """A staging folder whose files land in ``out`` only if the block succeeds.

    Yields an empty folder beside ``out``; on success its files are moved into ``out``
    (created then), on failure it is removed, so a failed command leaves no output folder
    (and no partial files) behind.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: exists and is not a folder")
    parent = out.parent if str(out.parent) else Path(".")
    missing = [p for p in (parent, *parent.parents) if not p.exists()]
    parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=parent))
    try:
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        for folder in missing:                      # parents made for it, innermost first
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    if not out.exists():
        os.replace(stage, out)
        return
    for item in stage.iterdir():
        os.replace(item, out / item.name)
    shutil.rmtree(stage, ignore_errors=True)


def _duration(job) -> float | None:
    """Seconds a job ran (so far, if it still runs); None before it started."""
    if job.started_at is None:
        return None
    end = job.finished_at or datetime.now(timezone.utc)
    return (end - job.started_at).total_seconds()


def _duration_text(seconds: float | None) -> str | None:
    if seconds is None:
        return None
    if seconds < 60:
        return f"{seconds:.1f}s"
    minutes, rest = divmod(int(round(seconds)), 60)
    return f"{minutes // 60}h{minutes % 60:02d}m" if minutes >= 60 else f"{minutes}m{rest:02d}s"


def _model_status(model) -> str:
    """A model's status for a person: a model whose training was cancelled is ``cancelled``
    (the server stores it as ``failed`` with the error code ``cancelled``)."""
    if model.status == "failed" and model.error is not None and model.error.code == "cancelled":
        return "cancelled"
    return model.status


# ---------------------------------------------------------------------------- actors

def actors_create(client, args) -> int:
    metadata = _json_arg(args.metadata, "--metadata") or None
    actor = client.actors.create(args.name, metadata=metadata)
    print(actor.id)
    return EXIT_OK


def actors_list(client, args) -> int:
    _print_rows(args, client.actors.list(),
                ("id", "name", "vertex_count", "marker_count", "created_at"))
    return EXIT_OK


def actors_get(client, args) -> int:
    _print_one(args, client.actors.get(args.actor))
    return EXIT_OK


def actors_delete(client, args) -> int:
    client.actors.delete(args.actor, cascade=args.cascade)
    return EXIT_OK


def clips_list(client, args) -> int:
    _print_rows(args, client.clips.list(args.actor),
                ("clip_id", "name", "frames", "size_bytes", "created_at"))
    return EXIT_OK


# ---------------------------------------------------------------------------- uploads

def upload_neutral(client, args) -> int:
    path = _file(args.file)
    if path.suffix.lower() == ".npz":
        arrays, dropped = _strip_npz(path, NEUTRAL_ARRAYS, (REGION_PREFIX,))
        _note_dropped(path, dropped)
        info = client.actors.upload_neutral(args.actor, arrays)
    else:
        info = client.actors.upload_neutral(args.actor, path)
    print(json.dumps(_json_of(info), default=str))
    return EXIT_OK


def upload_markers(client, args) -> int:
    info = client.actors.set_markers(args.actor, _file(args.file))
    print(json.dumps(_json_of(info), default=str))
    return EXIT_OK


def _clip_arrays(path: Path) -> dict:
    """A clip .npz's arrays as the API takes them.

    Arrays the API does not take (the sample actor's ``lowres``, ``vertices_medium``,
    ``weights``, ...) are left out, with a note. A sample actor performance's
    ``displacement`` is relative to its medium surface (``vertices_medium``), not to the
    clip's ``vertices`` as the API's: it is left out (``upload actor`` converts it), and so
    are maps that do not cover every frame.
    """
    arrays, dropped = _strip_npz(path, CLIP_ARRAYS)
    _note_dropped(path, dropped)
    frames = len(arrays.get("markers", arrays.get("vertices", ())))
    maps = [k for k in ("displacement", "albedo") if k in arrays]
    if "vertices_medium" in dropped and "displacement" in arrays:
        del arrays["displacement"]
        _say(f"{path.name}: left out 'displacement' (relative to the sample actor's medium "
             "surface, not to the clip's vertices; 'facesynth upload actor' converts it)")
    for key in maps:
        if key in arrays and len(arrays[key]) != frames:
            del arrays[key]
            _say(f"{path.name}: left out '{key}' (maps of only some of the {frames} frames)")
    return arrays


def upload_clip(client, args) -> int:
    files = [_file(f) for f in args.files]
    if args.markers:
        if not files or any(f.suffix.lower() != ".obj" for f in files):
            raise UsageError("with --markers, give the clip's per-frame .obj files in order")
        clip = client.clips.upload_frames(args.actor, files, _file(args.markers), fps=args.fps,
                                          name=args.name)
    elif len(files) == 1 and files[0].suffix.lower() == ".npz":
        arrays = _clip_arrays(files[0])
        if args.fps is not None:
            arrays["fps"] = args.fps
        clip = client.clips.upload(args.actor, arrays.pop("vertices", None),
                                   arrays.pop("markers", None), name=args.name or files[0].stem,
                                   **{k: arrays.get(k) for k in ("fps", "albedo", "displacement")})
    else:
        raise UsageError("give one clip .npz, or --markers FILE and per-frame .obj files")
    print(clip.clip_id)
    return EXIT_OK


def upload_rig(client, args) -> int:
    accepted = client.rigs.upload(args.actor, args.rig, _file(args.file))
    return _wait(client, args, accepted, f"rig {args.rig}")


def _actor_files(folder: Path, patterns: list[str], rigs: bool) -> dict:
    """What ``upload actor`` sends from ``folder``: neutral, layout, clips, rigs."""
    if not folder.is_dir():
        raise UsageError(f"{folder}: no such folder" if not folder.exists() else
                         f"{folder}: not a folder")
    neutral = next((folder / n for n in ("neutral.npz", "neutral.obj")
                    if (folder / n).is_file()), None)
    if neutral is None:
        raise UsageError(f"{folder}: no neutral.npz or neutral.obj")
    layout = _file(folder / "markers.json", "marker layout")
    performances = sorted((folder / "performances").glob("*.npz"))
    clips = [p for g in patterns for p in performances if fnmatch.fnmatch(p.stem, g)]
    clips = list(dict.fromkeys(clips))                 # in the patterns' order, once each
    if not clips:
        raise UsageError(f"{folder}: no clip matches {', '.join(patterns)} in performances/")
    rig_files = []
    if rigs:
        rig_files = sorted(p for p in folder.glob("input_rig*") if p.suffix in (".npz", ".obj"))
        if (folder / "rigs").is_dir():
            rig_files += sorted(p for p in (folder / "rigs").iterdir()
                                if p.suffix in (".npz", ".obj"))
    manifest = folder / "manifest.json"
    kind = json.loads(manifest.read_text()).get("kind") if manifest.is_file() else None
    return {"neutral": neutral, "layout": layout, "clips": clips, "rigs": rig_files,
            "sample": kind == SAMPLE_ACTOR_KIND}


def _npz_shapes(path: Path) -> dict[str, tuple[tuple[int, ...], int]]:
    """Every array's (shape, item size) of an .npz, read from the headers, not the data."""
    import numpy as np

    shapes = {}
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():
            if not info.filename.endswith(".npy"):
                continue
            with z.open(info) as member:
                version = np.lib.format.read_magic(member)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read_header(member)
            shapes[info.filename[:-4]] = (tuple(shape), dtype.itemsize)
    return shapes


def _size_text(size: float) -> str:
    """Bytes for a person: ``812 B``, ``29.3 KiB``, ``1185 MiB``, ``1.2 GiB``."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if size >= scale:
            value = size / scale
            return f"{value:.1f} {unit}" if value < 10 else f"{value:.0f} {unit}"
    return f"{int(size)} B"


def _clip_plan(path: Path, limit: int) -> bool:
    """Whether the clip at ``path`` goes with its maps (``displacement``, ``albedo``): only
    if they cover every frame and the clip's body (float32) stays within ``limit`` bytes.
    Raises :class:`UsageError` if even its vertices and markers exceed ``limit``."""
    import math

    shapes = _npz_shapes(path)
    frames = shapes.get("markers", shapes.get("vertices", ((0,), 4)))[0][0]

    def size(keys: tuple[str, ...]) -> int:
        return sum(4 * math.prod(shapes[k][0]) for k in keys if k in shapes)

    plain = size(("vertices", "markers"))
    if plain > limit:
        raise UsageError(f"{path}: {_size_text(plain)} even without maps, over "
                         f"--max-clip-bytes ({_size_text(limit)}); leave it out (--clips "
                         "'train_*') or raise the server's max_body_bytes and --max-clip-bytes")
    maps = ("displacement", "albedo")
    covered = all(k in shapes and shapes[k][0][0] == frames for k in maps if k in shapes)
    if not any(k in shapes for k in maps) or not covered:
        return False
    with_maps = plain + size(maps)
    if with_maps > limit:
        _say(f"{path.name}: its maps left out ({_size_text(with_maps)} with them, over "
             f"--max-clip-bytes {_size_text(limit)})")
        return False
    return True


def _sample_neutral(folder: Path) -> dict:
    """The sample actor's neutral arrays with its regions as ``region_<name>`` (V,) bool."""
    import numpy as np

    from service.samples.dataset import REGIONS

    arrays, dropped = _strip_npz(folder / "neutral.npz", NEUTRAL_ARRAYS + ("region",))
    region = arrays.pop("region", None)
    if region is not None:
        arrays.update({f"{REGION_PREFIX}{name}": np.isin(region, ids)
                       for name, ids in REGIONS.items()})
    _note_dropped(folder / "neutral.npz", dropped)
    return arrays


def _sample_clip(folder: Path, name: str, actor) -> dict:
    """A sample actor performance with its maps as the API's clip: the displacement made
    relative to the clip's vertices (:func:`service.samples.dataset.load_clip`, the one place
    that conversion lives), float32."""
    import numpy as np

    from service.samples.dataset import load_clip

    clip = load_clip(folder, name, actor)
    return {"vertices": clip.vertices.astype(np.float32), "markers": clip.markers.astype(np.float32),
            "fps": clip.fps, "displacement": clip.displacement, "albedo": clip.albedo}


def _plain_clip(path: Path) -> dict:
    """A clip's vertices, markers and fps (float32), without maps, read array by array."""
    import numpy as np

    with np.load(path, allow_pickle=False) as data:
        out = {k: data[k].astype(np.float32) for k in ("vertices", "markers")}
        if "fps" in data.files:
            out["fps"] = float(data["fps"])
    return out


def upload_actor(client, args) -> int:
    """A whole actor folder (``facesynth sample-actor``'s layout): a new actor with the
    neutral, the marker layout, the clips and the input rigs."""
    folder = Path(args.dir)
    found = _actor_files(folder, args.clips or list(DEFAULT_ACTOR_CLIPS), not args.no_rigs)
    with_maps = {path: _clip_plan(path, args.max_clip_bytes) for path in found["clips"]}
    actor = client.actors.create(args.name or folder.resolve().name,
                                 metadata={"source": folder.resolve().name})
    summary: dict[str, Any] = {"actor_id": actor.id, "clips": {}, "rigs": {}, "rig_jobs": {}}
    try:
        if found["sample"] and found["neutral"].suffix == ".npz":
            info = client.actors.upload_neutral(actor.id, _sample_neutral(folder))
        elif found["neutral"].suffix == ".npz":
            arrays, dropped = _strip_npz(found["neutral"], NEUTRAL_ARRAYS, (REGION_PREFIX,))
            _note_dropped(found["neutral"], dropped)
            info = client.actors.upload_neutral(actor.id, arrays)
        else:
            info = client.actors.upload_neutral(actor.id, found["neutral"])
        summary["neutral"] = _json_of(info)
        _say(f"actor {actor.id}: neutral {info.vertex_count} vertices, "
             f"{info.triangle_count} triangles")
        markers = client.actors.set_markers(actor.id, found["layout"])
        _say(f"actor {actor.id}: {markers.marker_count} markers")
        sample_actor = None
        if found["sample"]:
            from service.samples.dataset import load_actor

            sample_actor = load_actor(folder)
        for path in found["clips"]:
            if not with_maps[path]:
                arrays = _plain_clip(path)
            elif sample_actor is not None:
                arrays = _sample_clip(folder, path.stem, sample_actor)
            else:
                arrays = _clip_arrays(path)
            clip = client.clips.upload(actor.id, arrays.pop("vertices"), arrays.pop("markers"),
                                       name=path.stem, **arrays)
            summary["clips"][path.stem] = clip.clip_id
            _say(f"actor {actor.id}: clip {path.stem} ({clip.frames} frames) {clip.clip_id}")
        accepted = []
        for path in found["rigs"]:
            rig = client.rigs.upload(actor.id, path.stem, path)
            summary["rigs"][path.stem] = rig.rig_id
            summary["rig_jobs"][path.stem] = rig.job_id
            accepted.append(rig)
            _say(f"actor {actor.id}: input rig {path.stem} registering (job {rig.job_id})")
        if not args.no_wait:
            from facesynth_client import JobCancelled, JobFailed

            from service.progress_bar import job_progress

            for rig in accepted:
                try:
                    client.wait(rig, progress=job_progress(f"rig {rig.name}"))
                except (JobFailed, JobCancelled) as error:
                    _say(f"input rig {rig.name}: {error}")
                    return EXIT_JOB_FAILED
    except BaseException:
        with contextlib.suppress(Exception):
            client.actors.delete(actor.id, cascade=True)
            _say(f"the partly uploaded actor {actor.id} was deleted")
        raise
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print(actor.id)
    return EXIT_OK


# ---------------------------------------------------------------------------- training, jobs

def train(client, args) -> int:
    params = {**_json_arg(args.params, "--params"), **_assignments(args.set)}
    accepted = client.models.train(args.actor, args.kind, args.clips, params or None)
    if args.no_wait:
        print(accepted.job_id)
        _say(f"model {accepted.model_id} training (job {accepted.job_id})")
        return EXIT_OK
    print(accepted.model_id, flush=True)
    return _wait(client, args, accepted, f"train {accepted.model_id}")


def jobs_list(client, args) -> int:
    jobs = client.jobs.list(status=args.status, actor_id=args.actor, kind=args.kind)
    _print_rows(args, jobs, ("id", "kind", "status", "progress", "stage", "duration", "error",
                             "created_at"),
                extra=lambda job: {"duration": _duration_text(_duration(job))})
    return EXIT_OK


def jobs_show(client, args) -> int:
    job = client.jobs.get(args.job)
    _print_one(args, job, {"duration": _duration_text(_duration(job))})
    return EXIT_OK


def jobs_watch(client, args) -> int:
    return _wait(client, args, args.job)


def jobs_cancel(client, args) -> int:
    job = client.jobs.cancel(args.job)
    _say(f"job {job.id} {job.status}")
    return EXIT_OK


# ---------------------------------------------------------------------------- results

def _npz_frames(path: Path) -> int:
    """F of a synthesis result .npz, read from an array header (not the data)."""
    shapes = _npz_shapes(path)
    for key in ("clamped", "vertices", "vertices_detailed", "displacement"):
        if key in shapes and shapes[key][0]:
            return int(shapes[key][0][0])
    return 0


def _unpack_frames(archive: Path, stage: Path, pattern: str, start: int) -> dict[int, list[str]]:
    """The obj-exr zip's members into ``stage``, each frame's files named by ``pattern``
    with frame number ``start + index``; returns index → file names."""
    frames: dict[int, list[str]] = {}
    with zipfile.ZipFile(archive) as z:
        for info in z.infolist():
            match = _ZIP_MEMBER.match(info.filename)
            if match is None:
                name = Path(info.filename).name          # e.g. clamped.csv
                if not name:
                    continue
            else:
                index = int(match.group(1))
                name = f"{pattern.format(frame=start + index)}{match.group(2)}.{match.group(3)}"
                frames.setdefault(index, []).append(name)
            with z.open(info) as source, open(stage / name, "wb") as target:
                shutil.copyfileobj(source, target, 1 << 20)
    return frames


def _usd_frames(path: Path) -> int:
    """F of a USD point cache, from its stage's start and end time codes (metadata only)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
    return int(round(stage.GetEndTimeCode() - stage.GetStartTimeCode())) + 1


def _unpack_usd(artifact: Path, stage: Path, stem: str) -> dict[int, list[str]]:
    """A ``usd`` artifact into ``stage``: the cache as ``<stem>.usd``, or the zip's cache(s)
    and maps under their own names (the cache references the maps by them); returns frame
    index → the files holding that frame (the cache(s) and that frame's maps)."""
    if not zipfile.is_zipfile(artifact):
        artifact.rename(stage / f"{stem}.usd")
        caches, maps = [f"{stem}.usd"], {}
    else:
        with zipfile.ZipFile(artifact) as z:
            names = [Path(name).name for name in z.namelist()]
            for info, name in zip(z.infolist(), names):
                with z.open(info) as source, open(stage / name, "wb") as target:
                    shutil.copyfileobj(source, target, 1 << 20)
        artifact.unlink()
        caches = sorted(name for name in names if name.endswith(".usd"))
        maps = {}
        for name in names:
            match = _ZIP_MEMBER.match(name)
            if match is not None:
                maps.setdefault(int(match.group(1)), []).append(name)
    return {k: caches + sorted(maps.get(k, [])) for k in range(_usd_frames(stage / caches[0]))}


def _run_performance(client, args, **source: Any) -> int:
    """A synthesis job for a whole performance, waited for and written into ``args.out``
    with its frame map ``frames.json``."""
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: exists and is not a folder")
    accepted = client.synthesis.submit_job(
        args.model, outputs=args.outputs, format=FORMATS[args.format],
        marker_filter_frames=getattr(args, "marker_filter", 0.0), **source)
    code = _wait(client, args, accepted, f"{args.command} {accepted.job_id}")
    if code != EXIT_OK or args.no_wait:
        return code
    job = client.jobs.get(accepted)
    stem = Path(args.input).stem
    frame_map: dict[str, Any] = {"source": Path(args.input).name, "model_id": args.model,
                                 "job_id": job.id, "format": args.format,
                                 "start_frame": args.start_frame, "pattern": args.pattern,
                                 "frames": []}
    with _output_dir(out) as stage:
        for artifact_id in job.artifact_ids:
            if args.format == "npz":
                path = client.download_artifact(artifact_id, stage / f"{stem}.npz")
                frame_map["frames"] = [
                    {"frame": args.start_frame + k, "source_frame": k, "files": [path.name]}
                    for k in range(_npz_frames(path))]
            elif args.format == "usd":                 # time code k is the input's frame k
                download = client.download_artifact(artifact_id, stage / f".{stem}.artifact")
                frame_map["frames"] = [
                    {"frame": args.start_frame + k, "source_frame": k, "time_code": k,
                     "files": names}
                    for k, names in sorted(_unpack_usd(download, stage, stem).items())]
            else:
                archive = client.download_artifact(artifact_id, stage / f".{stem}.zip")
                frames = _unpack_frames(archive, stage, args.pattern, args.start_frame)
                archive.unlink()
                frame_map["frames"] = [
                    {"frame": args.start_frame + k, "source_frame": k, "files": sorted(names)}
                    for k, names in sorted(frames.items())]
        if args.format == "obj-exr":        # per-frame files: file → source frame index
            frame_map["files"] = {name: row["source_frame"] for row in frame_map["frames"]
                                  for name in row["files"]}
        (stage / "frames.json").write_text(json.dumps(frame_map, indent=1))
        files = sorted(p.name for p in stage.iterdir())
    _say(f"{len(frame_map['frames'])} frames, {len(files)} files in {out} (frame map: "
         f"{out / 'frames.json'})")
    print(out)
    return EXIT_OK


def synthesize(client, args) -> int:
    path = _file(args.input)
    if path.suffix.lower() not in (".c3d", ".trc", ".csv", ".npz", ".json"):
        raise UsageError(f"{path}: give markers as .c3d, .trc, .csv, .json or .npz "
                         "(markers (F,M,3))")
    if path.suffix.lower() == ".npz":              # e.g. a sample actor performance as it is
        import numpy as np

        with np.load(path, allow_pickle=False) as data:
            if "markers" not in data.files:
                raise UsageError(f"{path} has no 'markers' (F,M,3) (it has {sorted(data.files)})")
            markers = data["markers"]
            fps = float(data["fps"]) if "fps" in data.files else None
            _note_dropped(path, [k for k in data.files if k not in ("markers", "fps")],
                          "synthesize sends the markers")
        return _run_performance(client, args, markers=markers, fps=fps)
    return _run_performance(client, args, performance=path)


def enhance(client, args) -> int:
    import numpy as np

    path = _file(args.input)
    if path.suffix.lower() != ".npz":
        raise UsageError(f"{path}: give the frames as .npz with 'vertices' (F,v,3) (or 'markers')")
    with np.load(path, allow_pickle=False) as data:
        if "vertices" in data:
            source = {"vertices": data["vertices"]}
        elif "markers" in data:
            source = {"markers": data["markers"]}
        else:
            raise UsageError(f"{path} has neither 'vertices' nor 'markers' "
                             f"(it has {sorted(data.files)})")
        fps = float(data["fps"]) if "fps" in data else None
    return _run_performance(client, args, rig=args.rig, fps=fps, **source)


# ---------------------------------------------------------------------------- models

def models_list(client, args) -> int:
    _print_rows(args, client.models.list(args.actor),
                ("id", "kind", "status", "size_bytes", "created_at"),
                extra=lambda model: {"status": _model_status(model)})
    return EXIT_OK


def models_show(client, args) -> int:
    model = client.models.get(args.model)
    _print_one(args, model, {"status": _model_status(model)})
    return EXIT_OK


def models_delete(client, args) -> int:
    client.models.delete(args.model)
    return EXIT_OK


def models_export(client, args) -> int:
    """The model's description (params, metrics) as model.json and its UV maps as EXR."""
    out = Path(args.out)
    model = client.models.get(args.model)
    maps = client.models.maps(args.model)
    with _output_dir(out) as stage:
        (stage / "model.json").write_text(json.dumps(_json_of(model), indent=1, default=str))
        for info in maps:
            client.models.download_map(args.model, info.name, stage / f"{info.name}.exr")
    print(out)
    _say(f"model.json and {len(maps)} maps in {out}")
    return EXIT_OK


# ---------------------------------------------------------------------------- transfer, bone rigs

def read_landmarks(path: Path) -> list[list[int]]:
    """Landmark pairs (source vertex, target vertex) from a file: JSON (``[[s, t], ...]`` or
    ``{"landmarks": [...]}``), ``.npz`` with ``landmarks`` (L,2), or text/CSV with two
    integer columns per line (``#`` comments, an optional header line of names).

    Raises UsageError for a file that holds no (L,2) integer pairs.
    """
    import numpy as np

    path = _file(path, "landmark file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            value = json.loads(path.read_text())
            pairs = value.get("landmarks") if isinstance(value, dict) else value
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                if "landmarks" not in data.files:
                    raise UsageError(f"{path} has no 'landmarks' (L,2) (it has {sorted(data.files)})")
                pairs = data["landmarks"].tolist()
        else:
            rows = [line.split("#")[0].replace(",", " ").split()
                    for line in path.read_text().splitlines()]
            rows = [row for row in rows if row]
            if rows and not rows[0][0].lstrip("-").isdigit():
                rows = rows[1:]                                 # a header line
            pairs = [[int(v) for v in row] for row in rows]
    except (ValueError, TypeError) as error:
        raise UsageError(f"{path}: not landmark pairs ({error})") from None
    ok = (isinstance(pairs, list) and pairs
          and all(isinstance(row, list) and len(row) == 2
                  and all(isinstance(v, int) and not isinstance(v, bool) for v in row)
                  for row in pairs))
    if not ok:
        raise UsageError(f"{path}: expected pairs of integer vertex indices [source, target], "
                         "one per landmark")
    return [[int(a), int(b)] for a, b in pairs]


def transfer(client, args) -> int:
    landmarks = read_landmarks(args.landmarks)
    params = {**_json_arg(args.params, "--params"), **_assignments(args.set)}
    accepted = client.models.transfer(args.model, args.target, landmarks, params or None)
    if args.no_wait:
        print(accepted.job_id)
        _say(f"model {accepted.model_id} of actor {args.target} (job {accepted.job_id})")
        return EXIT_OK
    print(accepted.model_id, flush=True)
    return _wait(client, args, accepted, f"transfer {accepted.model_id}")


def bone_rig(client, args) -> int:
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: exists and is not a folder")
    params = {**_json_arg(args.params, "--params"), **_assignments(args.set)}
    accepted = client.bone_rigs.submit(args.actor, clip=args.clip, artifact=args.artifact,
                                       params=params or None, fps=args.fps, usd=args.usd)
    code = _wait(client, args, accepted, f"bone-rig {accepted.job_id}")
    if code != EXIT_OK or args.no_wait:
        return code
    job = client.jobs.get(accepted)
    metrics = (job.raw.get("result") or {}).get("metrics") or {}
    with _output_dir(out) as stage:
        for artifact_id, name in zip(job.artifact_ids, ("rig.npz", "rig.glb", "rig.usd")):
            client.download_artifact(artifact_id, stage / name)
        (stage / "rig.json").write_text(json.dumps(
            {"actor_id": args.actor, "job_id": job.id, "clip_id": args.clip,
             "artifact_id": args.artifact, "metrics": metrics}, indent=1))
    if metrics:
        _say(f"{metrics.get('bones')} bones, reconstruction RMS {metrics.get('rms_mm', 0):.4g}, "
             f"max {metrics.get('max_mm', 0):.4g} (actor units)")
    _say(f"rig.npz, rig.glb{', rig.usd' if args.usd else ''} and rig.json in {out}")
    print(out)
    return EXIT_OK


# ---------------------------------------------------------------------------- tracking

def stage_bars(label: str, stream=None, terminal: bool | None = None) -> Callable[[object], None]:
    """A ``progress`` callback for ``client.wait`` drawing one bar per stage of a tracking
    job (:data:`service.jobs.track_stages.STAGES`): each bar runs 0–100 % over its stage and
    is completed when the next stage starts."""
    from service.jobs.track_stages import STAGES, within
    from service.progress_bar import progress_bar

    current: dict = {}

    def update(job) -> None:
        stage = job.stage
        if stage not in STAGES:                      # queued, or between two runs
            return
        if current.get("stage") != stage:
            if current:
                current["bar"](1.0, "done")
            current.update(stage=stage, bar=progress_bar(f"{label} {stage}", stream, terminal))
        if job.status in ("succeeded",):
            current["bar"](1.0, "done")
        elif job.status in ("failed", "cancelled"):
            current["bar"](within(stage, job.progress), job.status)
        else:
            current["bar"](within(stage, job.progress), stage)

    return update


def track(client, args) -> int:
    from facesynth_client import JobCancelled, JobFailed

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: exists and is not a folder")
    cameras = _file(args.cameras, "camera calibration")
    try:
        json.loads(cameras.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise UsageError(f"{cameras}: not JSON ({error})") from None
    scans = [_file(p, "scan") for p in args.scan]
    frames = [_file(p, "frames file") for p in args.frames]
    params = {**_json_arg(args.params, "--params"), **_assignments(args.set)}
    accepted = client.tracking.submit(
        args.actor, cameras=cameras, scans=scans, scan_images=_file(args.scan_images, "zip"),
        frames=frames, scan_maps=_file(args.scan_maps, "npz") if args.scan_maps else None,
        params=params or None, format=FORMATS[args.format], map_resolution=args.map_resolution)
    if args.no_wait:
        print(accepted.job_id)
        return EXIT_OK
    try:
        job = client.wait(accepted, progress=stage_bars(f"track {accepted.job_id}"))
    except (JobFailed, JobCancelled) as error:
        _say(f"job {accepted.job_id}: {error}")
        return EXIT_JOB_FAILED
    result = job.raw.get("result") or {}
    artifacts = result.get("artifacts") or {}
    with _output_dir(out) as stage:
        for name, artifact_id in artifacts.items():
            client.download_artifact(artifact_id, stage / name)
        (stage / "track.json").write_text(json.dumps(
            {"actor_id": args.actor, "job_id": job.id, "artifacts": artifacts,
             "span_job_ids": result.get("span_job_ids", []),
             "metrics": result.get("metrics", {})}, indent=1))
    metrics = result.get("metrics") or {}
    _say(f"{metrics.get('frames')} frames tracked ({metrics.get('keyframes')} keyframes, "
         f"{metrics.get('spans')} span jobs); {', '.join(artifacts)} and track.json in {out}")
    print(out)
    return EXIT_OK


# ---------------------------------------------------------------------------- parser

def _landmarks_file(path: Path) -> tuple[list, list | None]:
    """Landmarks (L,2,2) ``[[u_s, v_s], [u_t, v_t]]`` and optional pinned indices from a JSON
    file (a list, or ``{"landmarks": [...], "pinned": [...]}``) or an ``.npz`` with
    ``landmarks`` (L,2,2) (and optionally ``pinned`` (P,))."""
    import numpy as np

    pinned = None
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as data:
            if "landmarks" not in data.files:
                raise UsageError(f"{path} has no 'landmarks' (L,2,2) (it has {sorted(data.files)})")
            landmarks = data["landmarks"]
            if "pinned" in data.files:
                pinned = [int(i) for i in np.ravel(data["pinned"])]
    else:
        try:
            value = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise UsageError(f"{path}: not JSON ({error})") from None
        if isinstance(value, dict):
            pinned = value.get("pinned")
            value = value.get("landmarks")
        landmarks = value
    try:
        array = np.asarray(landmarks, dtype=float)
    except (TypeError, ValueError):
        array = np.zeros(0)
    if array.ndim != 3 or array.shape[1:] != (2, 2):
        raise UsageError(f"{path}: landmarks must be (L,2,2) [[u_s, v_s], [u_t, v_t]] per point, "
                         f"got shape {array.shape}")
    return array.tolist(), pinned


def correspond(client, args) -> int:
    """A correspondence job (source scan → target scan's UV space), waited for with a
    progress bar; its artifacts (warped maps as EXR, warp.npz, blendshape.npz) and
    ``result.json`` (the job's metrics) are written into ``args.out``."""
    landmarks, pinned = _landmarks_file(_file(args.landmarks, "landmarks file"))
    if args.pinned is not None:
        pinned = args.pinned
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: exists and is not a folder")
    accepted = client.scans.correspond(args.actor, args.source, args.target, landmarks,
                                       pinned=pinned, params=_json_arg(args.params, "--params")
                                       or None, artist_uv=args.artist_uv)
    code = _wait(client, args, accepted, f"correspond {accepted.job_id}")
    if code != EXIT_OK or args.no_wait:
        return code
    job = client.jobs.get(accepted)
    files = dict(job.result.raw.get("artifacts") or {})
    with _output_dir(out) as stage:
        for filename, artifact_id in sorted(files.items()):
            client.download_artifact(artifact_id, stage / Path(filename).name)
        (stage / "result.json").write_text(json.dumps(
            {"job_id": job.id, "source_scan_id": args.source, "target_scan_id": args.target,
             "artifacts": files, "metrics": job.result.raw.get("metrics")}, indent=1))
    metrics = job.result.raw.get("metrics") or {}
    _say(f"{len(files)} files in {out}; mean confidence {metrics.get('mean_confidence', 0):.3f}, "
         f"coverage {metrics.get('coverage', 0):.3f}")
    print(out)
    return EXIT_OK


def add_global_options(parser: argparse.ArgumentParser) -> None:
    """``--server``, ``--token`` and ``--version`` on the top-level ``facesynth`` parser, so
    they may come before the command's name (``facesynth --server URL jobs list``)."""
    parser.add_argument("--server", default=None, metavar="URL",
                        help="server URL (FACESYNTH_URL, default http://127.0.0.1:8000)")
    parser.add_argument("--token", default=None, help="bearer token (FACESYNTH_TOKEN)")
    parser.add_argument("--version", action="version", version=version_text())


def version_text() -> str:
    """``facesynth X (facesynth-client Y)``: the installed versions."""
    from importlib import metadata

    def installed(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "not installed"

    return f"facesynth {installed('facesynth')} (facesynth-client {installed('facesynth-client')})"


def add_client_commands(sub: argparse._SubParsersAction) -> None:
    """Register the client subcommands on the ``facesynth`` parser's subparsers."""
    # after the command's name too; SUPPRESS: not given there, the top-level value stays
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--server", default=argparse.SUPPRESS, metavar="URL",
                        help="server URL (FACESYNTH_URL, default http://127.0.0.1:8000)")
    common.add_argument("--token", default=argparse.SUPPRESS,
                        help="bearer token (FACESYNTH_TOKEN)")
    listing = argparse.ArgumentParser(add_help=False)
    listing.add_argument("--json", action="store_true",
                         help="print the server's JSON instead of a table")
    waiting = argparse.ArgumentParser(add_help=False)
    waiting.add_argument("--no-wait", action="store_true",
                         help="print the job's id (one line on stdout) and return at once")

    def command(parent, name: str, func: Callable, help: str, parents=()) -> argparse.ArgumentParser:
        p = parent.add_parser(name, help=help, description=help[:1].upper() + help[1:] + ".",
                              parents=[common, *parents])
        p.set_defaults(func=run(func))
        return p

    def group(name: str, help: str) -> argparse._SubParsersAction:
        return sub.add_parser(name, help=help, description=help[:1].upper() + help[1:] + "."
                              ).add_subparsers(dest="action", required=True, metavar="ACTION")

    actors = group("actors", "create, list, show or delete actors on a server")
    p = command(actors, "create", actors_create, "create an actor; prints its id")
    p.add_argument("name", help="the actor's display name")
    p.add_argument("--metadata", help="JSON object stored with the actor")
    command(actors, "list", actors_list, "list the actors", [listing])
    p = command(actors, "get", actors_get, "show one actor (counts of what was uploaded)", [listing])
    p.add_argument("actor", help="actor id")
    p = command(actors, "delete", actors_delete, "delete an actor (with --cascade: its models too)")
    p.add_argument("actor", help="actor id")
    p.add_argument("--cascade", action="store_true", help="delete the actor's models too")

    upload = group("upload", "upload a whole actor folder, or an actor's neutral, markers, "
                             "clips or input rigs")
    p = command(upload, "actor", upload_actor,
                "create an actor from a folder (facesynth sample-actor's layout: neutral, "
                "markers.json, performances/*.npz, input rigs); prints its id", [waiting, listing])
    p.add_argument("dir", help="the actor folder")
    p.add_argument("--name", help="the actor's name (default: the folder's name)")
    p.add_argument("--clips", action="append", metavar="GLOB",
                   help="performances to send as clips, by file stem (repeatable; default: "
                        + ", ".join(DEFAULT_ACTOR_CLIPS) + ")")
    p.add_argument("--no-rigs", action="store_true", help="do not send the input rigs")
    p.add_argument("--max-clip-bytes", type=int, default=DEFAULT_MAX_CLIP_BYTES, metavar="N",
                   help="a clip's maps are left out above this many bytes, and a clip bigger "
                        "without them is refused before anything is sent (default 256 MiB, "
                        "the server's default max_body_bytes)")
    p = command(upload, "neutral", upload_neutral,
                "the high-resolution neutral (.obj or .npz with UVs)")
    p.add_argument("actor", help="actor id")
    p.add_argument("file", help="neutral mesh, .obj or .npz (arrays the API does not take "
                                "are left out)")
    p = command(upload, "markers", upload_markers, "the marker layout (.json, API.md format)")
    p.add_argument("actor", help="actor id")
    p.add_argument("file", help="marker layout .json")
    p = command(upload, "clip", upload_clip, "a clip: .npz, or per-frame .obj files with --markers; "
                                             "prints its id")
    p.add_argument("actor", help="actor id")
    p.add_argument("files", nargs="+", help="clip.npz, or frame .obj files in order")
    p.add_argument("--markers", help=".c3d, .trc, .csv or .json marker file (with .obj frames)")
    p.add_argument("--name", help="the clip's name (default: the .npz file's stem)")
    p.add_argument("--fps", type=float, help="frame rate (overrides the file's)")
    p = command(upload, "rig", upload_rig, "an input rig's neutral (registered as a job)", [waiting])
    p.add_argument("actor", help="actor id")
    p.add_argument("rig", help="the rig's name (letters, digits, ._-)")
    p.add_argument("file", help="the rig's neutral mesh, .obj or .npz")

    clips = group("clips", "list an actor's clips")
    p = command(clips, "list", clips_list, "list an actor's clips", [listing])
    p.add_argument("actor", help="actor id")

    p = command(sub, "train", train, "train a model from clips (a job); prints the model id, or "
                                     "with --no-wait only the job id", [waiting])
    p.add_argument("actor", help="actor id")
    p.add_argument("--kind", required=True, help="pdm, shape_space, ...")
    p.add_argument("--clips", nargs="+", required=True, help="clip ids")
    p.add_argument("--params", help="training parameters as a JSON object")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="one training parameter")

    jobs = group("jobs", "list, show, watch or cancel jobs")
    p = command(jobs, "list", jobs_list, "list jobs, with their duration and error", [listing])
    p.add_argument("--status", help="queued, running, succeeded, failed or cancelled")
    p.add_argument("--actor", help="only this actor's jobs")
    p.add_argument("--kind", help="only jobs of this kind")
    p = command(jobs, "show", jobs_show, "show one job", [listing])
    p.add_argument("job", help="job id")
    p = command(jobs, "watch", jobs_watch, "follow a job's progress until it ends")
    p.add_argument("job", help="job id")
    p = command(jobs, "cancel", jobs_cancel, "cancel a job")
    p.add_argument("job", help="job id")

    for name, func, what, input_help in (
            ("synthesize", synthesize, "markers (.c3d/.trc/.csv/.json/.npz)",
             "marker take: .c3d, .trc, .csv, .json, or .npz with 'markers' (F,M,3)"),
            ("enhance", enhance, "frames (.npz with vertices (F,v,3))",
             ".npz with 'vertices' (F,v,3) (or 'markers'), optionally 'fps'")):
        p = command(sub, name, func, f"run a model on a whole performance of {what} (a job) and "
                                     "write per-frame OBJ + EXR (or one NPZ) and frames.json",
                    [waiting])
        p.add_argument("model", help="model id")
        p.add_argument("input", help=input_help)
        p.add_argument("-o", "--out", required=True, help="output folder (made once the "
                                                          "results are in)")
        p.add_argument("--format", choices=tuple(FORMATS), default="obj-exr",
                       help="per-frame OBJ and EXR files (default), one NPZ, or one USD "
                            "point cache (time code k = input frame k; with maps, the cache "
                            "and the EXR maps it references, named as the cache expects)")
        p.add_argument("--outputs", help="comma-separated outputs (default: the model kind's)")
        p.add_argument("--pattern", type=_frame_pattern, default=DEFAULT_PATTERN,
                       help="name of a frame's files, a Python format of {frame} (default "
                            f"'{DEFAULT_PATTERN.replace('%', '%%')}'; files are "
                            "<name>.obj, <name>_detailed.obj, <name>_displacement.exr, ...)")
        p.add_argument("--start-frame", type=int, default=0, metavar="N",
                       help="the frame number of the input's first frame in file names and "
                            "frames.json (default 0)")
        if name == "enhance":
            p.add_argument("--rig", help="the registered input rig the frames are on")
        else:
            p.add_argument("--marker-filter", type=_filter_frames, default=0.0, metavar="FRAMES",
                           help="smooth the markers in time on the server before synthesis "
                                "(the job's marker_filter_frames: σ in frames of a local "
                                "quadratic fit over the whole take; 3 at 30 fps for ordinary "
                                "mocap noise; auto: the take's noise estimated and the "
                                "window chosen per frame in the modes of the model's marker "
                                "prior; default 0: off)")

    p = command(sub, "correspond", correspond,
                "bring a source scan into a target scan's UV space (a correspondence job) "
                "and write the warped maps, warp.npz and result.json to a folder", [waiting])
    p.add_argument("actor", help="actor id")
    p.add_argument("--source", required=True, help="source scan id (e.g. an expression)")
    p.add_argument("--target", required=True, help="target scan id (e.g. the neutral)")
    p.add_argument("--landmarks", required=True, metavar="FILE",
                   help="JSON [[[u_s, v_s], [u_t, v_t]], ...] (or {landmarks, pinned}), or "
                        ".npz with landmarks (L,2,2)")
    p.add_argument("--pinned", type=int, nargs="+", metavar="I",
                   help="indices of pinned landmarks")
    p.add_argument("--params", help="correspondence parameters as a JSON object")
    p.add_argument("--artist-uv", action="store_true",
                   help="the actor's neutral has the target scan's UVs: also write its "
                        "blendshape (blendshape.npz)")
    p.add_argument("-o", "--out", required=True, help="output folder (made once the results "
                                                      "are in)")

    models = group("models", "list, show, delete or export models")
    p = command(models, "list", models_list, "list an actor's models", [listing])
    p.add_argument("actor", help="actor id")
    p = command(models, "show", models_show, "show one model (params, metrics, error)", [listing])
    p.add_argument("model", help="model id")
    p = command(models, "delete", models_delete, "delete a model and its files")
    p.add_argument("model", help="model id")
    p = command(models, "export", models_export,
                "write a model's description and UV maps to a folder")
    p.add_argument("model", help="model id")
    p.add_argument("-o", "--out", required=True, help="output folder")

    p = command(sub, "transfer", transfer,
                "transfer a psd/wpsd model's details to another actor (a job); prints the new "
                "model's id, or with --no-wait only the job id", [waiting])
    p.add_argument("model", help="id of the source model (psd or wpsd, ready)")
    p.add_argument("--target", required=True, metavar="ACTOR", help="the target actor's id")
    p.add_argument("--landmarks", required=True, metavar="FILE",
                   help="corresponding vertex pairs (source, target): .json [[s, t], ...], "
                        ".npz with 'landmarks' (L,2), or .csv/.txt with two columns")
    p.add_argument("--params", help="transfer parameters as a JSON object (pose_weights)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="one parameter")

    p = command(sub, "bone-rig", bone_rig,
                "compress a performance to a bone rig (a job) and write rig.npz, rig.glb "
                "and rig.json to a folder", [waiting])
    p.add_argument("actor", help="actor id")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--clip", metavar="ID", help="one of the actor's clips")
    source.add_argument("--artifact", metavar="ID", help="a synthesis job's .npz result")
    p.add_argument("-o", "--out", required=True, help="output folder (made once the rig is in)")
    p.add_argument("--params", help="decomposition parameters as a JSON object (bones, "
                                    "max_influences, iterations, ...)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="one parameter")
    p.add_argument("--fps", type=float, help="frame rate of the exported animation")
    p.add_argument("--usd", action="store_true", help="also write the rig as a UsdSkel stage, rig.usd")

    p = command(sub, "track", track,
                "track a performance from video and static scans (a job, one bar per stage) "
                "and write its results (tracked.npz, weights.npz, maps.npz, scans.npz, "
                "track.json) to a folder", [waiting])
    p.add_argument("actor", help="actor id (its neutral is the mesh tracked)")
    p.add_argument("--cameras", required=True, metavar="JSON",
                   help='calibration: {"views": [{"name", "K", "R", "t", "width", "height"}]}')
    p.add_argument("--scan", action="append", required=True, metavar="MESH",
                   help="a raw static scan (.obj or .ply), once per scan; the neutral first")
    p.add_argument("--scan-images", required=True, metavar="ZIP",
                   help="zip of <scan>/<view>.png (or .exr), scan = its mesh's file stem")
    p.add_argument("--frames", action="append", required=True, metavar="FILE",
                   help="a zip of <view>/<frame>.png sequences, or one video per view "
                        "(repeat, in the calibration's order)")
    p.add_argument("--scan-maps", metavar="NPZ", help="per-scan UV maps to blend per frame")
    p.add_argument("-o", "--out", required=True, help="output folder (made once the results "
                                                      "are in)")
    p.add_argument("--params", help="tracking parameters as a JSON object")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="one parameter")
    p.add_argument("--format", choices=sorted(FORMATS), default="npz",
                   help="also write tracked.zip (obj-exr) or tracked.usd (usd)")
    p.add_argument("--map-resolution", type=int, help="side of the blended maps, texels")


def run(func: Callable) -> Callable[[argparse.Namespace], int]:
    """``func(client, args)`` with a client, errors mapped to the exit codes above (one line
    on stderr each)."""

    def main(args: argparse.Namespace) -> int:
        from facesynth_client import ApiError, FacesynthError

        try:
            with _client(args) as client:
                return func(client, args)
        except UsageError as error:
            _say(f"error: {error}")
            return EXIT_USAGE
        except OSError as error:                       # a local file
            where = f"{error.filename}: " if error.filename else ""
            _say(f"error: {where}{error.strerror or error}")
            return EXIT_USAGE
        except ApiError as error:
            _say(f"error: {error.status} {error.title}: {error.detail}")
            return EXIT_REJECTED if 400 <= error.status < 500 else EXIT_SERVER
        except FacesynthError as error:
            _say(f"error: {error}")
            return EXIT_SERVER

    return main

"""``facesynth demo``: the whole story against a server, through the client SDK.

:func:`run_demo` builds (or reuses) the level-1 sample actor, starts an embedded server when
none is given, and then does what a pipeline does over HTTP:

1. create an actor and upload its neutral (with UVs and regions), marker layout and the
   eight training clips;
2. train a PDM (Ma et al. 2008) as a job, following its progress;
3. synthesize the held-out in-range performance as a synthesis job in the ``obj-exr-zip``
   format and unpack it: per frame a medium-scale OBJ, an OBJ with the fine scale baked
   in, the displacement and normal maps as EXR;
4. render ground truth beside the synthesized meshes for three held-out frames
   (``side_by_side.png``) and print the vertex error against the ground truth.

Everything lands in one output folder::

    <out>/actor/                 the sample actor (built once, reused)
    <out>/server/                the embedded server's data directory (if one was started)
    <out>/result/frame_*.obj, frame_*_detailed.obj, frame_*_displacement.exr, frame_*_normal_map.exr
    <out>/side_by_side.png
    <out>/summary.json
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from service.progress_bar import job_progress, progress_bar

#: the held-out performance synthesized, and every how many of its frames
HELDOUT = "heldout_in_range"
FRAME_STEP = 8
#: held-out frames rendered side by side (strong, varied expressions)
SHOWN_FRAMES = (40, 95, 120)
#: how long an embedded server may take to become ready, seconds
STARTUP_SECONDS = 120.0


@dataclass
class DemoResult:
    """Where the demo put things, and how well the PDM did."""

    out: Path
    png: Path
    meshes: list[Path]
    maps: list[Path]
    mean_error_mm: float
    p95_error_mm: float


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def embedded_server(data_dir: Path, log: Path) -> Iterator[str]:
    """``facesynth serve`` on free loopback ports with its data in ``data_dir``; yields its
    URL once ``/readyz`` answers, stops it (SIGTERM) afterwards."""
    import httpx

    port, grpc_port = _free_port(), _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    cmd = [sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--grpc-port", str(grpc_port), "--data-dir", str(data_dir), "--workers", "1"]
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as sink:
        process = subprocess.Popen(cmd, env=env, stdout=sink, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + STARTUP_SECONDS
        while True:
            if process.poll() is not None:
                raise RuntimeError(f"the embedded server exited with {process.returncode}; see {log}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{url}/readyz", timeout=2.0).status_code == 200:
                    break
            if time.monotonic() > deadline:
                raise RuntimeError(f"the embedded server was not ready in {STARTUP_SECONDS:.0f} s; see {log}")
            time.sleep(0.5)
        yield url
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def ensure_sample_actor(actor_dir: Path, seed: int, level: int, progress: bool = True) -> Path:
    """The sample actor in ``actor_dir``, built with the training clips and the held-out
    performance unless a complete one is there already."""
    from service.samples import performances
    from service.samples.actor import build_sample_actor

    names = tuple(f"train_{name}" for name in performances.TRAINING_EXPRESSIONS) + (HELDOUT,)
    manifest = actor_dir / "manifest.json"
    if manifest.exists():
        built = json.loads(manifest.read_text())
        if (built.get("seed"), built.get("level")) == (seed, level) and set(names) <= set(built["performances"]):
            return actor_dir
    build_sample_actor(actor_dir, seed=seed, level=level, with_tracking=False, performance_names=names,
                       progress=progress_bar("sample actor") if progress else (lambda fraction, stage: None))
    return actor_dir


def render_side_by_side(path: Path, faces: np.ndarray, truth: np.ndarray, result: np.ndarray,
                        labels: list[str]) -> Path:
    """Ground truth (top row) and synthesized meshes (bottom row), grey under grazing light.

    truth, result : (k,n,3) float, mm, in the same pose
    """
    from service.samples.gallery import GRAZING_LIGHT, SIZE, caption, front_camera
    from service.samples.render import shade, to_srgb8, write_png

    cam = front_camera(truth[0], SIZE)
    grey = np.full((truth.shape[1], 3), 0.6)
    rows = [np.concatenate([caption(to_srgb8(shade(cam, V, faces, grey, light_dir=GRAZING_LIGHT,
                                                 ambient=0.05)), f"{text}: {which}")
                            for V, text in zip(meshes, labels)], axis=1)
            for meshes, which in ((truth, "ground truth"), (result, "facesynth PDM"))]
    write_png(path, np.concatenate(rows, axis=0))
    return path


def run_demo(out: Path, server: str | None = None, seed: int = 1, level: int = 1,
             token: str | None = None, progress: bool = True,
             say: Callable[[str], None] = print) -> DemoResult:
    """Run the story of the module docstring into ``out``; returns where things are."""
    from facesynth_client import Client

    from service.samples import dataset, performances

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    say(f"sample actor (seed {seed}, level {level}) in {out / 'actor'}")
    actor_dir = ensure_sample_actor(out / "actor", seed, level, progress)
    with contextlib.ExitStack() as stack:
        if server is None:
            say(f"starting an embedded server (data in {out / 'server'}, log in {out / 'server.log'})")
            server = stack.enter_context(embedded_server(out / "server", out / "server.log"))
        client = stack.enter_context(Client(server, token=token))
        say(f"server {server}")

        actor = dataset.load_actor(actor_dir)
        remote = client.actors.create(f"sample-actor-{seed}", metadata={"source": "facesynth demo"})
        client.actors.upload_neutral(remote.id, vertices=actor.vertices, faces=actor.faces,
                                     uv=actor.uv, uv_faces=actor.uv_faces,
                                     **{f"region_{k}": v for k, v in actor.regions.items()})
        client.actors.set_markers(remote.id, actor_dir / "markers.json")
        clip_ids = []
        for name in (f"train_{n}" for n in performances.TRAINING_EXPRESSIONS):
            clip = dataset.load_clip(actor_dir, name, actor)
            clip_ids.append(client.clips.upload(remote.id, clip.vertices, clip.markers, fps=clip.fps,
                                                name=name).clip_id)
        say(f"actor {remote.id}: neutral, {actor.n_markers} markers and {len(clip_ids)} training clips uploaded")

        accepted = client.models.train(remote.id, "pdm", clip_ids)
        say(f"training PDM {accepted.model_id} (job {accepted.job_id})")
        client.wait(accepted, progress=job_progress(f"train {accepted.model_id}") if progress else False)

        with np.load(actor_dir / "performances" / f"{HELDOUT}.npz") as data:
            frames = np.arange(0, len(data["markers"]), FRAME_STEP)
            markers = data["markers"][frames].astype(np.float64)
            shown = np.asarray(SHOWN_FRAMES)
            truth = data["vertices"][shown].astype(np.float64)
        job = client.synthesis.submit_job(accepted.model_id, markers=markers, format="obj-exr-zip",
                                          outputs=["mesh", "mesh_detailed", "displacement", "normal_map"])
        say(f"synthesizing {len(frames)} held-out frames (job {job.job_id})")
        done = client.wait(job, progress=job_progress(f"synthesize {job.job_id}") if progress else False)
        archive = out / "result.zip"
        client.download_artifact(done.artifact_ids[0], archive)
        result_dir = out / "result"
        with zipfile.ZipFile(archive) as z:
            z.extractall(result_dir)
        archive.unlink()

        synthesized = client.synthesis.synthesize(accepted.model_id, _markers_of(actor_dir, shown),
                                                  outputs=["mesh", "mesh_detailed"])
    V = synthesized["vertices_detailed"].astype(np.float64)
    face = np.asarray(actor.regions.get("face", np.ones(actor.n_vertices, bool)))
    err = np.linalg.norm(V - truth, axis=-1)[:, face]
    png = render_side_by_side(out / "side_by_side.png", actor.faces, truth, V,
                              [f"frame {f}" for f in shown])
    meshes = sorted(result_dir.glob("*.obj"))
    maps = sorted(result_dir.glob("*.exr"))
    summary = {"server": server, "actor_id": remote.id, "model_id": accepted.model_id,
               "frames": len(frames), "shown_frames": [int(f) for f in shown],
               "mean_vertex_error_mm": float(err.mean()),
               "p95_vertex_error_mm": float(np.percentile(err, 95)), "png": str(png)}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    say(f"wrote {len(meshes)} meshes and {len(maps)} EXR maps to {result_dir}")
    say(f"vertex error against the ground truth on the face, shown frames: mean {err.mean():.3f} mm, "
        f"95th percentile {np.percentile(err, 95):.3f} mm")
    say(f"side by side: {png}")
    return DemoResult(out, png, meshes, maps, float(err.mean()), float(np.percentile(err, 95)))


def _markers_of(actor_dir: Path, frames: np.ndarray) -> np.ndarray:
    with np.load(actor_dir / "performances" / f"{HELDOUT}.npz") as data:
        return data["markers"][frames].astype(np.float64)

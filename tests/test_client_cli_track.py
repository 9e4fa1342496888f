"""``facesynth track`` (service.client_cli) and ``client.tracking`` (the SDK, sync and async)
against the real app on a loopback port with a worker, on the tiny tracking scene: the
results folder, a bar per stage, the exit codes of a refused upload and a bad file."""

from __future__ import annotations

import asyncio
import io
import json

import numpy as np
import pytest

from service.client_cli import EXIT_OK, EXIT_REJECTED, EXIT_USAGE, stage_bars
from service.jobs.track_stages import STAGES
from service.samples.tracking_scene import build_tracking_scene, tracking_uploads
from tests.servers import serve_app
from tests.test_client_cli import run

PARAMS = {"candidate_stride": 2, "hat_slope": 0.3}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    running = serve_app(tmp_path_factory.mktemp("cli-track-server"), worker=True)
    yield running
    running.stop()


@pytest.fixture(scope="module")
def scene():
    return build_tracking_scene(frames=6, views=1, size=40, k=10)


@pytest.fixture
def files(tmp_path, scene):
    """The scene's upload as files: cameras.json, scan0.obj, scan1.obj, scan_images.zip,
    frames.zip."""
    paths = {}
    for name, (filename, data, _) in tracking_uploads(scene):
        (tmp_path / filename).write_bytes(data)
        paths.setdefault(name, []).append(str(tmp_path / filename))
    return paths



def actor_with_neutral(server, scene, name) -> str:
    from facesynth_client import Client

    with Client(server.url) as client:
        actor = client.actors.create(name)
        client.actors.upload_neutral(actor.id, vertices=scene.artist_vertices,
                                     faces=scene.faces.astype(np.int32), uv=scene.uv)
        return actor.id


def test_track_command_writes_the_results_with_a_bar_per_stage(capsys, server, scene, files, tmp_path):
    actor = actor_with_neutral(server, scene, "cli-track")
    out_dir = tmp_path / "tracked"
    argv = ["track", actor, "--cameras", files["cameras"][0], "--scan-images",
            files["scan_images"][0], "--frames", files["frames"][0], "-o", str(out_dir),
            "--params", json.dumps(PARAMS), "--map-resolution", "16"]
    for scan in files["scans"]:
        argv += ["--scan", scan]
    code, out, err = run(capsys, server, *argv)
    assert code == EXIT_OK, err
    assert out.strip() == str(out_dir)
    assert sorted(p.name for p in out_dir.iterdir()) == [
        "maps.npz", "scans.npz", "track.json", "tracked.npz", "weights.npz"]
    with np.load(out_dir / "tracked.npz") as d:
        assert d["vertices"].shape == (6, len(scene.artist_vertices), 3)
        err_mm = np.linalg.norm(d["vertices"] - scene.frame_truth, axis=2).mean()
    assert err_mm < np.linalg.norm(scene.artist_vertices - scene.frame_truth, axis=2).mean()
    info = json.loads((out_dir / "track.json").read_text())
    assert info["metrics"]["frames"] == 6 and len(info["span_job_ids"]) == info["metrics"]["spans"]
    # one bar per stage seen (plain lines off a terminal; the client polls, so a short
    # stage may pass unseen), each ending at 100 %, the last one "storing results"
    bars = {line.split(":")[0] for line in err.splitlines() if line.startswith("track job_")}
    assert len(bars) >= 2, err
    for bar in bars:
        assert f"{bar}: 100% done" in err, err
    assert any(bar.endswith(" storing results") for bar in bars)

    # refused by the server (a calibration that is not a rotation): exit 3, no folder
    bad = json.loads(open(files["cameras"][0]).read())
    bad["views"][0]["R"] = [[2, 0, 0], [0, 1, 0], [0, 0, 1]]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    code, _, err = run(capsys, server, *[a if a != files["cameras"][0] else str(tmp_path / "bad.json")
                                         for a in argv[:-6]], "-o", str(tmp_path / "none"),
                       *sum((["--scan", s] for s in files["scans"]), []))
    assert code == EXIT_REJECTED and "not a rotation" in err and not (tmp_path / "none").exists()
    # a local file that does not exist: exit 2
    code, _, err = run(capsys, server, "track", actor, "--cameras", str(tmp_path / "nope.json"),
                       "--scan", files["scans"][0], "--scan-images", files["scan_images"][0],
                       "--frames", files["frames"][0], "-o", str(tmp_path / "x"))
    assert code == EXIT_USAGE and "nope.json" in err


def test_sdk_submits_tracking_jobs_sync_and_async(server, scene, files):
    from facesynth_client import AsyncClient, Client

    actor = actor_with_neutral(server, scene, "sdk-track")
    with Client(server.url) as client:
        accepted = client.tracking.submit(actor, cameras=files["cameras"][0], scans=files["scans"],
                                          scan_images=files["scan_images"][0],
                                          frames=files["frames"][0], params=PARAMS,
                                          map_resolution=16)
        job = client.wait(accepted)
        assert job.status == "succeeded" and job.kind == "track"
        names = set(job.raw["result"]["artifacts"])
        assert names == {"tracked.npz", "weights.npz", "maps.npz", "scans.npz"}

    async def go():
        async with AsyncClient(server.url) as client:
            accepted = await client.tracking.submit(
                actor, cameras=json.loads(open(files["cameras"][0]).read()),
                scans=[open(p, "rb").read() for p in files["scans"]],
                scan_images=open(files["scan_images"][0], "rb").read(),
                frames=open(files["frames"][0], "rb").read(), params=PARAMS, map_resolution=16)
            return await client.wait(accepted)

    job = asyncio.run(go())
    assert job.status == "succeeded"


def test_stage_bars_draw_one_bar_per_stage():
    from types import SimpleNamespace as Job

    stream = io.StringIO()
    update = stage_bars("track j", stream, terminal=False)
    start, end = STAGES["full flows"]
    for progress, stage in ((0.0, "graph flows"), (0.25, "graph selection"),
                            (start + 0.5 * (end - start), "full flows"), (end, "keyframe solve")):
        update(Job(progress=progress, stage=stage, status="running"))
    update(Job(progress=1.0, stage="storing results", status="succeeded"))
    lines = stream.getvalue().splitlines()
    assert "track j full flows:  50% full flows" in lines
    assert "track j graph flows: 100% done" in lines and "track j full flows: 100% done" in lines
    assert lines[-1] == "track j storing results: 100% done"

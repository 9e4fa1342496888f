"""The ``facesynth`` client commands run as a shell script runs them: each one a separate
``python -m service.cli`` process (stdin closed, stdout and stderr pipes, not a terminal)
against the real app served in this process on a loopback port with an embedded worker.

What a script relies on is checked on the process itself: exit codes, one id on stdout
where one id is promised, ``--json`` that parses, one-line errors, ``--server`` before the
command's name, plain progress lines (no carriage returns) off a terminal, and no output
folder left by a failed command.

The actor is a folder in the sample actor's layout (``facesynth sample-actor``), written
here from the tiny 16×13 sheet of the API tests: its neutral carries the sample's ``region``
and ``rig_vertices`` arrays, its performances ``lowres``, ``vertices_medium``, ``weights``
and maps relative to the medium surface, as the real sample actor's files do.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import facesynth_client
from service.client_cli import EXIT_JOB_FAILED, EXIT_OK, EXIT_REJECTED, EXIT_SERVER, EXIT_USAGE
from tests.api.conftest import SHEET_MARKERS, sheet, sheet_motion
from tests.servers import serve_app

REPO = Path(__file__).resolve().parents[2]
PDM_PARAMS = {"medium_resolution": 32, "fine_resolution": 32}
#: the sheet's maps (sample-actor performances carry displacement and albedo per map frame)
MAP_SIZE = 16


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    running = serve_app(tmp_path_factory.mktemp("cli-script-server"), worker=True)
    yield running
    running.stop()


def facesynth(*argv: str, check: int | None = None) -> subprocess.CompletedProcess:
    """``facesynth ARGV`` in a new process, as a script would run it; ``check``: the
    expected exit code."""
    sdk = Path(facesynth_client.__file__).resolve().parents[1]       # the SDK under test
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(sdk), env.get("PYTHONPATH", "")])
    done = subprocess.run([sys.executable, "-m", "service.cli", *argv], cwd=REPO, env=env,
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=300)
    if check is not None:
        assert done.returncode == check, (argv, done.returncode, done.stdout, done.stderr)
    return done


def one_line(text: str) -> str:
    lines = text.splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def _sample_performance(V: np.ndarray, frames: int, phase: float, maps: bool) -> dict:
    """A performance in the sample actor's file layout (service.samples.actor)."""
    vertices = sheet_motion(V, frames, phase).astype(np.float32)
    medium = vertices.copy()
    medium[..., 2] -= 0.05                          # the fine scale the maps are relative to
    out = {"markers": vertices[:, list(SHEET_MARKERS)], "lowres": vertices,
           "vertices_medium": medium, "vertices": vertices,
           "weights": np.zeros((frames, 3), np.float32), "fps": np.float32(30.0)}
    if maps:
        rng = np.random.default_rng(7)
        out.update(map_frames=np.arange(frames, dtype=np.int32),
                   displacement=rng.normal(0, 0.01, (frames, MAP_SIZE, MAP_SIZE)).astype(np.float32),
                   albedo=np.full((frames, MAP_SIZE, MAP_SIZE, 3), 0.5, np.float16))
    return out


@pytest.fixture(scope="module")
def actor_dir(tmp_path_factory) -> Path:
    """The sheet as a sample actor folder: neutral.npz (with ``region``, ``rig_vertices``),
    markers.json (triangle + barycentric, as the sample's), manifest.json,
    performances/train_rise, train_fall (with maps), heldout (not a training clip), and
    a CSV marker take beside it."""
    from service.io.markers import MarkerSequence, write_markers_csv

    d = tmp_path_factory.mktemp("cli-actor") / "sheet-actor"
    (d / "performances").mkdir(parents=True)
    V, F, uv = sheet(16, 13)
    np.savez(d / "neutral.npz", vertices=V.astype(np.float32), faces=F.astype(np.int32),
             uv=uv.astype(np.float32), uv_faces=F.astype(np.int32),
             region=np.zeros(len(V), np.int8), rig_vertices=V.astype(np.float32))
    markers = []
    for k, v in enumerate(SHEET_MARKERS):
        t = int(np.flatnonzero((F == v).any(axis=1))[0])
        markers.append({"name": f"M{k}", "triangle": t,
                        "barycentric": [float(c == v) for c in F[t]]})
    (d / "markers.json").write_text(json.dumps({"markers": markers}))
    (d / "manifest.json").write_text(json.dumps({"kind": "facesynth.sample_actor", "version": 1,
                                                 "units": "mm"}))
    for name, phase in (("train_rise", 0.0), ("train_fall", 0.3)):
        np.savez(d / "performances" / f"{name}.npz", **_sample_performance(V, 12, phase, True))
    np.savez(d / "performances" / "heldout_in_range.npz", **_sample_performance(V, 5, 0.15, False))
    take = sheet_motion(V, 5, 0.15)[:, list(SHEET_MARKERS)]
    write_markers_csv(d.parent / "take.csv", MarkerSequence(
        take, tuple(f"M{k}" for k in range(len(SHEET_MARKERS))), 30.0))
    return d


def test_a_script_uploads_the_actor_folder_trains_and_synthesizes(server, actor_dir, tmp_path):
    url = server.url
    # the whole folder, --server before the command's name; stdout: the actor id only
    done = facesynth("--server", url, "upload", "actor", str(actor_dir), "--json", check=EXIT_OK)
    uploaded = json.loads(done.stdout)
    actor = uploaded["actor_id"]
    assert sorted(uploaded["clips"]) == ["train_fall", "train_rise"]      # not the held-out take
    assert sorted(uploaded["neutral"]["regions"]) == ["face", "head", "narrow_face"]
    # a sample performance file as it is: the arrays the API does not take left out, a note
    done = facesynth("--server", url, "upload", "clip", actor,
                     str(actor_dir / "performances" / "heldout_in_range.npz"), check=EXIT_OK)
    assert one_line(done.stdout).startswith("clp_") and "'lowres'" in done.stderr

    # actors get / clips list: JSON that parses, the sample's arrays made API clips
    got = json.loads(facesynth("actors", "get", actor, "--json", "--server", url,
                               check=EXIT_OK).stdout)
    assert (got["id"], got["vertex_count"], got["marker_count"]) == (actor, 16 * 13, 4)
    clips = json.loads(facesynth("--server", url, "clips", "list", actor, "--json",
                                 check=EXIT_OK).stdout)
    assert sorted((c["name"], c["frames"]) for c in clips) == [
        ("heldout_in_range", 5), ("train_fall", 12), ("train_rise", 12)]

    # train --no-wait: exactly one line on stdout, the job id
    done = facesynth("--server", url, "train", actor, "--kind", "pdm", "--clips",
                     *uploaded["clips"].values(), "--params", json.dumps(PDM_PARAMS),
                     "--no-wait", check=EXIT_OK)
    job_id = one_line(done.stdout)
    assert job_id.startswith("job_")
    # jobs watch off a terminal: plain progress lines, never a carriage return
    done = facesynth("--server", url, "jobs", "watch", job_id, check=EXIT_OK)
    assert "\r" not in done.stderr and "100%" in done.stderr and "succeeded" in done.stderr
    job = json.loads(facesynth("--server", url, "jobs", "show", job_id, "--json",
                               check=EXIT_OK).stdout)
    model = job["result"]["model_id"]
    assert job["status"] == "succeeded"
    listed = facesynth("--server", url, "jobs", "list", "--actor", actor, check=EXIT_OK).stdout
    header = listed.splitlines()[0].split()
    assert {"duration", "error"} <= set(header)
    shown = json.loads(facesynth("--server", url, "models", "show", model, "--json",
                                 check=EXIT_OK).stdout)
    assert (shown["id"], shown["status"], shown["kind"]) == (model, "ready", "pdm")

    # synthesize a CSV take: named frames from --start-frame, and the frame map
    out = tmp_path / "shot"
    facesynth("--server", url, "synthesize", model, str(actor_dir.parent / "take.csv"), "-o",
              str(out), "--pattern", "shot_{frame:03d}", "--start-frame", "101", check=EXIT_OK)
    frame_map = json.loads((out / "frames.json").read_text())
    assert [row["frame"] for row in frame_map["frames"]] == [101, 102, 103, 104, 105]
    assert [row["source_frame"] for row in frame_map["frames"]] == [0, 1, 2, 3, 4]
    assert frame_map["files"]["shot_103.obj"] == 2
    assert sorted(p.name for p in out.glob("*.obj")) == [f"shot_{k}.obj" for k in range(101, 106)]
    assert all((out / name).is_file() for name in frame_map["files"])

    # a sample performance file as it is (with 'lowres', 'vertices', maps): its markers go
    done = facesynth("--server", url, "synthesize", model,
                     str(actor_dir / "performances" / "heldout_in_range.npz"), "-o",
                     str(tmp_path / "npz"), "--format", "npz", check=EXIT_OK)
    assert "'lowres'" in done.stderr and one_line(done.stdout) == str(tmp_path / "npz")
    with np.load(tmp_path / "npz" / "heldout_in_range.npz") as result:
        assert result["vertices"].shape == (5, 16 * 13, 3)
    frame_map = json.loads((tmp_path / "npz" / "frames.json").read_text())
    assert [row["source_frame"] for row in frame_map["frames"]] == [0, 1, 2, 3, 4]

    # --format usd: one point cache (time code k = input frame k); with maps, the cache
    # beside the EXR maps it references, under the names it references them by
    from pxr import Usd, UsdGeom
    for outputs, files, frame_2 in (
            ("mesh", ["take.usd"], ["take.usd"]),
            ("mesh,displacement",
             ["clamped.csv", "confidence.json", "performance.usd"] + [f"frame_{k:04d}_displacement.exr"
                                                   for k in range(5)],
             ["performance.usd", "frame_0002_displacement.exr"])):
        out = tmp_path / f"usd-{len(files)}"
        facesynth("--server", url, "synthesize", model, str(actor_dir.parent / "take.csv"),
                  "-o", str(out), "--format", "usd", "--outputs", outputs, "--start-frame",
                  "101", check=EXIT_OK)
        assert sorted(p.name for p in out.iterdir()) == sorted(files + ["frames.json"])
        rows = json.loads((out / "frames.json").read_text())["frames"]
        assert [(row["frame"], row["time_code"]) for row in rows] == [(101 + k, k) for k in range(5)]
        assert rows[2]["files"] == frame_2
        stage = Usd.Stage.Open(str(out / rows[0]["files"][0]))
        points = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh")).GetPointsAttr()
        assert points.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0]
        assert np.asarray(points.Get(3)).shape == (16 * 13, 3)

    # every listing and show parses as JSON
    for argv in (("actors", "list"), ("models", "list", actor), ("jobs", "list"),
                 ("jobs", "list", "--status", "succeeded")):
        assert isinstance(json.loads(facesynth(*argv, "--json", "--server", url,
                                               check=EXIT_OK).stdout), list)

    # models delete: then it is gone (exit 3, the server's 404)
    facesynth("--server", url, "models", "delete", model, check=EXIT_OK)
    done = facesynth("--server", url, "models", "show", model, check=EXIT_REJECTED)
    assert "404" in one_line(done.stderr)


def test_script_errors_are_one_line_with_their_exit_codes(server, actor_dir, tmp_path):
    url = server.url
    actor = one_line(facesynth("--server", url, "actors", "create", "errors",
                               check=EXIT_OK).stdout)

    # a missing local file: exit 2, one line naming it, nothing sent
    missing = tmp_path / "nope.npz"
    for argv in (("upload", "clip", actor, str(missing)), ("upload", "neutral", actor, str(missing)),
                 ("synthesize", "model_x", str(missing), "-o", str(tmp_path / "o"))):
        done = facesynth("--server", url, *argv, check=EXIT_USAGE)
        assert str(missing) in one_line(done.stderr) and done.stdout == ""
    done = facesynth("--server", url, "upload", "actor", str(tmp_path / "no-folder"),
                     check=EXIT_USAGE)
    assert "no such folder" in one_line(done.stderr)

    # a clip over --max-clip-bytes even without its maps: refused before anything is sent
    before = len(json.loads(facesynth("--server", url, "actors", "list", "--json").stdout))
    done = facesynth("--server", url, "upload", "actor", str(actor_dir), "--max-clip-bytes",
                     "1000", check=EXIT_USAGE)
    assert one_line(done.stderr).endswith(("train_fall.npz: 30 KiB even without maps, over "
                                           "--max-clip-bytes (1000 B); leave it out (--clips "
                                           "'train_*') or raise the server's max_body_bytes "
                                           "and --max-clip-bytes"))
    assert len(json.loads(facesynth("--server", url, "actors", "list", "--json").stdout)) == before

    # bad --params JSON: exit 2, one line
    done = facesynth("--server", url, "train", actor, "--kind", "pdm", "--clips", "clip_x",
                     "--params", "{medium_resolution: 32", check=EXIT_USAGE)
    assert "--params is not valid JSON" in one_line(done.stderr)
    facesynth("train", actor, "--kind", "pdm", "--clips", "c", "--set", "novalue",
              "--server", url, check=EXIT_USAGE)
    facesynth("--server", url, "synthesize", "m", str(actor_dir.parent / "take.csv"), "-o",
              str(tmp_path / "o"), "--pattern", "no-frame-field", check=EXIT_USAGE)

    # a refused synthesis leaves no output folder (nor its parents)
    out = tmp_path / "new" / "shot"
    done = facesynth("--server", url, "synthesize", "model_00000000000000000000000000",
                     str(actor_dir.parent / "take.csv"), "-o", str(out), check=EXIT_REJECTED)
    assert "404" in one_line(done.stderr)
    assert not (tmp_path / "new").exists()

    # no server there: exit 4; --version and help need none
    done = facesynth("--server", "http://127.0.0.1:9", "actors", "list", check=EXIT_SERVER)
    assert one_line(done.stderr).startswith("error:")
    assert one_line(facesynth("--version", check=EXIT_OK).stdout).startswith("facesynth ")
    top = facesynth("--help", check=EXIT_OK).stdout
    assert "``" not in top and "--server" in top and "upload" in top


def test_a_cancelled_training_is_cancelled_in_models_list(tmp_path, actor_dir):
    """On a server without workers the training stays queued, so the cancel surely lands."""
    idle = serve_app(tmp_path / "idle", worker=False)
    try:
        url = idle.url
        uploaded = json.loads(facesynth("--server", url, "upload", "actor", str(actor_dir),
                                        "--json", check=EXIT_OK).stdout)
        actor = uploaded["actor_id"]
        job_id = one_line(facesynth(
            "--server", url, "train", actor, "--kind", "pdm", "--clips",
            *uploaded["clips"].values(), "--no-wait", check=EXIT_OK).stdout)
        facesynth("--server", url, "jobs", "cancel", job_id, check=EXIT_OK)
        done = facesynth("--server", url, "jobs", "watch", job_id, check=EXIT_JOB_FAILED)
        assert "cancelled" in done.stderr
        rows = facesynth("--server", url, "models", "list", actor,
                         check=EXIT_OK).stdout.splitlines()
        assert rows[0].split()[:3] == ["id", "kind", "status"]
        assert rows[1].split()[2] == "cancelled"
    finally:
        idle.stop()

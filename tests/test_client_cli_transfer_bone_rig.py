"""``facesynth transfer`` and ``facesynth bone-rig`` (service.client_cli) against the real app
on a loopback port with a worker: the new model's id, the rig's files, the exit codes, and
the landmark file formats."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.cli import main
from service.client_cli import EXIT_OK, EXIT_REJECTED, EXIT_USAGE, UsageError, read_landmarks
from service.io.usd_skel import skinned_points
from service.methods.bone_rig.rig import BoneRig
from tests.api.conftest import layout_body, npz, sheet, sheet_motion
from tests.servers import serve_app
from tests.test_client_cli import run

MARKERS = (0, 7, 15, 48, 56, 64, 100, 104, 110, 150, 160, 167, 192, 200, 207)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    running = serve_app(tmp_path_factory.mktemp("cli-jobs2-server"), worker=True)
    yield running
    running.stop()



def test_transfer_and_bone_rig_commands(capsys, server, tmp_path):
    V, F, uv = sheet(16, 13)
    (tmp_path / "neutral.npz").write_bytes(npz(vertices=V, faces=F, uv=uv))
    (tmp_path / "markers.json").write_bytes(layout_body(MARKERS))
    actor = run(capsys, server, "actors", "create", "cli-source")[1].strip()
    assert run(capsys, server, "upload", "neutral", actor, str(tmp_path / "neutral.npz"))[0] == EXIT_OK
    assert run(capsys, server, "upload", "markers", actor, str(tmp_path / "markers.json"))[0] == EXIT_OK
    clips = []
    for phase in (0.0, 0.3):
        frames = sheet_motion(V, 12, phase).astype(np.float32)
        (tmp_path / "clip.npz").write_bytes(npz(vertices=frames, markers=frames[:, list(MARKERS)]))
        clips.append(run(capsys, server, "upload", "clip", actor, str(tmp_path / "clip.npz"))[1].strip())
    code, out, err = run(capsys, server, "train", actor, "--kind", "wpsd", "--clips", *clips,
                         "--params", json.dumps({"basis_size": 4, "selection_vertices": 128,
                                                 "map_resolution": None}))
    assert code == EXIT_OK, err
    source = out.strip()

    lm = np.linspace(0, len(V) - 1, 40).astype(int)
    (tmp_path / "landmarks.csv").write_text("source,target\n" + "\n".join(
        f"{a},{a}" for a in lm) + "\n")
    code, out, err = run(capsys, server, "transfer", source, "--target", actor,
                         "--landmarks", str(tmp_path / "landmarks.csv"))
    assert code == EXIT_OK, err
    moved = out.strip()
    assert moved.startswith("mdl_") and moved != source and "succeeded" in err
    code, out, _ = run(capsys, server, "models", "show", moved, "--json")
    assert json.loads(out)["status"] == "ready" and json.loads(out)["kind"] == "wpsd"
    (tmp_path / "few.json").write_text(json.dumps([[0, 0], [1, 1], [2, 2], [3, 9999]]))
    code, _, err = run(capsys, server, "transfer", source, "--target", actor,
                       "--landmarks", str(tmp_path / "few.json"))
    assert code == EXIT_REJECTED and "422" in err and "9999" in err

    out_dir = tmp_path / "rig"
    code, out, err = run(capsys, server, "bone-rig", actor, "--clip", clips[0], "--out",
                         str(out_dir), "--set", "bones=4", "--set", "iterations=3", "--fps", "25")
    assert code == EXIT_OK, err
    assert out.strip() == str(out_dir) and "bones, reconstruction RMS" in err
    assert sorted(p.name for p in out_dir.iterdir()) == ["rig.glb", "rig.json", "rig.npz"]
    rig = BoneRig.load_npz(out_dir / "rig.npz")
    assert rig.frames == 12 and rig.fps == 25.0 and rig.bones <= 4
    info = json.loads((out_dir / "rig.json").read_text())
    assert info["metrics"]["rms_mm"] == pytest.approx(
        np.sqrt(np.mean(np.sum((rig.reconstruct() - sheet_motion(V, 12, 0.0)) ** 2, -1))), abs=1e-3)
    usd_dir = tmp_path / "rig-usd"                         # --usd: the UsdSkel stage too
    code, _, err = run(capsys, server, "bone-rig", actor, "--clip", clips[0], "--out",
                       str(usd_dir), "--set", "bones=4", "--set", "iterations=3", "--usd")
    assert code == EXIT_OK, err
    assert sorted(p.name for p in usd_dir.iterdir()) == ["rig.glb", "rig.json", "rig.npz", "rig.usd"]
    usd_rig = BoneRig.load_npz(usd_dir / "rig.npz")
    assert np.abs(skinned_points(usd_dir / "rig.usd", 11) - usd_rig.reconstruct()[11]).max() < 1e-3
    code, _, err = run(capsys, server, "bone-rig", actor, "--clip", clips[0], "--out",
                       str(tmp_path / "none"), "--set", "bones=9999")
    assert code == EXIT_REJECTED and not (tmp_path / "none").exists()
    with pytest.raises(SystemExit) as exited:              # neither --clip nor --artifact
        main(["bone-rig", actor, "--out", str(tmp_path / "x"), "--server", server.url])
    assert exited.value.code == EXIT_USAGE
    assert "--clip" in capsys.readouterr().err


def test_landmark_files(tmp_path):
    pairs = [[0, 3], [5, 8], [9, 1]]
    (tmp_path / "a.json").write_text(json.dumps({"landmarks": pairs}))
    (tmp_path / "b.txt").write_text("# source target\n0 3\n5 8  # brow\n9 1\n")
    np.savez(tmp_path / "c.npz", landmarks=np.array(pairs))
    for name in ("a.json", "b.txt", "c.npz"):
        assert read_landmarks(tmp_path / name) == pairs
    (tmp_path / "bad.json").write_text(json.dumps([[0, 1, 2]]))
    (tmp_path / "float.json").write_text(json.dumps([[0.5, 1]]))
    for name in ("bad.json", "float.json", "missing.json"):
        with pytest.raises(UsageError):
            read_landmarks(tmp_path / name)

"""The pdm-train / pdm-synthesize commands on the level-0 sample actor."""

import json
from pathlib import Path

import numpy as np

from service.cli import main


def test_pdm_train_and_synthesize_from_the_command_line(pdm_actor_dir, tmp_path, capsys):
    model = tmp_path / "model"
    assert main(["pdm-train", "--actor", str(pdm_actor_dir), "--out", str(model), "--clips",
                 "train_smile", "train_brow_raise", "--medium-resolution", "64",
                 "--fine-resolution", "64", "--order", "linear", "--ridge", "0.2"]) == 0
    assert "PCA energy" in capsys.readouterr().out
    params = json.loads((model / "manifest.json").read_text())["params"]
    assert (params["ridge"], params["gamma"]) == (0.2, None)     # --gamma: the paper's γ
    with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
        np.savez(tmp_path / "m.npz", markers=d["markers"][:10])
    assert main(["pdm-synthesize", "--model", str(model), "--markers", str(tmp_path / "m.npz"),
                 "--out", str(tmp_path / "out.npz"), "--outputs", "mesh,displacement"]) == 0
    with np.load(tmp_path / "out.npz") as d:
        assert d["vertices"].shape == (10, 11248, 3) and d["displacement"].shape == (10, 64, 64)
        assert np.isfinite(d["vertices"]).all()


def test_store_fsck_reports_and_removes_orphans(tmp_path, capsys):
    import json
    import os

    from models_store import registry
    from models_store.blobs import BlobStore
    from models_store.db import make_session_factory, upgrade
    from service.cli import main
    from service.config import Settings

    settings = Settings(data_dir=tmp_path)
    upgrade(settings.database_url_resolved)
    blobs = BlobStore(settings.blob_dir)
    sessions = make_session_factory(settings.database_url_resolved)
    with sessions() as session:
        actor = registry.create_actor(session, "Ada")
        registry.set_neutral(session, blobs, actor.id, b"n", vertex_count=3, triangle_count=1)
    blobs.put_bytes(f"actors/{actor.id}/neutral-orphan", b"old")
    os.utime(blobs.path(f"actors/{actor.id}/neutral-orphan"), (0, 0))
    sessions.kw["bind"].dispose()
    assert main(["store", "fsck", "--data-dir", str(tmp_path)]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["orphans"] == [f"actors/{actor.id}/neutral-orphan"] and report["removed"] == []
    assert main(["store", "fsck", "--data-dir", str(tmp_path), "--remove"]) == 0
    assert json.loads(capsys.readouterr().out)["removed"] == [f"actors/{actor.id}/neutral-orphan"]
    assert main(["store", "fsck", "--data-dir", str(tmp_path)]) == 0


def test_the_readme_documents_commands_and_files_that_exist():
    """The README's pipeline claims (issue 22): `upload actor DIR`, `serve --preload`,
    `check`, frames.json, the gRPC extra's StreamingClient, every benchmark it lists."""
    import re

    from service.cli import build_parser

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    parser = build_parser()
    for argv in (["upload", "actor", "DIR"], ["serve", "--preload", "all"], ["check"]):
        assert "facesynth " + " ".join(argv[:2]) in readme or argv[0] == "serve"
        parser.parse_args(argv)
    assert "--preload all|MODEL_ID" in readme and "frames.json" in readme
    assert "[grpc]" in readme and "StreamingClient" in readme
    import facesynth_client

    assert hasattr(facesynth_client, "StreamingClient")
    listed = set(re.findall(r"`(\w+\.py)`", readme.split("| `benchmarks/` |")[1].split("\n")[0]))
    on_disk = {p.name for p in (root / "benchmarks").glob("*.py")}
    assert "grpc_stream.py" in listed and listed == on_disk

"""The pdm-train / pdm-synthesize commands on the level-0 sample actor."""

import numpy as np

from service.cli import main


def test_pdm_train_and_synthesize_from_the_command_line(pdm_actor_dir, tmp_path, capsys):
    model = tmp_path / "model"
    assert main(["pdm-train", "--actor", str(pdm_actor_dir), "--out", str(model), "--clips",
                 "train_smile", "train_brow_raise", "--medium-resolution", "64",
                 "--fine-resolution", "64", "--order", "linear"]) == 0
    assert "PCA energy" in capsys.readouterr().out
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

"""models_store.fsck: orphaned and missing blobs, on SQLite and PostgreSQL."""

from __future__ import annotations

import os
import time

from models_store import registry as reg
from models_store.fsck import fsck


def _age(blobs, key, seconds):
    then = time.time() - seconds
    path = blobs.root / key
    for p in [path, *path.rglob("*")]:
        os.utime(p, (then, then))


def test_fsck_finds_and_removes_exactly_the_unreferenced_blobs(session, blobs, tmp_path):
    actor = reg.create_actor(session, "Ada")
    reg.set_neutral(session, blobs, actor.id, b"neutral", vertex_count=3, triangle_count=1)
    clip = reg.add_clip(session, blobs, actor.id, b"clip", frames=1, name="c")
    model, job = reg.create_model(session, actor.id, "pdm", {})
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "manifest.json").write_text("{}")
    model = reg.mark_model_ready(session, blobs, model.id, tmp_path / "m", metrics={})
    artifact = reg.add_artifact(session, blobs, job.id, b"result", media_type="x/y")
    clean = fsck(session, blobs)
    assert clean.clean and clean.referenced == 4 and clean.orphans == []
    # what crashes between a blob write and its row's commit leave behind
    blobs.put_bytes(f"actors/{actor.id}/neutral-orphan", b"old neutral")
    blobs.put_dir(f"models/{model.id}/attempt2", tmp_path / "m")
    blobs.put_bytes("actors/act_gone/clips/clp_gone", b"clip of a deleted actor")
    blobs.put_bytes(f"actors/{actor.id}/markers-young", b"being committed")
    (blobs.root / f"actors/{actor.id}/.neutral-x.tmp").write_bytes(b"temporary: not fsck's")
    os.mkdir(blobs.root / "actors" / actor.id / "empty")
    for key in (f"actors/{actor.id}/neutral-orphan", f"models/{model.id}/attempt2",
                "actors/act_gone"):
        _age(blobs, key, 7200)
    report = fsck(session, blobs, remove=True)
    assert report.orphans == sorted([f"actors/{actor.id}/neutral-orphan",
                                     f"actors/{actor.id}/markers-young",
                                     f"models/{model.id}/attempt2", "actors/act_gone"])
    assert report.kept_young == [f"actors/{actor.id}/markers-young"]
    assert sorted(report.removed) == sorted([f"actors/{actor.id}/neutral-orphan",
                                             f"models/{model.id}/attempt2", "actors/act_gone"])
    assert report.missing == []
    # everything referenced is intact
    assert reg.read_neutral(session, blobs, actor.id) == b"neutral"
    assert reg.read_clip(session, blobs, clip.id) == b"clip"
    reg.model_dir(session, blobs, model.id)
    assert reg.open_artifact(session, blobs, artifact.id)[1].read() == b"result"
    assert fsck(session, blobs).orphans == [f"actors/{actor.id}/markers-young"]


def test_fsck_reports_rows_whose_blob_is_missing(session, blobs):
    actor = reg.create_actor(session, "Ada")
    clip = reg.add_clip(session, blobs, actor.id, b"clip", frames=1)
    os.unlink(blobs.path(clip.blob))
    report = fsck(session, blobs)
    assert report.missing == [("clips", clip.id, clip.blob)] and not report.clean

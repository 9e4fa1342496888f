"""The registry on SQLite and PostgreSQL: actors, clips, rigs, models, jobs, artifacts."""

from __future__ import annotations

import threading
from datetime import timedelta

import pytest
from sqlalchemy import event, func, select

from models_store import registry as reg
from models_store.errors import BlobCorrupt, Conflict, NotFound
from models_store.schema import Actor, Clip, InputRig, Model, utcnow

LEASE = 60.0


@pytest.fixture
def actor(session):
    return reg.create_actor(session, "Ada", {"unit": "mm"})


@pytest.fixture
def model_dir(tmp_path):
    root = tmp_path / "trained"
    (root / "maps").mkdir(parents=True)
    (root / "manifest.json").write_text('{"kind": "pdm", "version": 1}')
    (root / "maps" / "x.exr").write_bytes(bytes(range(256)) * 10)
    return root


def ready_model(session, blobs, actor, model_dir, kind="pdm"):
    model, job = reg.create_model(session, actor.id, kind, {"order": "bicubic"})
    reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2, job_id=job.id)
    model = reg.mark_model_ready(session, blobs, model.id, model_dir, metrics={"rms": 0.1})
    reg.finish_job(session, job.id, "succeeded", worker="w", result={"model_id": model.id})
    return model


def count(session, row_type):
    return session.scalar(select(func.count()).select_from(row_type))


def stored_files(blobs):
    return sorted(p.relative_to(blobs.root).as_posix() for p in blobs.root.rglob("*")
                  if p.is_file())


# -- actors ----------------------------------------------------------------------------------
def test_create_get_list_actor(session, actor):
    assert actor.id.startswith("act_") and actor.name == "Ada"
    assert actor.meta == {"unit": "mm"}
    assert actor.created_at.utcoffset() == timedelta(0)
    other = reg.create_actor(session, "Bob")
    got = reg.get_actor(session, actor.id)
    assert (got.id, got.name, got.meta) == (actor.id, "Ada", {"unit": "mm"})
    assert [a.id for a in reg.list_actors(session)] == [actor.id, other.id]


@pytest.mark.parametrize("actor_id", ["act_" + "0" * 26, "../../etc", "act_x", ""])
def test_unknown_or_malformed_actor_is_not_found(session, actor_id):
    with pytest.raises(NotFound, match="actor"):
        reg.get_actor(session, actor_id)


def test_actor_name_must_not_be_empty(session):
    with pytest.raises(ValueError, match="1 to 200 characters"):
        reg.create_actor(session, "")


def test_set_neutral_and_markers_store_verified_blobs(session, blobs, actor):
    reg.set_neutral(session, blobs, actor.id, b"neutral-1", vertex_count=3, triangle_count=1)
    reg.set_markers(session, blobs, actor.id, b'{"markers": []}', marker_count=0)
    assert reg.read_neutral(session, blobs, actor.id) == b"neutral-1"
    assert reg.read_markers(session, blobs, actor.id) == b'{"markers": []}'
    got = reg.get_actor(session, actor.id)
    assert (got.vertex_count, got.triangle_count, got.marker_count) == (3, 1, 0)


def test_replacing_the_neutral_deletes_the_old_blob(session, blobs, actor, tmp_path):
    reg.set_neutral(session, blobs, actor.id, b"old", vertex_count=3, triangle_count=1)
    old_key = reg.get_actor(session, actor.id).neutral_blob
    source = tmp_path / "neutral.npz"
    source.write_bytes(b"new")
    reg.set_neutral(session, blobs, actor.id, source, vertex_count=4, triangle_count=2)
    assert reg.read_neutral(session, blobs, actor.id) == b"new"
    assert not blobs.exists(old_key)
    assert len(stored_files(blobs)) == 1


def test_missing_neutral_is_not_found(session, blobs, actor):
    with pytest.raises(NotFound, match="no neutral mesh yet"):
        reg.read_neutral(session, blobs, actor.id)


def test_neutral_cannot_change_under_trained_models(session, blobs, actor, model_dir):
    reg.set_neutral(session, blobs, actor.id, b"n", vertex_count=3, triangle_count=1)
    model = ready_model(session, blobs, actor, model_dir)
    with pytest.raises(Conflict, match=f"models {model.id} depend on it"):
        reg.set_neutral(session, blobs, actor.id, b"m", vertex_count=3, triangle_count=1)
    with pytest.raises(Conflict):
        reg.set_markers(session, blobs, actor.id, b"{}", marker_count=0)
    assert reg.read_neutral(session, blobs, actor.id) == b"n"


def test_delete_actor_with_models_is_a_conflict_unless_cascade(session, blobs, actor, model_dir):
    model = ready_model(session, blobs, actor, model_dir)
    with pytest.raises(Conflict, match=f"has 1 model\\(s\\) \\({model.id}\\)"):
        reg.delete_actor(session, blobs, actor.id)
    assert reg.get_model(session, model.id).status == "ready"
    reg.delete_actor(session, blobs, actor.id, cascade=True)
    with pytest.raises(NotFound):
        reg.get_actor(session, actor.id)


def test_cascade_delete_removes_rows_and_blobs_from_disk(session, blobs, actor, model_dir):
    other = reg.create_actor(session, "Other")
    reg.add_clip(session, blobs, other.id, b"other clip", frames=1)
    reg.set_neutral(session, blobs, actor.id, b"n", vertex_count=3, triangle_count=1)
    reg.set_markers(session, blobs, actor.id, b"{}", marker_count=0)
    reg.add_clip(session, blobs, actor.id, b"clip", frames=2)
    reg.put_input_rig(session, blobs, actor.id, "game", b"rig")
    ready = ready_model(session, blobs, actor, model_dir)
    training, train_job = reg.create_model(session, actor.id, "psd")
    assert len(stored_files(blobs)) == 7  # neutral, markers, 2 clips, rig, 2 model files

    reg.delete_actor(session, blobs, actor.id, cascade=True)

    assert stored_files(blobs) == [f"actors/{other.id}/clips/" +
                                   reg.list_clips(session, other.id)[0].id]
    assert not blobs.path(f"actors/{actor.id}").exists()
    assert not blobs.path(f"models/{ready.id}").exists()
    for row_type in (Model, InputRig):
        assert count(session, row_type) == 0
    assert count(session, Clip) == 1 and count(session, Actor) == 1
    job = reg.get_job(session, train_job.id)   # job records outlive the actor, cancelled
    assert job.status == "cancelled"


def test_delete_actor_without_models_removes_its_clips(session, blobs, actor):
    clip = reg.add_clip(session, blobs, actor.id, b"c", frames=1)
    reg.delete_actor(session, blobs, actor.id)
    assert count(session, Clip) == 0
    assert not blobs.exists(clip.blob) and stored_files(blobs) == []


# -- clips -----------------------------------------------------------------------------------
def test_add_list_read_delete_clip(session, blobs, actor, tmp_path):
    first = reg.add_clip(session, blobs, actor.id, b"\x00\x01frames", frames=12, name="smile")
    source = tmp_path / "c.npz"
    source.write_bytes(b"second")
    second = reg.add_clip(session, blobs, actor.id, source, frames=3)
    assert (first.frames, first.name, first.size_bytes) == (12, "smile", 8)
    assert [c.id for c in reg.list_clips(session, actor.id)] == [first.id, second.id]
    assert reg.read_clip(session, blobs, first.id) == b"\x00\x01frames"
    reg.delete_clip(session, blobs, first.id, actor.id)
    assert not blobs.exists(first.blob)
    assert [c.id for c in reg.list_clips(session, actor.id)] == [second.id]
    with pytest.raises(NotFound):
        reg.get_clip(session, first.id)


def test_clip_of_another_actor_is_not_found(session, blobs, actor):
    other = reg.create_actor(session, "Other")
    clip = reg.add_clip(session, blobs, other.id, b"c", frames=1)
    with pytest.raises(NotFound, match="belongs to another actor"):
        reg.get_clip(session, clip.id, actor.id)
    with pytest.raises(NotFound):
        reg.delete_clip(session, blobs, clip.id, actor.id)
    with pytest.raises(NotFound):
        reg.create_model(session, actor.id, "pdm", clip_ids=[clip.id])
    assert count(session, Model) == 0


def test_clip_for_unknown_actor_writes_no_blob(session, blobs):
    with pytest.raises(NotFound):
        reg.add_clip(session, blobs, "act_" + "0" * 26, b"c", frames=1)
    assert stored_files(blobs) == []


def test_corrupted_clip_raises_blob_corrupt(session, blobs, actor):
    clip = reg.add_clip(session, blobs, actor.id, b"clean", frames=1)
    blobs.path(clip.blob).write_bytes(b"dirty")
    with pytest.raises(BlobCorrupt):
        reg.read_clip(session, blobs, clip.id)


# -- input rigs ------------------------------------------------------------------------------
def test_input_rig_register_then_replace(session, blobs, actor):
    rig = reg.put_input_rig(session, blobs, actor.id, "game", b"mesh-1")
    assert rig.status == "registering" and rig.id.startswith("rig_")
    rig = reg.mark_rig_ready(session, blobs, rig.id, b"registration")
    assert rig.status == "ready"
    with pytest.raises(Conflict, match="is ready, not registering"):
        reg.mark_rig_failed(session, rig.id, "x", "y")
    old = (rig.mesh_blob, rig.registration_blob)
    again = reg.put_input_rig(session, blobs, actor.id, "game", b"mesh-2")
    assert again.id == rig.id and again.status == "registering"
    assert again.registration_blob is None
    assert not any(blobs.exists(k) for k in old)
    assert [r.name for r in reg.list_input_rigs(session, actor.id)] == ["game"]
    assert reg.get_input_rig(session, actor.id, "game").mesh_sha256 == again.mesh_sha256
    failed = reg.mark_rig_failed(session, rig.id, "no_fit", "landmarks disagree")
    assert failed.error == {"code": "no_fit", "message": "landmarks disagree"}
    with pytest.raises(NotFound, match="no input rig of that name"):
        reg.get_input_rig(session, actor.id, "film")


# -- models ----------------------------------------------------------------------------------
def test_create_model_makes_a_training_model_and_its_queued_job(session, blobs, actor):
    clip = reg.add_clip(session, blobs, actor.id, b"c", frames=1)
    model, job = reg.create_model(session, actor.id, "pdm", {"order": "linear"},
                                  clip_ids=[clip.id])
    assert model.status == "training" and model.params == {"order": "linear"}
    assert (job.kind, job.status, job.model_id, job.actor_id) == ("train", "queued", model.id,
                                                                  actor.id)
    assert job.payload == {"model_id": model.id, "clip_ids": [clip.id]}
    assert [m.id for m in reg.list_models(session, actor.id)] == [model.id]
    assert reg.list_models(session, status="ready") == []


def test_mark_ready_stores_the_directory_and_metrics(session, blobs, actor, model_dir):
    model = ready_model(session, blobs, actor, model_dir)
    got = reg.get_model(session, model.id)
    assert got.status == "ready" and got.metrics == {"rms": 0.1}
    assert got.size_bytes == sum(p.stat().st_size for p in model_dir.rglob("*") if p.is_file())
    path = reg.model_dir(session, blobs, model.id)
    assert (path / "maps" / "x.exr").read_bytes() == (model_dir / "maps" / "x.exr").read_bytes()
    (path / "manifest.json").write_text("tampered")
    with pytest.raises(BlobCorrupt):
        reg.model_dir(session, blobs, model.id)


def test_a_ready_model_is_immutable(session, sessions, blobs, actor, model_dir, tmp_path):
    model = ready_model(session, blobs, actor, model_dir)
    files = stored_files(blobs)
    with pytest.raises(Conflict, match="is ready, not training"):
        reg.mark_model_ready(session, blobs, model.id, model_dir, metrics={"rms": 9.9})
    with pytest.raises(Conflict, match="is ready, not training"):
        reg.mark_model_failed(session, model.id, "late", "too late")
    assert stored_files(blobs) == files             # the refused call stored nothing
    with sessions() as other:                       # a direct ORM change is refused too
        row = other.get(Model, model.id)
        row.params = {"order": "linear"}
        with pytest.raises(Conflict, match="ready and immutable; refused to change params"):
            other.commit()
    got = reg.get_model(session, model.id)
    assert (got.status, got.params, got.metrics) == ("ready", {"order": "bicubic"}, {"rms": 0.1})


def test_model_files_are_only_served_when_ready(session, blobs, actor):
    model, _ = reg.create_model(session, actor.id, "pdm")
    with pytest.raises(Conflict, match="is training, not ready"):
        reg.model_dir(session, blobs, model.id)


def test_mark_failed_then_ready_is_refused(session, sessions, blobs, actor, model_dir):
    model, _ = reg.create_model(session, actor.id, "pdm")
    failed = reg.mark_model_failed(session, model.id, "diverged", "fit error grew")
    assert failed.status == "failed" and failed.error["code"] == "diverged"
    with pytest.raises(Conflict):
        reg.mark_model_ready(session, blobs, model.id, model_dir, metrics={})
    assert stored_files(blobs) == []
    with pytest.raises(NotFound):
        reg.mark_model_failed(session, "mdl_" + "0" * 26, "x", "y")
    with sessions() as other:   # the refused call released the write lock (SQLite)
        reg.create_actor(other, "next")


def test_delete_model_removes_its_files_and_cancels_its_jobs(session, blobs, actor, model_dir):
    model = ready_model(session, blobs, actor, model_dir)
    synth = reg.create_job(session, "synthesis", actor.id, model_id=model.id)
    reg.delete_model(session, blobs, model.id)
    assert stored_files(blobs) == []
    assert not blobs.path(f"models/{model.id}").exists()
    assert reg.get_job(session, synth.id).status == "cancelled"
    with pytest.raises(NotFound):
        reg.get_model(session, model.id)


# -- jobs ------------------------------------------------------------------------------------
def test_create_and_filter_jobs(session, actor):
    other = reg.create_actor(session, "Other")
    a = reg.create_job(session, "track", actor.id, payload={"views": 2})
    b = reg.create_job(session, "register", actor.id)
    c = reg.create_job(session, "track", other.id)
    reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2, job_id=b.id)
    ids = lambda jobs: [j.id for j in jobs]  # noqa: E731
    assert ids(reg.list_jobs(session)) == [a.id, b.id, c.id]
    assert ids(reg.list_jobs(session, kind="track")) == [a.id, c.id]
    assert ids(reg.list_jobs(session, actor_id=actor.id, kind="track")) == [a.id]
    assert ids(reg.list_jobs(session, status="running")) == [b.id]
    assert reg.get_job(session, a.id).payload == {"views": 2}
    with pytest.raises(NotFound):
        reg.create_job(session, "track", "act_" + "0" * 26)


def test_claim_takes_the_oldest_queued_job_with_a_lease(session, actor):
    first = reg.create_job(session, "track", actor.id)
    reg.create_job(session, "track", actor.id)
    now = utcnow()
    job = reg.claim_job(session, "host:1", lease_seconds=30, max_retries=2, now=now)
    assert job.id == first.id
    assert (job.status, job.worker, job.attempts) == ("running", "host:1", 1)
    assert job.lease_expires_at == now + timedelta(seconds=30)
    assert job.started_at == now


def test_claim_filters_by_kind_and_returns_none_when_nothing_is_left(session, actor):
    track = reg.create_job(session, "track", actor.id)
    assert reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2, kinds=["x"]) is None
    assert reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2,
                         kinds=["track"]).id == track.id
    assert reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2) is None
    assert reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2,
                         job_id=track.id) is None


def test_two_claimers_never_both_claim_one_job(sessions, session, actor):
    for _ in range(10):
        job = reg.create_job(session, "train", actor.id)
        start = threading.Barrier(2)
        results = {}

        def claim(worker):
            with sessions() as own:
                start.wait()
                results[worker] = reg.claim_job(own, worker, lease_seconds=LEASE,
                                                max_retries=2, job_id=job.id)

        threads = [threading.Thread(target=claim, args=(f"w{i}",)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        winners = [w for w, got in results.items() if got is not None]
        assert len(results) == 2 and len(winners) == 1
        stored = reg.get_job(session, job.id)
        assert (stored.worker, stored.attempts) == (winners[0], 1)


def test_concurrent_workers_claim_every_job_exactly_once(sessions, session, actor):
    jobs = {reg.create_job(session, "synthesis", actor.id).id for _ in range(24)}
    claimed: dict[str, list[str]] = {}
    start = threading.Barrier(4)
    errors = []

    def work(worker):
        try:
            with sessions() as own:
                start.wait()
                while job := reg.claim_job(own, worker, lease_seconds=LEASE, max_retries=2):
                    claimed.setdefault(worker, []).append(job.id)
                    reg.finish_job(own, job.id, "succeeded", worker=worker)
        except Exception as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(f"w{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    everything = [j for ids in claimed.values() for j in ids]
    assert sorted(everything) == sorted(jobs)                 # each exactly once
    assert {j.status for j in reg.list_jobs(session)} == {"succeeded"}
    assert {j.attempts for j in reg.list_jobs(session)} == {1}


def test_progress_is_recorded_and_cancellation_is_cooperative(session, actor):
    model, job = reg.create_model(session, actor.id, "pdm")
    reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2, job_id=job.id)
    seen = reg.update_job_progress(session, job.id, 0.25, "fitting medium scale", worker="w")
    assert (seen.progress, seen.stage, seen.cancel_requested) == (0.25, "fitting medium scale",
                                                                  False)
    assert reg.request_cancel(session, job.id).status == "running"   # flagged only
    seen = reg.update_job_progress(session, job.id, 0.5, worker="w")
    assert seen.cancel_requested
    done = reg.finish_job(session, job.id, "cancelled", worker="w")
    assert done.status == "cancelled" and done.finished_at is not None
    assert done.error["code"] == "cancelled"
    assert reg.get_model(session, model.id).status == "failed"
    assert reg.request_cancel(session, job.id).status == "cancelled"  # idempotent
    with pytest.raises(ValueError, match="within \\[0, 1\\]"):
        reg.update_job_progress(session, job.id, 1.5)


def test_cancelling_a_queued_job_is_immediate(session, actor):
    model, job = reg.create_model(session, actor.id, "pdm")
    cancelled = reg.request_cancel(session, job.id)
    assert cancelled.status == "cancelled" and cancelled.finished_at is not None
    assert reg.get_model(session, model.id).status == "failed"
    assert reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2) is None


@pytest.mark.parametrize("move", ["park", "claim"])
def test_a_job_parked_or_claimed_while_being_cancelled_still_ends_cancelled(
        engine, sessions, session, actor, move):
    """The worker moves the job (running → queued by park_job, or queued → running by
    claim_job) from its own connection just before the cancellation's UPDATE runs: the job
    is still either cancelled or flagged, never left queued and unflagged (a select then two
    updates lost the park: a tracking job then found its span jobs cancelled and failed)."""
    job = reg.create_job(session, "track", actor.id)
    if move == "park":
        reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2, job_id=job.id)
    fired = []

    def before(conn, cursor, statement, parameters, context, executemany):
        if fired or not statement.lstrip().upper().startswith("UPDATE JOB"):
            return
        fired.append(statement)
        with sessions() as worker:
            if move == "park":
                reg.park_job(worker, job.id, worker="w")
            else:
                reg.claim_job(worker, "w", lease_seconds=LEASE, max_retries=2, job_id=job.id)

    event.listen(engine, "before_cursor_execute", before)
    try:
        reg.request_cancel(session, job.id)
    finally:
        event.remove(engine, "before_cursor_execute", before)
    assert fired
    seen = reg.get_job(session, job.id)
    assert seen.cancel_requested
    assert seen.status == ("cancelled" if move == "park" else "running")
    assert reg.claim_job(session, "v", lease_seconds=LEASE, max_retries=2, job_id=job.id) is None


def test_finish_records_result_or_error(session, actor):
    ok = reg.create_job(session, "track", actor.id)
    bad = reg.create_job(session, "track", actor.id)
    for job in (ok, bad):
        reg.claim_job(session, "w", lease_seconds=LEASE, max_retries=2, job_id=job.id)
    done = reg.finish_job(session, ok.id, "succeeded", worker="w",
                          result={"artifact_ids": ["art_1"]})
    assert (done.status, done.progress, done.result) == ("succeeded", 1.0,
                                                         {"artifact_ids": ["art_1"]})
    assert done.lease_expires_at is None and done.error is None
    with pytest.raises(ValueError, match="needs an error"):
        reg.finish_job(session, bad.id, "failed", worker="w")
    with pytest.raises(ValueError, match="'code' and 'message'"):
        reg.finish_job(session, bad.id, "failed", worker="w", error={"msg": "x"})
    failed = reg.finish_job(session, bad.id, "failed", worker="w",
                            error={"code": "no_views", "message": "no camera saw the face"})
    assert failed.error == {"code": "no_views", "message": "no camera saw the face"}
    with pytest.raises(Conflict, match="is failed, not running"):
        reg.finish_job(session, bad.id, "succeeded", worker="w")


def test_heartbeat_extends_the_lease_and_a_lost_lease_is_a_conflict(session, actor):
    job = reg.create_job(session, "track", actor.id)
    t0 = utcnow()
    reg.claim_job(session, "a", lease_seconds=10, max_retries=2, now=t0)
    beat = reg.heartbeat(session, job.id, "a", 10, now=t0 + timedelta(seconds=8))
    assert beat.lease_expires_at == t0 + timedelta(seconds=18)
    assert reg.reap_expired(session, max_retries=2, now=t0 + timedelta(seconds=15)).requeued == []
    # a dies; after expiry b takes the job over directly
    late = t0 + timedelta(seconds=19)
    taken = reg.claim_job(session, "b", lease_seconds=10, max_retries=2, now=late)
    assert (taken.id, taken.worker, taken.attempts) == (job.id, "b", 2)
    with pytest.raises(Conflict, match="lease lost: it is now held by worker 'b', not 'a'"):
        reg.heartbeat(session, job.id, "a", 10)
    with pytest.raises(Conflict, match="lease lost"):
        reg.update_job_progress(session, job.id, 0.9, worker="a")
    with pytest.raises(Conflict, match="lease lost"):
        reg.finish_job(session, job.id, "succeeded", worker="a")
    assert reg.finish_job(session, job.id, "succeeded", worker="b").status == "succeeded"


def test_expired_leases_are_requeued_then_failed_after_max_retries(session, actor):
    model, job = reg.create_model(session, actor.id, "pdm")
    now = utcnow()
    for attempt in (1, 2, 3):
        claimed = reg.claim_job(session, f"w{attempt}", lease_seconds=LEASE, max_retries=2,
                                now=now)
        assert (claimed.id, claimed.attempts) == (job.id, attempt)
        now += timedelta(seconds=LEASE + 1)               # the worker died silently
        reaped = reg.reap_expired(session, max_retries=2, now=now)
        if attempt < 3:
            assert reaped.requeued == [job.id] and reaped.failed == []
            assert reg.get_job(session, job.id).status == "queued"
    assert reaped.failed == [job.id] and reaped.requeued == []
    failed = reg.get_job(session, job.id)
    assert failed.status == "failed" and failed.error["code"] == "lease_expired"
    assert "'w3'" in failed.error["message"] and "3 attempt(s)" in failed.error["message"]
    assert reg.get_model(session, model.id).status == "failed"
    assert reg.claim_job(session, "w4", lease_seconds=LEASE, max_retries=2, now=now) is None


def test_an_expired_job_past_its_retries_cannot_be_claimed_directly(session, actor):
    job = reg.create_job(session, "track", actor.id)
    now = utcnow()
    reg.claim_job(session, "a", lease_seconds=LEASE, max_retries=0, now=now)
    later = now + timedelta(seconds=LEASE + 1)
    assert reg.claim_job(session, "b", lease_seconds=LEASE, max_retries=0, now=later) is None
    assert reg.reap_expired(session, max_retries=0, now=later).failed == [job.id]


def test_reaping_a_cancelled_running_job_cancels_it(session, actor):
    job = reg.create_job(session, "track", actor.id)
    now = utcnow()
    reg.claim_job(session, "a", lease_seconds=LEASE, max_retries=2, now=now)
    reg.request_cancel(session, job.id)
    reaped = reg.reap_expired(session, max_retries=2, now=now + timedelta(seconds=LEASE + 1))
    assert reaped.cancelled == [job.id]
    assert reg.get_job(session, job.id).status == "cancelled"


# -- artifacts -------------------------------------------------------------------------------
def test_artifact_round_trip_and_corruption(session, blobs, actor):
    job = reg.create_job(session, "synthesis", actor.id)
    artifact = reg.add_artifact(session, blobs, job.id, b"npz bytes",
                                media_type="application/x-npz", filename="out.npz")
    assert artifact.id.startswith("art_") and artifact.size_bytes == 9
    assert [a.id for a in reg.list_artifacts(session, job.id)] == [artifact.id]
    got, stream = reg.open_artifact(session, blobs, artifact.id)
    with stream:
        assert stream.read() == b"npz bytes" and got.media_type == "application/x-npz"
    blobs.path(artifact.blob).write_bytes(b"npz bytez")
    with pytest.raises(BlobCorrupt):
        reg.open_artifact(session, blobs, artifact.id)


# -- concurrent replacement leaves no orphan blobs (issue 16, defect 6) ----------------------
def _concurrently(n, target):
    start = threading.Barrier(n)
    errors = []

    def run(i):
        start.wait()
        try:
            target(i)
        except Exception as error:  # noqa: BLE001 - collected and asserted below
            errors.append(error)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    return errors


@pytest.mark.parametrize("what", ["neutral", "markers"])
def test_concurrent_replacements_leave_exactly_the_referenced_blob(sessions, session, blobs,
                                                                   actor, what):
    def put(i):
        with sessions() as own:
            if what == "neutral":
                reg.set_neutral(own, blobs, actor.id, b"neutral %d" % i, vertex_count=i + 3,
                                triangle_count=1)
            else:
                reg.set_markers(own, blobs, actor.id, b"markers %d" % i, marker_count=i + 1)

    assert _concurrently(16, put) == []
    row = reg.get_actor(session, actor.id)
    key = row.neutral_blob if what == "neutral" else row.markers_blob
    assert stored_files(blobs) == [key]                          # no orphans
    data = (reg.read_neutral if what == "neutral" else reg.read_markers)(session, blobs, actor.id)
    i = int(data.split()[1])                                     # the row and blob agree
    assert (row.vertex_count if what == "neutral" else row.marker_count) == (
        i + 3 if what == "neutral" else i + 1)


@pytest.mark.parametrize("what", ["neutral", "markers"])
def test_a_read_racing_replacements_gets_a_current_blob(sessions, session, blobs, actor, what):
    """Readers during 12 concurrent replacements each get one of the written blobs, never a
    NotFound for the blob a replacement deleted under them; a blob missing for real (the
    row still names it) stays NotFound."""
    put = reg.set_neutral if what == "neutral" else reg.set_markers
    read = reg.read_neutral if what == "neutral" else reg.read_markers
    counts = {"vertex_count": 3, "triangle_count": 1} if what == "neutral" else {"marker_count": 1}
    put(session, blobs, actor.id, b"first", **counts)
    got: list[bytes] = []

    def race(i):
        with sessions() as own:
            if i % 2:
                put(own, blobs, actor.id, b"blob %d" % i, **counts)
            else:
                for _ in range(20):
                    got.append(read(own, blobs, actor.id))

    assert _concurrently(24, race) == []
    assert len(got) == 12 * 20 and all(d == b"first" or d.startswith(b"blob ") for d in got)
    row = reg.get_actor(session, actor.id)
    blobs.delete(row.neutral_blob if what == "neutral" else row.markers_blob)
    with pytest.raises(NotFound):
        read(session, blobs, actor.id)


def test_concurrent_rig_replacements_leave_exactly_the_referenced_blob(sessions, session, blobs,
                                                                       actor):
    reg.put_input_rig(session, blobs, actor.id, "lowres", b"first")

    def put(i):
        with sessions() as own:
            reg.put_input_rig(own, blobs, actor.id, "lowres", b"mesh %d" % i)

    assert _concurrently(12, put) == []
    rig = reg.get_input_rig(session, actor.id, "lowres")
    assert stored_files(blobs) == [rig.mesh_blob]


def test_concurrent_first_puts_of_one_rig_make_one_rig_and_no_orphans(sessions, session, blobs,
                                                                      actor):
    def put(i):
        with sessions() as own:
            reg.put_input_rig(own, blobs, actor.id, "fresh", b"mesh %d" % i)

    assert _concurrently(8, put) == []
    (rig,) = reg.list_input_rigs(session, actor.id)
    assert stored_files(blobs) == [rig.mesh_blob]


# -- tenants (issue 16, defect 13) -----------------------------------------------------------
def test_every_lookup_is_scoped_to_the_tenant_and_others_ids_are_plain_not_found(
        session, blobs, model_dir):
    a = reg.create_actor(session, "Ada", tenant="studio-a")
    b = reg.create_actor(session, "Bob", tenant="studio-b")
    reg.set_neutral(session, blobs, a.id, b"n", vertex_count=3, triangle_count=1)
    clip = reg.add_clip(session, blobs, a.id, b"clip", frames=1)
    reg.put_input_rig(session, blobs, a.id, "low", b"mesh")
    model, job = reg.create_model(session, a.id, "pdm", {}, clip_ids=[clip.id])
    artifact = reg.add_artifact(session, blobs, job.id, b"r", media_type="x/y")
    assert (model.tenant, job.tenant) == ("studio-a", "studio-a")      # inherited from the actor
    assert [x.id for x in reg.list_actors(session, tenant="studio-a")] == [a.id]
    assert [x.id for x in reg.list_actors(session, tenant="studio-b")] == [b.id]
    assert len(reg.list_actors(session)) == 2                            # admin: every tenant
    assert reg.list_models(session, tenant="studio-b") == []
    assert reg.list_jobs(session, tenant="studio-b") == []
    assert [j.id for j in reg.list_jobs(session, tenant="studio-a")] == [job.id]
    other = "studio-b"
    calls = {
        "actor": lambda: reg.get_actor(session, a.id, tenant=other),
        "neutral": lambda: reg.read_neutral(session, blobs, a.id, tenant=other),
        "set neutral": lambda: reg.set_neutral(session, blobs, a.id, b"x", vertex_count=3,
                                               triangle_count=1, tenant=other),
        "clips": lambda: reg.list_clips(session, a.id, tenant=other),
        "clip": lambda: reg.get_clip(session, clip.id, tenant=other),
        "add clip": lambda: reg.add_clip(session, blobs, a.id, b"c", frames=1, tenant=other),
        "delete clip": lambda: reg.delete_clip(session, blobs, clip.id, tenant=other),
        "rig": lambda: reg.get_input_rig(session, a.id, "low", tenant=other),
        "put rig": lambda: reg.put_input_rig(session, blobs, a.id, "low", b"m", tenant=other),
        "model": lambda: reg.get_model(session, model.id, tenant=other),
        "models": lambda: reg.list_models(session, a.id, tenant=other),
        "train": lambda: reg.create_model(session, a.id, "pdm", {}, tenant=other),
        "delete model": lambda: reg.delete_model(session, blobs, model.id, tenant=other),
        "job": lambda: reg.get_job(session, job.id, tenant=other),
        "create job": lambda: reg.create_job(session, "synthesize", a.id, tenant=other),
        "cancel": lambda: reg.request_cancel(session, job.id, tenant=other),
        "artifact": lambda: reg.get_artifact(session, artifact.id, tenant=other),
        "artifacts": lambda: reg.list_artifacts(session, job.id, tenant=other),
        "open artifact": lambda: reg.open_artifact(session, blobs, artifact.id, tenant=other),
        "delete actor": lambda: reg.delete_actor(session, blobs, a.id, cascade=True,
                                                 tenant=other),
    }
    for what, call in calls.items():
        with pytest.raises(NotFound) as raised:
            call()
        assert "another" not in str(raised.value) and "studio" not in str(raised.value), what
    # nothing changed
    assert reg.get_job(session, job.id, tenant="studio-a").status == "queued"
    assert reg.read_clip(session, blobs, clip.id, tenant="studio-a") == b"clip"
    assert len(reg.list_clips(session, a.id)) == 1
    assert reg.get_model(session, model.id, tenant="studio-a").id == model.id


def test_malformed_tenants_are_refused(session):
    for bad in ("", "../x", "a b", "x" * 65):
        with pytest.raises(ValueError, match="tenant"):
            reg.create_actor(session, "Ada", tenant=bad)


def test_acting_for_scopes_every_call_without_arguments(session, blobs):
    with reg.acting_for("studio-a", "studio-a"):
        a = reg.create_actor(session, "Ada")
        job = reg.create_job(session, "synthesize", a.id)
    with reg.acting_for("studio-b", "studio-b"):
        b = reg.create_actor(session, "Bob")
        assert [x.id for x in reg.list_actors(session)] == [b.id]
        assert reg.list_jobs(session) == []
        for call in (lambda: reg.get_actor(session, a.id), lambda: reg.get_job(session, job.id),
                     lambda: reg.list_clips(session, a.id)):
            with pytest.raises(NotFound):
                call()
    with reg.acting_for("ops", None):                     # an admin
        assert {x.id for x in reg.list_actors(session)} == {a.id, b.id}
        assert reg.create_actor(session, "Op").tenant == "ops"
    assert (a.tenant, b.tenant, job.tenant) == ("studio-a", "studio-b", "studio-a")
    assert len(reg.list_actors(session)) == 3            # no scope outside a request


@pytest.mark.parametrize("name, metadata", [("ok", {"k": "\udfff"}), ("ok", {"\ud800": 1}),
                                            ("p\udfff", {}), ("ok", {"k": ["a\x00"]})])
def test_unencodable_strings_are_never_committed(session, blobs, name, metadata):
    with pytest.raises(ValueError, match="refused before writing"):
        reg.create_actor(session, name, metadata)
    assert reg.list_actors(session) == []
    actor = reg.create_actor(session, "fine")
    with pytest.raises(ValueError, match="refused before writing"):
        reg.add_clip(session, blobs, actor.id, b"clip", frames=1, name="a\x00b")
    assert reg.list_clips(session, actor.id) == [] and list(blobs.root.rglob("*")) == []

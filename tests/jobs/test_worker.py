"""End to end through real queues: worker threads consuming SqliteHuey and RedisHuey, jobs
training and synthesizing with the sample actor, cancellation, dead workers, bad input."""

from __future__ import annotations

import dataclasses
import io
import secrets
import threading
import zipfile
from datetime import timedelta

import numpy as np
import pytest

from models_store import registry
from models_store.schema import utcnow
from service.store import actors as actor_store
from service.io.exr import read_map
from service.io.mesh import read_obj
from service.io.npz import npz_arrays
from service.jobs.queue import get_queue, submit
from service.jobs.worker import reap_and_resubmit, resubmit_stale
from service.methods import kinds
from service.samples import dataset


def _markers(pdm_actor_dir, frames: int = 20) -> np.ndarray:
    with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
        return d["markers"][:frames].astype(np.float64)


def test_training_job_on_the_sqlite_queue_makes_a_ready_model(deployment, trained, pdm_actor_dir):
    model_id, job = trained
    assert (job.status, job.progress, job.error) == ("succeeded", 1.0, None)
    assert job.result == {"model_id": model_id} and job.attempts == 1
    assert job.started_at <= job.finished_at
    model = deployment.model(model_id)
    assert model.status == "ready" and model.size_bytes > 0
    assert model.metrics["training_frames"] == 40 and model.metrics["clips"] == list(
        dataset.performance_names(pdm_actor_dir, "train_smile")
        + dataset.performance_names(pdm_actor_dir, "train_brow_raise"))
    # the stored model loads and synthesizes
    with deployment.session() as session:
        path = registry.model_dir(session, deployment.store.blobs, model_id)
    out = kinds.get_kind("pdm").load(path).synthesize(_markers(pdm_actor_dir, 3))
    assert out["vertices"].shape == (3, 11248, 3) and np.isfinite(out["vertices"]).all()
    assert out["displacement"].shape == (3, 64, 64)
    assert (deployment.settings.data_dir / "queue.db").is_file()


def _run_synthesis_job(deployment, start_worker, model_id, markers, **payload):
    """Run a synthesis job to success; its one artifact row, the artifact's bytes and the
    model's directory."""
    job_id = deployment.create_synthesis_job(model_id, markers, **payload)
    start_worker(deployment.settings)
    submit(deployment.settings, job_id)
    job = deployment.wait(job_id)
    assert job.status == "succeeded", job.error
    (artifact_id,) = job.result["artifact_ids"]
    with deployment.session() as session:
        artifact, stream = registry.open_artifact(session, deployment.store.blobs, artifact_id)
        with stream:
            data = stream.read()
        return artifact, data, registry.model_dir(session, deployment.store.blobs, model_id)


def test_synthesis_job_writes_an_npz_artifact(deployment, trained, start_worker, pdm_actor_dir):
    model_id, _ = trained
    markers = _markers(pdm_actor_dir, 20)
    markers[5, 3] = np.nan  # an occluded marker
    artifact, data, path = _run_synthesis_job(deployment, start_worker, model_id, markers,
                                              outputs=["mesh", "displacement", "normal_map"])
    result = npz_arrays(data)
    assert artifact.media_type == "application/x-npz"
    assert result["vertices"].shape == (20, 11248, 3) and result["normal_map"].shape == (20, 64, 64, 3)
    expected = kinds.get_kind("pdm").load(path).synthesize(markers, ("mesh", "displacement"))
    np.testing.assert_array_equal(result["vertices"], expected["vertices"])
    np.testing.assert_array_equal(result["displacement"], expected["displacement"])
    np.testing.assert_array_equal(result["faces"], expected["faces"])


def test_synthesis_job_filters_the_markers_in_time_when_asked(deployment, trained, start_worker,
                                                              pdm_actor_dir):
    """``marker_filter_frames``: the job synthesizes the temporally filtered performance, and
    the confidence reads the noise of the markers as captured (``captured``)."""
    from service.geometry.marker_filter import filter_performance

    model_id, _ = trained
    markers = _markers(pdm_actor_dir, 12)
    # float32-exact, as the job's stored input is
    markers = (markers + np.random.default_rng(0).normal(0, 0.3, markers.shape)).astype(np.float32).astype(np.float64)
    for sigma in (2.0, "auto"):
        _, data, path = _run_synthesis_job(deployment, start_worker, model_id, markers,
                                           outputs=["mesh"], marker_filter_frames=sigma)
        model = kinds.get_kind("pdm").load(path)          # "auto": in its prior's modes
        assert model.marker_modes is not None
        filtered = filter_performance(markers, sigma, modes=model.marker_modes)
        expected = model.synthesize(filtered, ("mesh",), captured=markers)
        result = npz_arrays(data)
        np.testing.assert_array_equal(result["vertices"], expected["vertices"])
        np.testing.assert_array_equal(result["confidence"], expected["confidence"])
        assert np.all(result["confidence"] < model.synthesize(filtered, ("mesh",))["confidence"])


def test_training_job_on_the_redis_queue(deployment, redis_server, start_worker):
    settings = deployment.settings.model_copy(update={
        "queue_url": redis_server, "queue_name": f"facesynth_test_{secrets.token_hex(4)}"})
    queue = get_queue(settings)
    try:
        model, job = deployment.create_model()
        start_worker(settings)
        submit(settings, job.id)
        job = deployment.wait(job.id, timeout=120)
        assert (job.status, job.progress, job.error) == ("succeeded", 1.0, None)
        assert deployment.model(model.id).status == "ready"
        # the message travelled as JSON, under this run's own keys
        keys = queue.huey.storage.conn.keys(f"huey.*{settings.queue_name}*")
        assert all(settings.queue_name in key.decode() for key in keys)
    finally:
        queue.huey.storage.flush_all()
        conn = queue.huey.storage.conn
        for key in conn.scan_iter(f"huey.*{settings.queue_name}*"):
            conn.delete(key)
        assert not list(conn.scan_iter(f"*{settings.queue_name}*"))


@pytest.fixture
def gated_training(monkeypatch):
    """Make ``pdm`` training stop at its first progress point until ``proceed`` is set."""
    kind = kinds.KINDS["pdm"]
    started, proceed = threading.Event(), threading.Event()

    def train(actor, clips, params, progress):
        def gated(fraction, stage):
            if not started.is_set():
                started.set()
                assert proceed.wait(30), "the test never let training proceed"
            progress(fraction, stage)
        return kind.train(actor, clips, params, gated)

    monkeypatch.setitem(kinds.KINDS, "pdm", dataclasses.replace(kind, train=train))
    yield started, proceed
    proceed.set()


def test_cancelling_a_running_training_job_stops_it_at_the_next_progress_point(
        deployment, start_worker, gated_training):
    started, proceed = gated_training
    model, job = deployment.create_model()
    start_worker(deployment.settings)
    submit(deployment.settings, job.id)
    assert started.wait(30)
    with deployment.session() as session:
        flagged = registry.request_cancel(session, job.id)
    assert (flagged.status, flagged.cancel_requested) == ("running", True)
    proceed.set()
    job = deployment.wait(job.id)
    assert job.status == "cancelled" and job.error["code"] == "cancelled"
    assert job.progress < 0.1 and job.stage == "alignment"  # the method's first progress point
    model = deployment.model(model.id)
    assert model.status == "failed" and model.blob is None


def test_a_stopping_worker_gives_a_running_job_back(deployment, start_worker, gated_training):
    started, proceed = gated_training
    model, job = deployment.create_model()
    handle = start_worker(deployment.settings, grace_seconds=0.2)
    submit(deployment.settings, job.id)
    assert started.wait(30)
    stopper = threading.Thread(target=handle.stop)
    stopper.start()
    get_queue(deployment.settings).abandon.wait(10)  # the grace period ran out
    proceed.set()
    stopper.join(30)
    assert not handle.running
    released = deployment.job(job.id)
    assert released.status == "running" and released.lease_expires_at <= utcnow()
    assert reap_and_resubmit(deployment.settings) == [job.id]
    assert deployment.job(job.id).status == "queued" and deployment.model(model.id).status == "training"
    with deployment.session() as session:  # not trained again here: cancel the requeued job
        assert registry.request_cancel(session, job.id).status == "cancelled"
    assert deployment.model(model.id).status == "failed"


def test_a_job_whose_worker_died_is_reaped_and_completed_by_a_live_worker(
        deployment, trained, start_worker, pdm_actor_dir):
    model_id, _ = trained
    job_id = deployment.create_synthesis_job(model_id, _markers(pdm_actor_dir, 4))
    ghost = "ghost-host:4242:Worker-1"
    with deployment.session() as session:  # a worker claimed it, then died a minute ago
        claimed = registry.claim_job(session, ghost, lease_seconds=1.0, max_retries=2,
                                     job_id=job_id, now=utcnow() - timedelta(seconds=60))
    assert claimed.status == "running" and claimed.lease_expires_at < utcnow()
    start_worker(deployment.settings)  # no message: the reaper finds it
    job = deployment.wait(job_id)
    assert job.status == "succeeded" and job.attempts == 2
    assert job.worker != ghost and len(job.result["artifact_ids"]) == 1


def test_training_on_a_clip_with_the_wrong_marker_count_fails_with_invalid_input(
        deployment, uploads, start_worker):
    _, _, clips = uploads
    with np.load(io.BytesIO(clips["train_smile"])) as d:
        short = actor_store.clip_npz(d["vertices"], d["markers"][:, :149], fps=float(d["fps"]))
    clip_id = deployment.add_clip("short_markers", short)
    model, job = deployment.create_model([deployment.clip_ids[0], clip_id])
    start_worker(deployment.settings)
    submit(deployment.settings, job.id)
    job = deployment.wait(job.id)
    assert job.status == "failed" and job.error["code"] == "invalid_input"
    assert "clip 'short_markers': markers must be (F,150,3), got (20, 149, 3)" in job.error["message"]
    model = deployment.model(model.id)
    assert model.status == "failed" and model.error == job.error


def test_synthesis_with_the_wrong_marker_count_fails_with_invalid_input(
        deployment, trained, start_worker, pdm_actor_dir):
    model_id, _ = trained
    job_id = deployment.create_synthesis_job(model_id, _markers(pdm_actor_dir, 2)[:, :140])
    start_worker(deployment.settings)
    submit(deployment.settings, job_id)
    job = deployment.wait(job_id)
    assert job.status == "failed" and job.error == {
        "code": "invalid_input", "message": "frames 0-1: model expects markers (F,150,3), got (2, 140, 3)"}


def test_queued_jobs_whose_message_was_lost_are_resubmitted_when_a_worker_starts(deployment):
    model, job = deployment.create_model()
    with deployment.session() as session:
        assert job.id not in resubmit_stale(deployment.settings)  # too young to be lost
        assert job.id in resubmit_stale(deployment.settings, older_than=0.0)
        # its message now waits in the queue: not submitted again
        assert job.id not in resubmit_stale(deployment.settings, older_than=0.0)
        registry.request_cancel(session, job.id)
    get_queue(deployment.settings).huey.flush()


# -- issue 16, defect 5: lost messages and dead workers, without restarting anything --------
@pytest.fixture
def probe_kind(monkeypatch):
    from service.jobs import tasks

    monkeypatch.setitem(tasks.TASKS, "probe", lambda job: {"ran": job.attempt})


def test_a_job_whose_message_is_lost_runs_within_the_bound_on_a_running_worker(
        deployment, start_worker, probe_kind):
    settings = deployment.settings.model_copy(update={"job_resubmit_seconds": 1.0})
    start_worker(settings)
    with deployment.session() as session:     # committed, never enqueued: the message is lost
        job = registry.create_job(session, "probe", deployment.actor_id)
    finished = deployment.wait(job.id, timeout=1.0 + 5 * settings.job_lease_seconds)
    assert (finished.status, finished.result) == ("succeeded", {"ran": 1})
    assert (finished.started_at - job.created_at).total_seconds() >= 1.0


def test_expired_leases_are_reaped_with_no_worker_alive(deployment, probe_kind):
    from service.jobs.worker import start_maintenance

    with deployment.session() as session:
        job = registry.create_job(session, "probe", deployment.actor_id)
        registry.claim_job(session, "dead-host:1:thread", lease_seconds=0.2, max_retries=2,
                           job_id=job.id)
    maintenance = start_maintenance(deployment.settings)      # what an API process runs
    try:
        requeued = deployment.wait(job.id, timeout=3 * deployment.settings.job_lease_seconds,
                                   until=lambda j: j.status != "running")
    finally:
        maintenance.stop(timeout=10)
    assert (requeued.status, requeued.worker, requeued.attempts) == ("queued", None, 1)
    with deployment.session() as session:
        registry.request_cancel(session, job.id)
    get_queue(deployment.settings).huey.flush()


def test_synthesis_job_writes_per_frame_obj_and_exr_into_a_zip(deployment, trained, start_worker,
                                                               pdm_actor_dir):
    model_id, _ = trained
    markers = _markers(pdm_actor_dir, 3)
    artifact, data, path = _run_synthesis_job(deployment, start_worker, model_id, markers,
                                              outputs=["mesh", "displacement"], format="obj-exr-zip")
    assert artifact.media_type == "application/zip" and artifact.filename.endswith(".zip")
    expected = kinds.get_kind("pdm").load(path).synthesize(markers, ("mesh", "displacement"))
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        assert sorted(z.namelist()) == ["clamped.csv", "confidence.json"] + [
            f"frame_{i:04d}{s}" for i in range(3) for s in (".obj", "_displacement.exr")]
        mesh = read_obj(io.BytesIO(z.read("frame_0002.obj")))
        np.testing.assert_array_equal(mesh.vertices.astype(np.float32), expected["vertices"][2])
        assert mesh.uv_faces is not None and len(mesh.uv_faces) == len(mesh.faces)
        np.testing.assert_array_equal(read_map(z.read("frame_0001_displacement.exr")),
                                      expected["displacement"][1])


def _usd_points(path):
    """(points (F,V,3) float32 at the time samples, faceVertexIndices (T·3,), time codes,
    timeCodesPerSecond) of the cache at ``path``."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    times = mesh.GetPointsAttr().GetTimeSamples()
    points = np.stack([np.asarray(mesh.GetPointsAttr().Get(t)) for t in times])
    return (points, np.asarray(mesh.GetFaceVertexIndicesAttr().Get()), times,
            stage.GetTimeCodesPerSecond())


def _job_with_fps(deployment, model_id, markers, fps, **payload) -> str:
    """A queued synthesis job whose input artifact states ``fps``."""
    buffer = io.BytesIO()
    np.savez(buffer, markers=markers.astype(np.float32), fps=np.float64(fps))
    with deployment.session() as session:
        job = registry.create_job(session, "synthesize", deployment.actor_id, model_id=model_id)
        artifact = registry.add_artifact(session, deployment.store.blobs, job.id,
                                         buffer.getvalue(), media_type="application/x-npz")
        job.payload = {"model_id": model_id, "markers_artifact_id": artifact.id, **payload}
        session.commit()
        return job.id


def _artifact(deployment, job):
    (artifact_id,) = job.result["artifact_ids"]
    with deployment.session() as session:
        artifact, stream = registry.open_artifact(session, deployment.store.blobs, artifact_id)
        with stream:
            return artifact, stream.read()


def test_synthesis_job_writes_a_usd_cache_whose_points_are_the_npz_vertices(
        deployment, trained, start_worker, pdm_actor_dir, tmp_path):
    model_id, _ = trained
    markers = _markers(pdm_actor_dir, 20)           # two chunks of CHUNK_FRAMES = 16
    start_worker(deployment.settings)
    jobs = {fmt: _job_with_fps(deployment, model_id, markers, 24.0, outputs=["mesh"], format=fmt)
            for fmt in ("usd", "npz")}
    for job_id in jobs.values():
        submit(deployment.settings, job_id)
    (usd_artifact, usd), (_, npz) = (_artifact(deployment, deployment.wait(jobs[fmt]))
                                     for fmt in ("usd", "npz"))
    assert (usd_artifact.media_type, usd_artifact.filename) == ("application/octet-stream",
                                                                f"{jobs['usd']}.usd")
    (tmp_path / "take.usd").write_bytes(usd)
    points, corners, times, fps = _usd_points(tmp_path / "take.usd")
    result = npz_arrays(npz)
    assert points.dtype == np.float32 and result["vertices"].dtype == np.float32
    np.testing.assert_array_equal(points, result["vertices"])          # bit-exact
    np.testing.assert_array_equal(corners, result["faces"].ravel())
    assert times == list(map(float, range(20))) and fps == 24.0


def test_cancelling_a_usd_job_stops_it_at_the_next_chunk(deployment, trained, pdm_actor_dir,
                                                        monkeypatch):
    import importlib

    from service.jobs import runner

    task = importlib.import_module("service.jobs.tasks.synthesize")  # the module, not the task

    model_id, _ = trained
    job_id = deployment.create_synthesis_job(model_id, _markers(pdm_actor_dir, 6),
                                             outputs=["mesh"], format="usd")
    chunks = []

    class CancelAfterOneChunk(task.FrameUsdWriter):
        def write(self, start, arrays):
            super().write(start, arrays)
            chunks.append(start)
            with deployment.session() as session:
                registry.request_cancel(session, job_id)

    monkeypatch.setattr(task, "FrameUsdWriter", CancelAfterOneChunk)
    monkeypatch.setattr(task, "CHUNK_FRAMES", 2)
    monkeypatch.setattr(runner, "PROGRESS_INTERVAL", 0.0)   # every progress point is written
    assert runner.execute(deployment.settings, job_id, "test-host:1:MainThread") == "cancelled"
    job = deployment.job(job_id)
    assert chunks == [0] and job.status == "cancelled" and job.result is None
    assert job.progress == pytest.approx(task.LOADED + (task.SYNTHESIZED - task.LOADED) * 2 / 6)

"""service.jobs.runner.execute without a queue: claiming, progress, cancellation, leases,
and how a task's ending becomes the job's state."""

from __future__ import annotations

import time

import pytest
from sqlalchemy import update

from models_store import registry
from models_store.schema import Job, utcnow
from service.jobs import runner, tasks
from service.methods.inputs import InvalidInput

WORKER = "test-host:1:MainThread"


@pytest.fixture
def probe(deployment, monkeypatch):
    """``probe(task)``: a queued job of kind ``probe`` that runs ``task(job)``; its id."""

    def make(task) -> str:
        monkeypatch.setitem(tasks.TASKS, "probe", task)
        with deployment.session() as session:
            return registry.create_job(session, "probe", deployment.actor_id,
                                       payload={"n": 3}).id

    return make


def test_a_task_result_becomes_the_succeeded_jobs_result(deployment, probe):
    seen = {}

    def task(job):
        seen.update(payload=job.payload, attempt=job.attempt, kind=job.kind)
        job.progress(0.5, "half")
        return {"artifact_ids": []}

    job_id = probe(task)
    assert runner.execute(deployment.settings, job_id, WORKER) == "succeeded"
    job = deployment.job(job_id)
    assert (job.status, job.progress, job.stage, job.result) == ("succeeded", 1.0, "half",
                                                                 {"artifact_ids": []})
    assert seen == {"payload": {"n": 3}, "attempt": 1, "kind": "probe"}
    # a second message for the same job is a no-op
    assert runner.execute(deployment.settings, job_id, WORKER) is None


def test_unclaimable_and_unknown_jobs_are_skipped(deployment):
    assert runner.execute(deployment.settings, "job_01m84g72zv56qgast3a85c8cy8", WORKER) is None
    assert runner.execute(deployment.settings, "not-a-job-id", WORKER) is None


@pytest.mark.parametrize("error, code, message", [
    (InvalidInput("clip 'x' frame 3 has NaN"), "invalid_input", "clip 'x' frame 3 has NaN"),
    (RuntimeError("disk on fire"), "internal", "RuntimeError: disk on fire"),
    # issue 16, defect 4: storage errors get their own codes and never show server paths
    (OSError(28, "No space left on device", "/srv/data/blobs/.synthesize-x/vertices.npy"),
     "insufficient_storage", "the server's storage is full (No space left on device); the "
                             "job can be submitted again once space is freed"),
    (OSError(122, "Disk quota exceeded", "/srv/data/blobs/a"),
     "insufficient_storage", "the server's storage is full (Disk quota exceeded); the "
                             "job can be submitted again once space is freed"),
    (OSError(30, "Read-only file system", "/srv/data/blobs/a"),
     "storage_unavailable", "the server's storage cannot be written (Read-only file system); "
                            "the job can be submitted again once it is writable"),
    (PermissionError(13, "Permission denied", "/srv/data/blobs/a"),
     "storage_unavailable", "the server's storage cannot be written (Permission denied); "
                            "the job can be submitted again once it is writable"),
])
def test_task_errors_become_the_jobs_error(deployment, probe, error, code, message):
    def task(job):
        raise error

    job_id = probe(task)
    assert runner.execute(deployment.settings, job_id, WORKER) == "failed"
    assert deployment.job(job_id).error == {"code": code, "message": message}


def test_a_job_kind_without_a_task_fails_with_a_reason(deployment):
    with deployment.session() as session:
        job_id = registry.create_job(session, "teleport", deployment.actor_id).id
    assert runner.execute(deployment.settings, job_id, WORKER) == "failed"
    error = deployment.job(job_id).error
    assert error["code"] == "unsupported_job_kind" and "'teleport'" in error["message"]


def test_progress_is_throttled_and_cancellation_takes_effect_at_a_progress_point(
        deployment, probe, monkeypatch):
    writes = []
    real = registry.update_job_progress
    monkeypatch.setattr(registry, "update_job_progress",
                        lambda *a, **k: writes.append(a[2:4]) or real(*a, **k))
    reached = []

    def task(job):
        for i in range(50):               # same stage, quickly: one write
            job.progress(0.01 * i, "loading")
        job.progress(0.6, "fitting")      # a new stage: written at once
        assert deployment.job(job.id).progress == 0.6
        with deployment.session() as session:
            registry.request_cancel(session, job.id)
        reached.append("before")
        job.progress(0.7, "fitting more")  # the next progress point sees the request
        reached.append("after")
        return {}

    job_id = probe(task)
    assert runner.execute(deployment.settings, job_id, WORKER) == "cancelled"
    assert writes[:2] == [(0.0, "loading"), (0.6, "fitting")] and len(writes) == 3
    assert reached == ["before"]
    job = deployment.job(job_id)
    assert job.status == "cancelled" and job.progress == 0.7


def test_heartbeats_keep_the_lease_of_a_long_task(deployment, probe):
    settings = deployment.settings.model_copy(update={"job_lease_seconds": 0.6})
    leases = []

    def task(job):
        for _ in range(5):  # five lease periods without a progress point
            time.sleep(0.6)
            with deployment.session() as session:
                assert registry.reap_expired(session, 2).requeued == []
            leases.append(deployment.job(job.id).lease_expires_at)
        return {}

    job_id = probe(task)
    assert runner.execute(settings, job_id, WORKER) == "succeeded"
    assert all(lease > earlier for earlier, lease in zip(leases, leases[1:]))


def test_a_worker_that_lost_its_lease_stops_quietly(deployment, probe):
    def task(job):
        with deployment.session() as session:  # presumed dead: another worker took over
            session.execute(update(Job).where(Job.id == job.id).values(worker="successor"))
            session.commit()
        job.progress(0.5, "next stage")
        raise AssertionError("not reached")

    job_id = probe(task)
    assert runner.execute(deployment.settings, job_id, WORKER) is None
    job = deployment.job(job_id)
    assert (job.status, job.worker, job.error) == ("running", "successor", None)
    with deployment.session() as session:
        session.execute(update(Job).where(Job.id == job_id).values(status="cancelled",
                                                                   finished_at=utcnow()))
        session.commit()

"""Fault injection on a real multi-process deployment (issue 16): API + workers over
PostgreSQL and Redis, processes SIGKILLed at the worst moments, lost queue messages, no
worker alive, concurrent writes, a full and a read-only data disk, two tenants.

Every wait is bounded (a few lease periods at most); the small filesystems are tmpfs mounts
the tests make and remove (:mod:`tests.filesystems`; skipped with the reason where mounting
is impossible); only loopback is used. The sample actor is the level-0 one with 64² maps (two
training clips and the held-out performance), so a training takes seconds.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Iterator

import httpx
import numpy as np
import pytest

from models_store import registry
from models_store.fsck import fsck
from service.samples.uploads import sample_actor_uploads
from service.io.npz import npz_arrays, npz_bytes
from tests.e2e.conftest import FAULT_CLIPS, LEASE_SECONDS, Deployment, running_deployment
from tests.servers import postgres_server, redis_server  # noqa: F401

pytestmark = pytest.mark.e2e

NPZ = {"Content-Type": "application/x-npz"}
CLIPS = FAULT_CLIPS
PARAMS = {"order": "biquadratic", "medium_resolution": 64, "fine_resolution": 64}
FINAL = ("succeeded", "failed", "cancelled")
#: maintenance and hygiene made fast, so the bounds below are short
ENV = {"FACESYNTH_JOB_RESUBMIT_SECONDS": "3", "FACESYNTH_MAINTENANCE_INTERVAL_SECONDS": "1",
       "FACESYNTH_STALE_TEMPORARY_SECONDS": "4", "FACESYNTH_TEMPORARY_SWEEP_SECONDS": "2"}
#: a job whose worker died is requeued by then (lease + maintenance rounds + slack)
REAP_BOUND = LEASE_SECONDS + 6
#: a queued job whose message was lost runs by then
RESUBMIT_BOUND = 3 + 6


@pytest.fixture(scope="module")
def deployment(tmp_path_factory, postgres_server, redis_server) -> Iterator[Deployment]:  # noqa: F811
    with running_deployment(tmp_path_factory.mktemp("e2e_faults"), postgres_server,
                            redis_server, env=ENV) as deployment:
        yield deployment


@pytest.fixture(scope="module")
def state() -> dict:
    return {}


def ok(response: httpx.Response, status: int = 200) -> dict:
    assert response.status_code == status, f"{response.request.method} {response.request.url}: " \
                                           f"{response.status_code} {response.text[:2000]}"
    kind = response.headers.get("content-type", "")
    return response.json() if kind.startswith(("application/json",
                                               "application/problem+json")) else {}


def wait_job(client: httpx.Client, job_id: str, timeout: float,
             until=lambda job: job["status"] in FINAL, interval: float = 0.1) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        job = ok(client.get(f"/v1/jobs/{job_id}"))
        if until(job):
            return job
        assert time.monotonic() < deadline, f"job {job_id} still {job['status']} " \
                                            f"({job['stage']!r}, {job['progress']:.2f}) after {timeout} s"
        time.sleep(interval)


def job_row(deployment: Deployment, job_id: str):
    sessions = deployment.sessions()
    try:
        with sessions() as session:
            return registry.get_job(session, job_id)
    finally:
        sessions.kw["bind"].dispose()


def store_report(deployment: Deployment, remove: bool = False):
    sessions = deployment.sessions()
    try:
        with sessions() as session:
            return fsck(session, deployment.blobs(), remove=remove, min_age=0.0)
    finally:
        sessions.kw["bind"].dispose()


def hidden_files(deployment: Deployment) -> list[str]:
    root = deployment.blobs().root
    return sorted(p.relative_to(root).as_posix() for p in root.rglob(".*"))


def kill_worker_of(deployment: Deployment, job_id: str) -> None:
    """SIGKILL the worker process that holds ``job_id`` and start a replacement."""
    row = job_row(deployment, job_id)
    pid = int(row.worker.split(":")[1])
    victim = deployment.worker_by_pid(pid)
    os.kill(victim.pid, signal.SIGKILL)
    assert victim.popen.wait(10) == -signal.SIGKILL
    deployment.workers.remove(victim)


def markers_of(actor_dir: Path, repeat: int = 1) -> np.ndarray:
    with np.load(actor_dir / "performances" / "heldout_in_range.npz") as d:
        markers = d["markers"].astype(np.float32)
    return np.concatenate([markers] * repeat)


# ---------------------------------------------------------------------------- tests
def test_setup_actor_and_an_uninterrupted_model(deployment, actor_dir, state):
    neutral, layout, clips = sample_actor_uploads(actor_dir, CLIPS)
    canonical = json.loads(layout)
    body = {"markers": [{"name": n, "triangle": t, "barycentric": b} for n, t, b in
                        zip(canonical["names"], canonical["triangle"], canonical["barycentric"])]}
    with deployment.client() as client:
        actor_id = ok(client.post("/v1/actors", json={"name": "faults"}), 201)["id"]
        ok(client.put(f"/v1/actors/{actor_id}/neutral", content=neutral, headers=NPZ))
        ok(client.put(f"/v1/actors/{actor_id}/markers", json=body))
        clip_ids = [ok(client.post(f"/v1/actors/{actor_id}/clips", content=clips[name],
                                   headers=NPZ, params={"name": name}), 201)["clip_id"]
                    for name in CLIPS]
        accepted = ok(client.post(f"/v1/actors/{actor_id}/models",
                                  json={"kind": "pdm", "clips": clip_ids, "params": PARAMS}), 202)
        job = wait_job(client, accepted["job_id"], timeout=180)
        assert job["status"] == "succeeded", job
    state.update(actor_id=actor_id, clip_ids=clip_ids, model_id=accepted["model_id"],
                 neutral=neutral, markers_body=body, clips=clips)


def _needs(state, *keys):
    if any(k not in state for k in keys):
        pytest.skip("needs the actor and model of test_setup_actor_and_an_uninterrupted_model")


def test_a_worker_killed_mid_training_changes_nothing_in_the_model(deployment, actor_dir, state):
    _needs(state, "model_id")
    with deployment.client() as client:
        accepted = ok(client.post(f"/v1/actors/{state['actor_id']}/models",
                                  json={"kind": "pdm", "clips": state["clip_ids"],
                                        "params": PARAMS}), 202)
        job_id = accepted["job_id"]
        wait_job(client, job_id, timeout=60, interval=0.05,
                 until=lambda j: j["status"] == "running" and j["progress"] > 0.05)
        kill_worker_of(deployment, job_id)
        deployment.start_worker()
        job = wait_job(client, job_id, timeout=REAP_BOUND + 180)
        assert job["status"] == "succeeded", job
        assert job_row(deployment, job_id).attempts == 2
        markers = markers_of(actor_dir)[::10]
        outputs = {"outputs": "mesh,displacement,normal_map"}
        first = npz_arrays(client.post(f"/v1/models/{state['model_id']}/synthesize",
                                       content=npz_bytes(markers=markers), headers=NPZ,
                                       params=outputs).content)
        again = npz_arrays(client.post(f"/v1/models/{accepted['model_id']}/synthesize",
                                       content=npz_bytes(markers=markers), headers=NPZ,
                                       params=outputs).content)
    for key in ("vertices", "displacement", "normal_map", "faces"):
        np.testing.assert_array_equal(again[key], first[key], err_msg=key)   # bit-identical
    assert hidden_files(deployment) == [] or _swept(deployment)


def _swept(deployment: Deployment, timeout: float = 15.0) -> bool:
    """Whether the temporaries disappear within ``timeout`` s (the sweep's period + age)."""
    deadline = time.monotonic() + timeout
    while hidden_files(deployment):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.5)
    return True


def _synthesis_job(client, state, markers) -> str:
    return ok(client.post(f"/v1/models/{state['model_id']}/synthesis-jobs",
                          content=npz_bytes(markers=markers), headers=NPZ,
                          params={"outputs": "mesh,displacement,normal_map"}), 202)["job_id"]


def _artifact_arrays(client, job: dict) -> dict:
    (artifact_id,) = job["result"]["artifact_ids"]
    response = client.get(f"/v1/artifacts/{artifact_id}")
    assert response.status_code == 200
    return npz_arrays(response.content)


def test_a_worker_killed_mid_synthesis_gives_the_same_artifact(deployment, actor_dir, state):
    _needs(state, "model_id")
    markers = markers_of(actor_dir, repeat=2)
    with deployment.client() as client:
        reference = wait_job(client, _synthesis_job(client, state, markers), timeout=180)
        assert reference["status"] == "succeeded", reference
        job_id = _synthesis_job(client, state, markers)
        wait_job(client, job_id, timeout=60, interval=0.02,
                 until=lambda j: j["status"] == "running" and j["stage"] == "synthesizing")
        kill_worker_of(deployment, job_id)
        deployment.start_worker()
        job = wait_job(client, job_id, timeout=REAP_BOUND + 180)
        assert job["status"] == "succeeded", job
        assert job_row(deployment, job_id).attempts == 2
        expected, got = _artifact_arrays(client, reference), _artifact_arrays(client, job)
    assert sorted(got) == sorted(expected)
    for key in expected:
        np.testing.assert_array_equal(got[key], expected[key], err_msg=key)
    assert _swept(deployment), hidden_files(deployment)   # the killed job's scratch directory


def test_a_job_whose_queue_message_was_lost_runs_within_the_bound(deployment, actor_dir, state):
    _needs(state, "model_id")
    with deployment.client() as client:
        template = job_row(deployment, _synthesis_job(client, state, markers_of(actor_dir)[:4]))
        # the API died between committing a job and enqueuing it: a row, no message
        sessions = deployment.sessions()
        try:
            with sessions() as session:
                lost = registry.create_job(session, "synthesize", state["actor_id"],
                                           model_id=state["model_id"], payload=template.payload)
        finally:
            sessions.kw["bind"].dispose()
        job = wait_job(client, lost.id, timeout=RESUBMIT_BOUND + 30)
        assert job["status"] == "succeeded", job
        waited = job_row(deployment, lost.id).started_at - lost.created_at
        assert 3 <= waited.total_seconds() <= RESUBMIT_BOUND, waited


def test_with_every_worker_dead_the_lease_is_reaped_and_the_job_later_runs(
        deployment, actor_dir, state):
    _needs(state, "model_id")
    with deployment.client() as client:
        job_id = _synthesis_job(client, state, markers_of(actor_dir, repeat=2))
        wait_job(client, job_id, timeout=60, interval=0.02,
                 until=lambda j: j["status"] == "running")
        for worker in list(deployment.workers):
            os.kill(worker.pid, signal.SIGKILL)
            worker.popen.wait(10)
            deployment.workers.remove(worker)
        # the API's maintenance reaps the expired lease: the job does not stay "running"
        requeued = wait_job(client, job_id, timeout=REAP_BOUND,
                            until=lambda j: j["status"] != "running")
        assert requeued["status"] == "queued", requeued
        deployment.start_worker()
        deployment.start_worker()
        job = wait_job(client, job_id, timeout=RESUBMIT_BOUND + 120)
        assert job["status"] == "succeeded", job


def test_concurrent_neutral_and_marker_puts_leave_no_orphans(deployment, state):
    _needs(state, "neutral")
    with deployment.client() as client:
        actor_id = ok(client.post("/v1/actors", json={"name": "concurrent"}), 201)["id"]
        ok(client.put(f"/v1/actors/{actor_id}/neutral", content=state["neutral"], headers=NPZ))
    barrier = threading.Barrier(16)
    statuses: list[int] = []

    def put(i: int) -> None:
        with deployment.client() as own:
            barrier.wait()
            if i % 2:
                statuses.append(own.put(f"/v1/actors/{actor_id}/neutral", content=state["neutral"],
                                        headers=NPZ).status_code)
            else:
                statuses.append(own.put(f"/v1/actors/{actor_id}/markers",
                                        json=state["markers_body"]).status_code)

    threads = [threading.Thread(target=put, args=(i,)) for i in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert statuses == [200] * 16
    report = store_report(deployment)
    assert report.orphans == [] and report.missing == [], report


SLOW_UPLOAD_CHUNK = 1 << 16


def test_an_api_killed_mid_upload_loses_no_acknowledged_write_and_leaves_no_partial_blob(
        deployment, state):
    _needs(state, "clips")
    body = state["clips"][CLIPS[0]]
    with deployment.client() as client:
        acknowledged = ok(client.post(f"/v1/actors/{state['actor_id']}/clips", content=body,
                                      headers=NPZ, params={"name": "before-kill"}), 201)
    sent = threading.Event()

    def slowly() -> Iterator[bytes]:
        for start in range(0, len(body), SLOW_UPLOAD_CHUNK):
            yield body[start:start + SLOW_UPLOAD_CHUNK]
            if start > len(body) // 2:
                sent.set()
                time.sleep(0.2)

    outcome: list[object] = []

    def upload() -> None:
        try:
            with deployment.client(timeout=30) as own:
                outcome.append(own.post(f"/v1/actors/{state['actor_id']}/clips", content=slowly(),
                                        headers={**NPZ, "Content-Length": str(len(body))},
                                        params={"name": "killed"}).status_code)
        except httpx.HTTPError as error:
            outcome.append(error)

    thread = threading.Thread(target=upload)
    thread.start()
    assert sent.wait(30)
    os.kill(deployment.api.pid, signal.SIGKILL)
    deployment.api.popen.wait(10)
    thread.join(30)
    assert outcome and isinstance(outcome[0], httpx.HTTPError), outcome
    deployment.start_api()
    with deployment.client() as client:
        clips = ok(client.get(f"/v1/actors/{state['actor_id']}/clips"))["items"]
    names = [c["name"] for c in clips]
    assert "before-kill" in names and "killed" not in names
    assert acknowledged["clip_id"] in [c["clip_id"] for c in clips]
    assert _swept(deployment), hidden_files(deployment)
    report = store_report(deployment)
    assert report.orphans == [] and report.missing == [], report

"""service.jobs.tasks.track: a tracking job end to end through the HTTP route and an embedded
worker on a tiny synthetic scene (a 14×14-vertex cap, 48² images, 8 frames, 2 scans, 1 view):
the tracked vertices against ground truth, the fan-out of one ``track_span`` job per
in-between span, the parent's result against a single-process ``track()`` on the same stored
input, and cancellation (the span jobs end with their parent)."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from models_store import registry
from service.api.app import create_app
from service.config import Settings
from service.io.npz import npz_bytes
from service.jobs.queue import close_queues
from service.jobs.tasks.track import SPAN_JOB, load_input, span_jobs
from service.methods.tracking.params import TrackingParams
from service.methods.tracking.track import spans, track
from service.samples.tracking_scene import build_tracking_scene, tracking_uploads
from service.store.container import close_stores, get_store
from tests.jobs.conftest import FINAL, LEASE_SECONDS

#: parameters of the scene's jobs: candidates every 2nd frame and a steeper hat (8 frames
#: are few: at the paper's 4 % the neutral's first-frame edge suppresses every other
#: candidate), so the graph keeps 4 keyframes and 2 in-between spans
PARAMS = {"candidate_stride": 2, "hat_slope": 0.3}


@pytest.fixture(scope="module")
def scene():
    return build_tracking_scene(frames=8, views=1, size=48)


@pytest.fixture(scope="module")
def server(tmp_path_factory, scene):
    """A client of an app on a SQLite deployment (real queue) and an actor whose neutral is
    the scene's artist mesh."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("track"), job_lease_seconds=LEASE_SECONDS,
                        job_max_retries=2, tokens=[])
    with TestClient(create_app(settings)) as client:
        actor = client.post("/v1/actors", json={"name": "cap"}).json()["id"]
        response = client.put(f"/v1/actors/{actor}/neutral", headers={"Content-Type": "application/x-npz"},
                              content=npz_bytes(vertices=scene.artist_vertices, faces=scene.faces,
                                                uv=scene.uv))
        assert response.status_code == 200, response.text
        yield settings, client, actor
    close_queues()
    close_stores()


def submit(client, actor, scene, params=PARAMS, **query) -> str:
    import json

    response = client.post(f"/v1/actors/{actor}/tracking-jobs", files=tracking_uploads(scene),
                           data={"params": json.dumps(params)}, params=query)
    assert response.status_code == 202, response.text
    assert response.headers["location"] == f"/v1/jobs/{response.json()['job_id']}"
    return response.json()["job_id"]


def wait(client, job_id, timeout=120.0, until=lambda job: job["status"] in FINAL):
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if until(job):
            return job
        assert time.monotonic() < deadline, f"job {job_id}: {job}"
        time.sleep(0.02)


def artifact(client, job, name) -> dict:
    data = client.get(f"/v1/artifacts/{job['result']['artifacts'][name]}").content
    with np.load(io.BytesIO(data)) as d:
        return {k: d[k] for k in d.files}


def test_a_tracking_job_fans_out_one_job_per_span_and_equals_track(server, scene, start_worker):
    settings, client, actor = server
    job_id = submit(client, actor, scene, map_resolution=32)
    start_worker(settings, workers=2)
    stages = []
    job = wait(client, job_id, until=lambda j: stages.append(j["stage"]) or j["status"] in FINAL)
    assert job["status"] == "succeeded", job
    assert job["kind"] == "track" and job["progress"] == 1.0
    assert "tween solve" in stages          # polled: a short stage may pass unseen
    store = get_store(settings)
    with store.sessions() as session:
        row = registry.get_job(session, job_id)
        children = span_jobs(session, row)
        payload = dict(row.payload)
    tracked = artifact(client, job, "tracked.npz")
    keyframes = tracked["keyframes"].tolist()
    # one child job per in-between span, each succeeded, named in the result
    assert len(children) == len(spans(keyframes)) >= 2
    assert {c.kind for c in children} == {SPAN_JOB}
    assert all(c.status == "succeeded" for c in children)
    assert sorted((c.payload["a"], c.payload["b"]) for c in children) == spans(keyframes)
    assert set(job["result"]["span_job_ids"]) == {c.id for c in children}

    # the same as one process running track() on the job's stored input: bit-identical
    inp, _ = load_input(store, payload)
    reference = track(inp, TrackingParams(**PARAMS))
    assert reference.keyframes == keyframes
    np.testing.assert_array_equal(tracked["vertices"], reference.vertices)
    np.testing.assert_array_equal(tracked["rotations"], reference.rotations)

    # against the ground truth: measured 0.49 mm at frame 0, a mean 0.46× the untracked
    # error over frames 1-7, at most 1.36 mm. (With the per-scan voting, frame 0 has an edge
    # to scan 1 besides the neutral's and shares scan 1's registration error, 0.36 mm; with
    # the old all-scan suppression frame 0 had the neutral's edge alone and measured 0.17
    # mm, but the mean was 0.49×, the max 1.50 mm and scan 1 was 0.70 mm off.)
    err = np.linalg.norm(tracked["vertices"] - scene.frame_truth, axis=2).mean(axis=1)
    still = np.linalg.norm(scene.artist_vertices[None] - scene.frame_truth, axis=2).mean(axis=1)
    assert err[0] < 0.6
    assert err[1:].mean() < 0.65 * still[1:].mean(), (err, still)
    assert err.max() < 1.8

    weights = artifact(client, job, "weights.npz")["weights"]
    assert weights.shape == (8, len(scene.artist_vertices), 2)
    np.testing.assert_allclose(weights.sum(axis=2), 1.0, atol=1e-5)
    maps = artifact(client, job, "maps.npz")
    assert maps["reflectance"].shape == (8, 32, 32)
    assert 0.2 < float(maps["reflectance"][0][maps["reflectance"][0] > 0].mean()) < 0.9
    scans = artifact(client, job, "scans.npz")
    assert scans["registered"][0] and scans["vertices"].shape == (2, len(scene.artist_vertices), 3)
    # the registered neutral scan is the artist mesh (the ground, eq. 12)
    np.testing.assert_allclose(scans["vertices"][0], scene.artist_vertices, atol=1e-4)
    # scan 1 registered to the artist topology (Fig. 11): measured 0.36 mm from its truth
    assert np.linalg.norm(scans["vertices"][1] - scene.scan_truth[1], axis=1).mean() < 0.5


def test_cancelling_a_tracking_job_cancels_its_span_jobs(server, scene, start_worker):
    settings, client, actor = server
    job_id = submit(client, actor, scene)
    start_worker(settings, workers=1)
    wait(client, job_id, until=lambda j: j["stage"] == "tween solve" or j["status"] in FINAL)
    response = client.delete(f"/v1/jobs/{job_id}")
    assert response.status_code in (200, 202)
    job = wait(client, job_id)
    assert job["status"] == "cancelled", job
    store = get_store(settings)
    with store.sessions() as session:
        children = span_jobs(session, registry.get_job(session, job_id))
    assert children
    deadline = time.monotonic() + 30
    while any(c.status not in FINAL for c in children) and time.monotonic() < deadline:
        time.sleep(0.05)
        with store.sessions() as session:
            children = span_jobs(session, registry.get_job(session, job_id))
    assert all(c.status in FINAL for c in children), [c.status for c in children]
    assert any(c.status == "cancelled" for c in children)


def test_park_job_requeues_without_an_attempt_and_honours_a_cancellation(server):
    settings, client, actor = server
    store = get_store(settings)
    with store.sessions() as session:
        job = registry.create_job(session, "track", actor, payload={})
        registry.claim_job(session, "w1", lease_seconds=5, max_retries=2, job_id=job.id)
        registry.update_job_progress(session, job.id, 0.6, "tween solve", worker="w1")
        parked = registry.park_job(session, job.id, worker="w1")
        assert (parked.status, parked.attempts, parked.progress, parked.stage) == (
            "queued", 0, 0.6, "tween solve")
        assert parked.worker is None and parked.lease_expires_at is None
        registry.claim_job(session, "w2", lease_seconds=5, max_retries=2, job_id=job.id)
        registry.request_cancel(session, job.id)          # flagged while it runs
        assert registry.park_job(session, job.id, worker="w2").status == "cancelled"

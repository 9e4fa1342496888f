"""End to end, as deployed: the API, two workers, PostgreSQL and Redis as separate processes.

The tests run in order on one deployment (:func:`tests.e2e.conftest.deployment`):

1. the level-1 sample actor is uploaded over HTTP, a PDM is trained through the API (job
   progress followed over SSE and by polling) and synthesizes held-out frames whose medium
   vertex error against the ground truth is bounded and clearly below a no-detail thin shell;
2. a ``shape_space`` model is trained on the same clips while the actor's input rig is
   registered (both jobs at once, one per worker); held-out frames given as the rig's
   low-resolution meshes are enhanced (``rig=``) with a bounded vertex error that recovers
   most of the ground truth's detail, and two clip frames are retimed;
3. a second training's worker is SIGKILLed mid-job: the job still ends (the other worker
   retries it after the lease expires, or it fails with a reason) and the store holds nothing
   half-written — no job running, no model training, every blob verifies its sha256;
4. the API is restarted (SIGTERM, then started again on the same ports): actors, clips,
   models and jobs read back identical, and the models synthesize (and enhance, through the
   registered rig) bit-identical meshes.

Later tests need the model of the first one and are skipped if it failed.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import time

import httpx
import numpy as np
import pytest

from models_store import registry
from service.samples.uploads import sample_actor_uploads
from service.samples import dataset, performances
from service.io.npz import npz_arrays as load_npz, npz_bytes as npz  # noqa: F401 (used by the tests)
from tests.e2e.conftest import HELDOUT, MAP_RESOLUTION, Deployment

pytestmark = pytest.mark.e2e

NPZ = {"Content-Type": "application/x-npz"}
TRAINING = tuple(f"train_{name}" for name in performances.TRAINING_EXPRESSIONS)
#: reduced resolutions (the paper's are 512 / 1024): ~35 s of training on one core
PARAMS = {"order": "biquadratic", "medium_resolution": 128, "fine_resolution": MAP_RESOLUTION}
#: held-out in-range frames synthesized: strong, varied expressions (smile, brows raised,
#: furrow + squint, smile + brows, sneer, chin raise)
FRAMES = (20, 40, 60, 95, 120, 140)
#: bounds of the medium vertex error |V - V_gt| (mm, face-region vertices, pooled over
#: FRAMES). Measured: PDM mean 0.255, p95 0.903; the no-detail thin shell mean 0.331, p95
#: 1.262 (benchmarks/pdm_report.md, 512²/1024² maps over 31 frames of this performance:
#: 0.191 and 0.247). The bounds leave ~15 % for numerical differences and still fail a
#: model that does not beat the no-detail baseline.
MEDIUM_MEAN_BOUND_MM = 0.30
MEDIUM_P95_BOUND_MM = 1.05
#: the PDM must remove at least this fraction of the no-detail mean error (measured 23 %)
MIN_IMPROVEMENT = 0.15
#: shape_space training: smoothing on the rest pose (one factorization) and every 4th frame
#: of the 8 clips (40 database frames). Measured on 2 cores: ~35 s of training, ~35 s for the
#: rig's registration (ICP, no landmarks), 0.6 s per enhanced frame.
SHAPE_SPACE_PARAMS = {"smoothing": "rest", "frame_stride": 4}
#: the input rig's name
RIG = "ict"
#: ground-truth vertices farther than this from the medium surface carry detail, mm
DETAIL_MM = 0.05
#: bounds of the shape_space vertex error |V - V_gt| of the held-out FRAMES given as the rig's
#: ``lowres`` meshes (mm, face-region vertices). Measured: mean 0.0289, p95 0.124 (the
#: propagated rig mesh alone: mean 0.0126; the enhancement's small low-frequency drift
#: outweighs the detail it adds in the whole-face mean, where detail-free skin dominates).
#: Where the ground truth has detail (~1 % of the face's vertex-frames) the error is 0.061
#: against 0.135 for the ground-truth medium surface without detail: the bounds leave ~20 %.
SHAPE_SPACE_MEAN_BOUND_MM = 0.035
SHAPE_SPACE_P95_BOUND_MM = 0.15
#: the enhancement must remove at least this fraction of the no-detail error where the
#: ground truth has detail (measured 55 %)
MIN_DETAIL_RECOVERED = 0.4
#: agreement of a shape_space enhancement before and after an API restart, mm
SHAPE_SPACE_RESTART_ATOL_MM = 1e-5
FINAL = ("succeeded", "failed", "cancelled")
ACTIVE = ("queued", "running")


# ---------------------------------------------------------------------------- helpers


def ok(response: httpx.Response, status: int = 200) -> dict:
    assert response.status_code == status, f"{response.request.method} {response.request.url}: " \
                                           f"{response.status_code} {response.text[:2000]}"
    return response.json() if response.headers.get("content-type", "").startswith(
        ("application/json", "application/problem+json")) else {}


def wait_job(client: httpx.Client, job_id: str, timeout: float,
             until=lambda job: job["status"] in FINAL, seen: list | None = None) -> dict:
    """Poll ``GET /v1/jobs/{id}`` until ``until(job)``; ``seen`` collects the distinct
    (status, stage) pairs observed."""
    deadline = time.monotonic() + timeout
    while True:
        job = ok(client.get(f"/v1/jobs/{job_id}"))
        if seen is not None and (not seen or seen[-1] != (job["status"], job["stage"])):
            seen.append((job["status"], job["stage"]))
        if until(job):
            return job
        assert time.monotonic() < deadline, f"job {job_id} still {job['status']} " \
                                            f"({job['stage']!r}, {job['progress']:.2f}) after {timeout} s"
        time.sleep(0.25)


def read_events(client: httpx.Client, job_id: str, stages: int = 3,
                timeout: float = 120.0) -> list[tuple[str, dict]]:
    """Server-sent events of a job until ``stages`` distinct running stages were seen, or the
    ``end`` event: [(event name, job)]."""
    events: list[tuple[str, dict]] = []
    deadline = time.monotonic() + timeout
    with client.stream("GET", f"/v1/jobs/{job_id}/events",
                       timeout=httpx.Timeout(10.0, read=30.0)) as response:
        assert response.status_code == 200
        assert response.headers["content-type"].startswith("text/event-stream")
        name, data = None, None
        for line in response.iter_lines():
            if line.startswith("event:"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                data = json.loads(line.split(":", 1)[1])
            elif not line and name is not None:
                events.append((name, data))
                running = {job["stage"] for _, job in events if job["status"] == "running"}
                if name == "end" or len(running) >= stages:
                    break
                name, data = None, None
            assert time.monotonic() < deadline, f"events of {job_id} after {timeout} s: {events}"
    return events


def heldout(actor_dir) -> tuple[np.ndarray, np.ndarray]:
    """Markers (F,M,3) and ground-truth vertices (F,V,3) of the held-out FRAMES."""
    with np.load(actor_dir / "performances" / f"{HELDOUT}.npz") as d:
        frames = list(FRAMES)
        return d["markers"][frames].astype(np.float64), d["vertices"][frames].astype(np.float64)


def heldout_lowres(actor_dir) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The input rig's meshes (F,v,3), the ground-truth vertices (F,V,3) and the
    ground-truth medium surface (F,V,3) of the held-out FRAMES."""
    with np.load(actor_dir / "performances" / f"{HELDOUT}.npz") as d:
        frames = list(FRAMES)
        return (d["lowres"][frames].astype(np.float64), d["vertices"][frames].astype(np.float64),
                d["vertices_medium"][frames].astype(np.float64))


def job_row(deployment: Deployment, job_id: str):
    """The job's database row (``worker`` and ``attempts`` are not part of the API)."""
    sessions = deployment.sessions()
    try:
        with sessions() as session:
            return registry.get_job(session, job_id)
    finally:
        sessions.kw["bind"].dispose()


def worker_pid(worker: str) -> int:
    """The pid in a worker name ``host:pid:thread``."""
    return int(worker.split(":")[1])


def no_detail(deployment: Deployment, model_id: str, actor, markers: np.ndarray) -> np.ndarray:
    """The no-detail baseline of ``benchmarks/pdm_report.py``: the neutral with its own
    vertex-level detail deformed by the linear thin shell that the model's handles drive
    (its head pose and handle displacements), nothing learned from the clips. Here the thin
    shell's basis is the model's stored one (of the smoothed neutral) rather than one
    solved for the detailed neutral, which costs 11 s; the two differ by ~2 % in mean error."""
    from service.methods.kinds import get_kind

    sessions = deployment.sessions()
    try:
        with sessions() as session:
            path = registry.model_dir(session, deployment.blobs(), model_id)  # verifies sha256
        model = get_kind("pdm").load(path)
    finally:
        sessions.kw["bind"].dispose()
    pose, u_H, _ = model.evaluator.deformation(markers)
    base = model.evaluator.base
    return pose.restore(actor.vertices + (base.deform(u_H) - base.smooth))


def assert_store_whole(deployment: Deployment, client: httpx.Client) -> dict:
    """Nothing half-written: no job queued or running, no model training, every blob that a
    row references verifies its sha256 (models through the API's map downloads too), and no
    model files exist that no ready model owns. Returns counts for the report."""
    jobs = ok(client.get("/v1/jobs"))["items"]
    assert not [j for j in jobs if j["status"] in ACTIVE], jobs
    models = [m for a in ok(client.get("/v1/actors"))["items"]
              for m in ok(client.get(f"/v1/actors/{a['id']}/models"))["items"]]
    assert not [m for m in models if m["status"] == "training"], models
    for model in models:
        if model["status"] == "failed":
            assert model["error"]["code"] and model["error"]["message"], model
        if model["status"] != "ready" or model["kind"] != "pdm":   # shape_space has no maps
            continue
        maps = ok(client.get(f"/v1/models/{model['id']}/maps"))["items"]
        assert {m["name"] for m in maps} >= {"medium", "fine"}, maps
        for info in maps:
            response = client.get(info["url"])
            assert response.status_code == 200, response.text
            assert len(response.content) == info["size_bytes"]
            assert response.headers["etag"] == f'"{hashlib.sha256(response.content).hexdigest()}"'

    blobs = deployment.blobs()
    sessions = deployment.sessions()
    checked = 0
    try:
        with sessions() as session:
            referenced = []
            for actor in registry.list_actors(session):
                for key, digest in ((actor.neutral_blob, actor.neutral_sha256),
                                    (actor.markers_blob, actor.markers_sha256)):
                    referenced.append((key, digest))
                referenced += [(c.blob, c.sha256) for c in registry.list_clips(session, actor.id)]
                for rig in registry.list_input_rigs(session, actor.id):
                    referenced.append((rig.mesh_blob, rig.mesh_sha256))
                    if rig.status == "ready":
                        referenced.append((rig.registration_blob, rig.registration_sha256))
            ready = registry.list_models(session, status="ready")
            referenced += [(m.blob, m.sha256) for m in ready]
            for model in registry.list_models(session):
                assert model.status != "ready" or model.blob, model.id
                assert model.status == "ready" or model.blob is None, model.id
            for key, digest in referenced:
                assert key and blobs.digest(key) == digest, key
                checked += 1
    finally:
        sessions.kw["bind"].dispose()
    # model directories on disk: exactly the ready models' (a killed attempt left none,
    # visible or as a temporary sibling)
    on_disk = {p.relative_to(blobs.root).as_posix()
               for p in (blobs.root / "models").glob("*/*")}
    assert on_disk == {m.blob for m in ready}, on_disk
    assert not list(blobs.root.glob(".train-*")), "a training's temporary directory was left"
    return {"jobs": len(jobs), "models": len(models), "blobs_verified": checked}


# ---------------------------------------------------------------------------- state
@pytest.fixture(scope="module")
def state() -> dict:
    """What the tests hand on to each other (ids, held-out data, the first synthesis)."""
    return {}


def needs(state: dict, *keys: str) -> None:
    missing = [k for k in keys if k not in state]
    if missing:
        pytest.skip(f"needs {missing} from an earlier test of this module, which failed")


# ---------------------------------------------------------------------------- tests
def test_train_through_the_api_and_synthesize_heldout_frames(deployment, e2e_actor_dir, state):
    actor = dataset.load_actor(e2e_actor_dir)
    neutral, layout, clips = sample_actor_uploads(e2e_actor_dir, TRAINING)
    canonical = json.loads(layout)
    markers_body = {"markers": [{"name": n, "triangle": t, "barycentric": b} for n, t, b in
                                zip(canonical["names"], canonical["triangle"],
                                    canonical["barycentric"])]}
    with deployment.client() as client:
        actor_id = ok(client.post("/v1/actors", json={
            "name": "sample actor (level 1)", "metadata": {"seed": 1, "level": 1}}), 201)["id"]
        info = ok(client.put(f"/v1/actors/{actor_id}/neutral", content=neutral, headers=NPZ))
        assert (info["vertex_count"], info["triangle_count"]) == (actor.n_vertices, len(actor.faces))
        assert ok(client.put(f"/v1/actors/{actor_id}/markers",
                             json=markers_body))["marker_count"] == actor.n_markers == 150
        clip_ids = []
        for name in TRAINING:
            clip = ok(client.post(f"/v1/actors/{actor_id}/clips", content=clips[name],
                                  headers=NPZ, params={"name": name}), 201)
            assert clip["frames"] == 20
            clip_ids.append(clip["clip_id"])
        assert [c["clip_id"] for c in ok(client.get(f"/v1/actors/{actor_id}/clips"))["items"]] \
            == clip_ids

        response = client.post(f"/v1/actors/{actor_id}/models",
                               json={"kind": "pdm", "clips": clip_ids, "params": PARAMS})
        accepted = ok(response, 202)
        model_id, job_id = accepted["model_id"], accepted["job_id"]
        assert response.headers["location"] == f"/v1/jobs/{job_id}"
        assert ok(client.get(f"/v1/models/{model_id}"))["status"] == "training"

        # the progress stream: the job's stages in order, progress never going back
        events = read_events(client, job_id, stages=3)
        running = [job for name, job in events if job["status"] == "running"]
        assert events[0][1]["id"] == job_id and events[0][1]["status"] in ("queued", "running")
        assert len({job["stage"] for job in running}) >= 3 or events[-1][0] == "end", events
        assert [j["progress"] for j in running] == sorted(j["progress"] for j in running), events
        assert max(j["progress"] for j in running) > 0, events

        job = wait_job(client, job_id, timeout=300)
        assert job["status"] == "succeeded", job
        assert (job["progress"], job["result"]["model_id"], job["error"]) == (1.0, model_id, None)
        model = ok(client.get(f"/v1/models/{model_id}"))
        assert model["status"] == "ready" and model["size_bytes"] > 0, model
        assert model["metrics"]["training_frames"] == 8 * 20
        assert model["params"]["order"] == "biquadratic"
        # one worker ran it start to end: a busy worker keeps its lease by heartbeats
        row = job_row(deployment, job_id)
        assert row.attempts == 1 and worker_pid(row.worker) in [w.pid for w in deployment.workers]

        markers, truth = heldout(e2e_actor_dir)
        response = client.post(f"/v1/models/{model_id}/synthesize", content=npz(markers=markers),
                               headers=NPZ, params={"outputs": "mesh,displacement"})
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "application/x-npz"
        out = load_npz(response.content)
    F, n = len(FRAMES), actor.n_vertices
    assert out["vertices"].shape == (F, n, 3) and out["vertices"].dtype == np.float32
    assert out["displacement"].shape == (F, MAP_RESOLUTION, MAP_RESOLUTION)
    np.testing.assert_array_equal(out["faces"], actor.faces)
    assert np.isfinite(out["displacement"]).all() and np.abs(out["displacement"]).max() > 0

    face = np.asarray(actor.regions["face"])
    error = np.linalg.norm(out["vertices"] - truth, axis=-1)[:, face]
    baseline = np.linalg.norm(no_detail(deployment, model_id, actor, markers) - truth,
                              axis=-1)[:, face]
    mean, p95 = float(error.mean()), float(np.percentile(error, 95))
    base_mean = float(baseline.mean())
    print(f"\nmedium vertex error, face region, {F} held-out frames: PDM mean {mean:.3f} mm "
          f"(p95 {p95:.3f}), no-detail thin shell mean {base_mean:.3f} mm "
          f"(p95 {np.percentile(baseline, 95):.3f}); per frame PDM "
          f"{np.round(error.mean(axis=1), 3).tolist()} vs {np.round(baseline.mean(axis=1), 3).tolist()}")
    assert mean < MEDIUM_MEAN_BOUND_MM and p95 < MEDIUM_P95_BOUND_MM, (mean, p95)
    assert mean < (1 - MIN_IMPROVEMENT) * base_mean, (mean, base_mean)

    state.update(actor_id=actor_id, clip_ids=clip_ids, model_id=model_id, job_id=job_id,
                 markers=markers, vertices=out["vertices"], displacement=out["displacement"])


def test_shape_space_enhances_rig_frames_and_retimes(deployment, e2e_actor_dir, state):
    needs(state, "actor_id", "clip_ids")
    actor = dataset.load_actor(e2e_actor_dir)
    actor_id, clip_ids = state["actor_id"], state["clip_ids"]
    started = time.monotonic()
    with deployment.client() as client:
        accepted = ok(client.post(f"/v1/actors/{actor_id}/models", json={
            "kind": "shape_space", "clips": clip_ids, "params": SHAPE_SPACE_PARAMS}), 202)
        model_id = accepted["model_id"]
        rig = ok(client.put(f"/v1/actors/{actor_id}/input-rigs/{RIG}",
                            content=(e2e_actor_dir / "input_rig.npz").read_bytes(),
                            headers=NPZ), 202)
        lowres, truth, medium = heldout_lowres(e2e_actor_dir)
        assert rig["vertex_count"] == lowres.shape[1]
        # while it registers, the rig is refused by name with its job
        early = client.post(f"/v1/models/{model_id}/enhance", content=npz(vertices=lowres[:1]),
                            headers=NPZ, params={"rig": RIG})
        assert early.status_code == 409, early.text
        trained = wait_job(client, accepted["job_id"], timeout=300)
        registered = wait_job(client, rig["job_id"], timeout=300)
        assert trained["status"] == registered["status"] == "succeeded", (trained, registered)
        assert ok(client.get(f"/v1/actors/{actor_id}/input-rigs/{RIG}"))["status"] == "ready"
        jobs_done = time.monotonic()

        response = client.post(f"/v1/models/{model_id}/enhance", content=npz(vertices=lowres),
                               headers=NPZ, params={"rig": RIG, "outputs": "mesh"})
        assert response.status_code == 200, response.text
        out = load_npz(response.content)
        enhanced = time.monotonic()

        clip = clip_ids[0]
        response = client.post(f"/v1/models/{model_id}/retime", json={
            "keyframes": [{"clip_id": clip, "frame": 0}, {"clip_id": clip, "frame": 19}],
            "length": 8})
        assert response.status_code == 200, response.text
        retimed = load_npz(response.content)
    finished = time.monotonic()

    F, n = len(FRAMES), actor.n_vertices
    assert out["vertices"].shape == (F, n, 3) and np.isfinite(out["vertices"]).all()
    np.testing.assert_array_equal(out["faces"], actor.faces)
    face = np.asarray(actor.regions["face"])
    error = np.linalg.norm(out["vertices"] - truth, axis=-1)[:, face]
    no_detail = np.linalg.norm(medium - truth, axis=-1)[:, face]
    detail = no_detail > DETAIL_MM
    mean, p95 = float(error.mean()), float(np.percentile(error, 95))
    at_detail, base_at_detail = float(error[detail].mean()), float(no_detail[detail].mean())
    print(f"\nshape_space: trained and registered in {jobs_done - started:.0f} s, {F} frames "
          f"enhanced in {enhanced - jobs_done:.1f} s, retimed in {finished - enhanced:.1f} s; "
          f"vertex error, face region: mean {mean:.4f} mm (p95 {p95:.4f}); where the ground "
          f"truth has detail ({detail.mean():.1%} of vertex-frames) {at_detail:.4f} mm vs "
          f"{base_at_detail:.4f} mm without detail; per frame "
          f"{np.round(error.mean(axis=1), 4).tolist()}")
    assert mean < SHAPE_SPACE_MEAN_BOUND_MM and p95 < SHAPE_SPACE_P95_BOUND_MM, (mean, p95)
    assert at_detail < (1 - MIN_DETAIL_RECOVERED) * base_at_detail, (at_detail, base_at_detail)

    assert retimed["vertices"].shape == (8, n, 3) and retimed["timestamps"].shape == (8,)
    assert np.isfinite(retimed["vertices"]).all()
    with np.load(e2e_actor_dir / "performances" / f"{TRAINING[0]}.npz") as d:
        ends = d["vertices"][[0, 19]]
    np.testing.assert_array_equal(retimed["vertices"][0], ends[0])
    np.testing.assert_allclose(retimed["vertices"][-1], ends[1], atol=1e-4)
    state.update(shape_space_model_id=model_id, lowres=lowres[:1], enhanced=out["vertices"][:1])


def test_a_killed_worker_s_job_still_ends_and_nothing_is_half_written(deployment, state):
    needs(state, "model_id")
    with deployment.client() as client:
        accepted = ok(client.post(f"/v1/actors/{state['actor_id']}/models", json={
            "kind": "pdm", "clips": state["clip_ids"], "params": {**PARAMS, "order": "linear"}}),
            202)
        model_id, job_id = accepted["model_id"], accepted["job_id"]
        job = wait_job(client, job_id, timeout=120,
                       until=lambda j: j["status"] in FINAL or (j["status"] == "running"
                                                                 and j["progress"] > 0))
        assert job["status"] == "running", job
        row = job_row(deployment, job_id)
        assert row.attempts == 1
        victim = deployment.worker_by_pid(worker_pid(row.worker))
        survivor = next(w for w in deployment.workers if w is not victim and w.alive())
        assert job["stage"] != "storing the model", job   # killed long before any file is written
        os.kill(victim.pid, signal.SIGKILL)
        assert victim.popen.wait(10) == -signal.SIGKILL
        killed_at = time.monotonic()

        seen: list = []
        final = wait_job(client, job_id, timeout=300, seen=seen)
        ended_after = time.monotonic() - killed_at
        row = job_row(deployment, job_id)
        model = ok(client.get(f"/v1/models/{model_id}"))
        print(f"\nkilled {victim.name} (pid {victim.pid}) at {job['stage']!r} "
              f"(progress {job['progress']:.2f}); the job ended {final['status']} "
              f"{ended_after:.0f} s later after {row.attempts} attempts on {row.worker}; "
              f"states seen {seen}")
        if final["status"] == "succeeded":
            # retried on the other worker once the dead one's lease expired
            assert row.attempts >= 2 and worker_pid(row.worker) == survivor.pid, row
            assert model["status"] == "ready" and model["metrics"]["training_frames"] == 160
        else:
            assert final["status"] == "failed", final
            assert final["error"]["code"] and final["error"]["message"], final
            assert model["status"] == "failed" and model["error"] == final["error"], model
        assert survivor.alive()
        counts = assert_store_whole(deployment, client)
        print(f"store whole: {counts}")
    state.update(killed_job_id=job_id, killed_model_id=model_id)


def test_a_restarted_api_serves_the_same_state(deployment, state):
    needs(state, "model_id")

    def snapshot(client: httpx.Client) -> dict:
        actors = ok(client.get("/v1/actors"))["items"]
        return {
            "actors": actors,
            "clips": {a["id"]: ok(client.get(f"/v1/actors/{a['id']}/clips"))["items"] for a in actors},
            "models": {a["id"]: ok(client.get(f"/v1/actors/{a['id']}/models"))["items"]
                       for a in actors},
            "jobs": ok(client.get("/v1/jobs"))["items"],
        }

    with deployment.client() as client:
        wait_job(client, state["job_id"], timeout=10)
        deadline = time.monotonic() + 300
        while [j for j in ok(client.get("/v1/jobs"))["items"] if j["status"] in ACTIVE]:
            assert time.monotonic() < deadline, "jobs still active"
            time.sleep(0.5)
        before = snapshot(client)
    assert state["model_id"] in {m["id"] for ms in before["models"].values() for m in ms}
    assert {state["job_id"], state.get("killed_job_id", state["job_id"])} <= {
        j["id"] for j in before["jobs"]}

    old = deployment.api
    assert old.stop(signal.SIGTERM, timeout=60) == 0, old.tail()   # a graceful, clean exit
    assert "Application shutdown complete" in old.stderr.read_text()
    with pytest.raises(httpx.TransportError):
        httpx.get(f"{deployment.base_url}/healthz", timeout=2)
    new = deployment.start_api()
    assert new.pid != old.pid

    with deployment.client() as client:
        after = snapshot(client)
        assert after == before
        response = client.post(f"/v1/models/{state['model_id']}/synthesize",
                               content=npz(markers=state["markers"]), headers=NPZ,
                               params={"outputs": "mesh,displacement"})
        assert response.status_code == 200, response.text
        out = load_npz(response.content)
    # a fresh process loads the stored model and computes exactly the same meshes and maps
    np.testing.assert_array_equal(out["vertices"], state["vertices"])
    np.testing.assert_array_equal(out["displacement"], state["displacement"])
    if "shape_space_model_id" in state:      # the rig's registration, loaded by the new process
        with deployment.client() as client:
            response = client.post(f"/v1/models/{state['shape_space_model_id']}/enhance",
                                   content=npz(vertices=state["lowres"]), headers=NPZ,
                                   params={"rig": RIG, "outputs": "mesh"})
        assert response.status_code == 200, response.text
        # within one process shape_space is bit-reproducible; across processes a few
        # coordinates have been seen to differ by one float32 ulp (3 of 134 358, 1.9e-6 mm)
        np.testing.assert_allclose(load_npz(response.content)["vertices"], state["enhanced"],
                                   rtol=0, atol=SHAPE_SPACE_RESTART_ATOL_MM)
    print(f"\nafter the restart: {len(after['actors'])} actor(s), "
          f"{sum(map(len, after['clips'].values()))} clips, "
          f"{[(m['id'], m['status']) for ms in after['models'].values() for m in ms]}, "
          f"{[(j['id'], j['status']) for j in after['jobs']]} unchanged")

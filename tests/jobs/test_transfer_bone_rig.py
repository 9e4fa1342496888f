"""The ``transfer`` and ``bone_rig`` task functions (service.jobs.tasks.transfer,
service.jobs.tasks.bone_rig) run directly and through the runner: stages reported, retries
that find their result stored, and a source deleted while its transfer was queued."""

from __future__ import annotations

import numpy as np

from models_store import registry
from service.api.deps import get_submit
from service.jobs.running import RunningJob
from service.jobs.runner import execute
from service.jobs.tasks.bone_rig import bone_rig
from service.jobs.tasks.transfer import transfer
from tests.api.conftest import Recorder
from tests.api.test_transfer import app_client, source, upload_actor  # noqa: F401 (fixtures)


def running(client, job_id: str, stages: list) -> RunningJob:
    services = client.app.state.services
    with services.session() as session:
        job = registry.get_job(session, job_id)
        return RunningJob(job.id, job.kind, job.actor_id, job.model_id, dict(job.payload), 1,
                          services.store, lambda f, s: stages.append((f, s)))


def test_a_bone_rig_task_reports_stages_and_a_retry_reuses_its_artifacts(app_client, source):
    actor_id, _ = source
    services = app_client.app.state.services
    with services.session() as session:
        clip_id = registry.list_clips(session, actor_id)[0].id
        job = registry.create_job(session, "bone_rig", actor_id, payload={
            "clip_id": clip_id, "params": {"bones": 3, "iterations": 2}})
    stages: list = []
    first = bone_rig(running(app_client, job.id, stages))
    fractions = [f for f, _ in stages]
    assert fractions == sorted(fractions) and fractions[-1] == 0.9
    assert {s for _, s in stages} >= {"loading the performance", "alternation", "writing the rig"}
    again = bone_rig(running(app_client, job.id, stages := []))
    assert again["artifact_ids"] == first["artifact_ids"] and stages == []
    with services.session() as session:
        assert len(registry.list_artifacts(session, job.id)) == 2


def test_a_transfer_whose_source_was_deleted_fails_its_model(app_client, source):
    actor_id, model_id = source
    recorder = Recorder()
    app_client.app.dependency_overrides[get_submit] = lambda: recorder
    lm = np.linspace(0, 207, 10).astype(int)
    accepted = app_client.post(f"/v1/models/{model_id}/transfer", json={
        "target_actor_id": actor_id, "landmarks": np.stack([lm, lm], 1).tolist()}).json()
    assert recorder == [accepted["job_id"]]
    assert app_client.delete(f"/v1/models/{model_id}").status_code == 204
    settings = app_client.app.state.services.settings
    assert execute(settings, accepted["job_id"], "test-worker") == "failed"
    job = app_client.get(f"/v1/jobs/{accepted['job_id']}").json()
    assert job["error"]["code"] == "not_found" and model_id in job["error"]["message"]
    assert app_client.get(f"/v1/models/{accepted['model_id']}").json()["status"] == "failed"


def test_a_transfer_retry_finds_its_model_ready(app_client, source):
    actor_id, model_id = source
    lm = np.linspace(0, 207, 10).astype(int)
    accepted = app_client.post(f"/v1/models/{model_id}/transfer", json={
        "target_actor_id": actor_id, "landmarks": np.stack([lm, lm], 1).tolist()}).json()
    stages: list = []
    assert transfer(running(app_client, accepted["job_id"], stages)) == {
        "model_id": accepted["model_id"]}
    assert stages == [(0.0, "loading the source model and the target actor")]

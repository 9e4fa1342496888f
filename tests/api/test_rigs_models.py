"""Input rigs (registration jobs) and model training requests, without running the jobs."""

from __future__ import annotations

import json

import numpy as np

from models_store import registry
from tests.api.conftest import NPZ, assert_problem, grid, npz


def _clip(client, actor_id) -> str:
    body = npz(vertices=np.stack([grid()[0]] * 2), markers=np.zeros((2, 3, 3)))
    return client.post(f"/v1/actors/{actor_id}/clips", content=body, headers=NPZ).json()["clip_id"]


# ---------------------------------------------------------------------------- input rigs
def test_put_input_rig_queues_a_registration_job(client, grid_actor, submitted):
    V, F, _ = grid(4)
    response = client.put(f"/v1/actors/{grid_actor}/input-rigs/lod2",
                          content=npz(vertices=V, faces=F), headers=NPZ)
    assert response.status_code == 202, response.text
    accepted = response.json()
    assert response.headers["location"] == f"/v1/jobs/{accepted['job_id']}"
    assert (accepted["name"], accepted["vertex_count"], accepted["landmarks"]) == ("lod2", 16, 0)
    assert submitted == [accepted["job_id"]]
    job = client.get(f"/v1/jobs/{accepted['job_id']}").json()
    assert (job["kind"], job["status"], job["actor_id"]) == ("register", "queued", grid_actor)
    rig = client.get(f"/v1/actors/{grid_actor}/input-rigs/lod2").json()
    assert (rig["rig_id"], rig["status"]) == (accepted["rig_id"], "registering")
    assert [r["name"] for r in client.get(f"/v1/actors/{grid_actor}/input-rigs").json()["items"]] == ["lod2"]
    # replacing the rig cancels the registration still queued
    again = client.put(f"/v1/actors/{grid_actor}/input-rigs/lod2",
                       content=npz(vertices=V, faces=F), headers=NPZ).json()
    assert again["rig_id"] == accepted["rig_id"]
    assert client.get(f"/v1/jobs/{accepted['job_id']}").json()["status"] == "cancelled"


def test_put_input_rig_multipart_with_landmarks(client, grid_actor):
    V, F, _ = grid(4)
    files = {"mesh": ("rig.npz", npz(vertices=V, faces=F), "application/octet-stream")}
    response = client.put(f"/v1/actors/{grid_actor}/input-rigs/lod1", files=files,
                          data={"landmarks": json.dumps([[0, 0], [15, 35]])})
    assert response.status_code == 202, response.text
    job = client.get(f"/v1/jobs/{response.json()['job_id']}")
    assert response.json()["landmarks"] == 2 and job.status_code == 200
    bad = client.put(f"/v1/actors/{grid_actor}/input-rigs/lod1", files=files,
                     data={"landmarks": json.dumps([[0, 36]])})
    assert_problem(bad, 422, "landmark 0", "neutral vertex 36")


def test_put_input_rig_refusals(client, grid_actor):
    V, F, _ = grid(4)
    body = npz(vertices=V, faces=F)
    bare = client.post("/v1/actors", json={"name": "B"}).json()["id"]
    assert_problem(client.put(f"/v1/actors/{bare}/input-rigs/x", content=body, headers=NPZ), 409,
                   "no neutral mesh")
    assert_problem(client.put(f"/v1/actors/{grid_actor}/input-rigs/..bad", content=body,
                              headers=NPZ), 422, "rig")
    assert_problem(client.put(f"/v1/actors/{grid_actor}/input-rigs/x", content=body,
                              headers={"Content-Type": "image/png"}), 415)
    V[2] = np.inf
    assert_problem(client.put(f"/v1/actors/{grid_actor}/input-rigs/x",
                              content=npz(vertices=V, faces=F), headers=NPZ), 422, "vertex 2")
    assert_problem(client.get(f"/v1/actors/{grid_actor}/input-rigs/none"), 404, "none")


# ---------------------------------------------------------------------------- models
def test_train_model_answers_202_with_a_queued_job(client, grid_actor, submitted):
    clip_id = _clip(client, grid_actor)
    response = client.post(f"/v1/actors/{grid_actor}/models",
                           json={"kind": "pdm", "clips": [clip_id],
                                 "params": {"order": "linear", "medium_resolution": 64}})
    assert response.status_code == 202, response.text
    accepted = response.json()
    assert response.headers["location"] == f"/v1/jobs/{accepted['job_id']}"
    assert submitted == [accepted["job_id"]]
    model = client.get(f"/v1/models/{accepted['model_id']}").json()
    assert (model["status"], model["kind"], model["actor_id"]) == ("training", "pdm", grid_actor)
    assert model["params"]["order"] == "linear" and model["params"]["fine_resolution"] is None
    job = client.get(f"/v1/jobs/{accepted['job_id']}").json()
    assert (job["kind"], job["model_id"], job["status"]) == ("train", accepted["model_id"], "queued")
    listed = client.get(f"/v1/actors/{grid_actor}/models").json()["items"]
    assert [m["id"] for m in listed] == [accepted["model_id"]]
    assert client.get(f"/v1/actors/{grid_actor}/models", params={"status": "ready"}).json() == {"items": [], "next_cursor": None}


def test_train_model_rejects_a_misspelt_param(client, grid_actor):
    clip_id = _clip(client, grid_actor)
    body = assert_problem(client.post(f"/v1/actors/{grid_actor}/models", json={
        "kind": "pdm", "clips": [clip_id], "params": {"ordr": "linear"}}), 422, "ordr")
    assert body["errors"][0]["type"] == "extra_forbidden"
    assert_problem(client.post(f"/v1/actors/{grid_actor}/models", json={
        "kind": "pdm", "clips": [clip_id], "params": {"medium_resolution": 4}}), 422,
        "medium_resolution")


def test_train_model_rejects_unknown_kind_clip_and_state(client, grid_actor):
    clip_id = _clip(client, grid_actor)
    url = f"/v1/actors/{grid_actor}/models"
    assert_problem(client.post(url, json={"kind": "pdmm", "clips": [clip_id]}), 422, "kind")
    assert_problem(client.post(url, json={"kind": "pdm", "clips": []}), 422, "clips")
    assert_problem(client.post(url, json={"kind": "pdm", "clips": ["clp_00000000000000000000000000"]}),
                   404, "clp_00000000000000000000000000")
    other = client.post("/v1/actors", json={"name": "B"}).json()["id"]
    assert_problem(client.post(f"/v1/actors/{other}/models", json={"kind": "pdm", "clips": [clip_id]}),
                   409, "no neutral")


def test_train_model_when_the_queue_is_down_is_503_and_cancels(client, grid_actor, submitted):
    clip_id = _clip(client, grid_actor)
    submitted.fail = True
    response = client.post(f"/v1/actors/{grid_actor}/models", json={"kind": "pdm", "clips": [clip_id]})
    assert_problem(response, 503, "queue")
    assert response.headers["retry-after"] == "1"
    model = client.get(f"/v1/actors/{grid_actor}/models").json()["items"][0]
    # its training job was cancelled, so the model reports cancelled (error code cancelled)
    assert (model["status"], model["error"]["code"]) == ("cancelled", "cancelled")


def test_training_model_cannot_synthesize_or_list_maps(client, grid_actor):
    clip_id = _clip(client, grid_actor)
    model_id = client.post(f"/v1/actors/{grid_actor}/models",
                           json={"kind": "pdm", "clips": [clip_id]}).json()["model_id"]
    assert_problem(client.post(f"/v1/models/{model_id}/synthesize",
                               json={"markers": [[[0, 0, 0]] * 3]}), 409, "not ready", "training")
    assert_problem(client.get(f"/v1/models/{model_id}/maps"), 409, "not ready")
    assert_problem(client.get(f"/v1/models/{model_id}/maps/fine.exr"), 409)
    assert_problem(client.post(f"/v1/models/{model_id}/synthesis-jobs", content=npz(
        markers=np.zeros((2, 3, 3))), headers=NPZ), 409, "not ready")
    assert client.delete(f"/v1/models/{model_id}").status_code == 204
    assert_problem(client.get(f"/v1/models/{model_id}"), 404)
    assert_problem(client.post(f"/v1/models/{model_id}/synthesize",
                               json={"markers": [[[0, 0, 0]] * 3]}), 404)


def test_kinds_and_openapi_document_pdm_with_its_patent_notice(client):
    kinds = client.get("/v1/kinds").json()["items"]
    pdm = next(k for k in kinds if k["name"] == "pdm")
    assert "8,902,232" in pdm["description"] and pdm["input"] == "markers"
    assert pdm["params_schema"]["properties"]["medium_resolution"]["default"] == 512
    assert client.get("/v1/kinds/pdm").json() == pdm
    assert_problem(client.get("/v1/kinds/nope"), 404, "pdm")
    spec = client.get("/openapi.json").json()
    train = spec["paths"]["/v1/actors/{actor_id}/models"]["post"]
    assert "8,902,232" in train["description"] and train["tags"] == ["models"]
    assert {t["name"] for t in spec["tags"]} >= {"actors", "models", "synthesis", "jobs"}
    assert "TrainPdm" in spec["components"]["schemas"]


def test_a_cancelled_training_reports_the_model_cancelled(client, grid_actor):
    """Cancelling a queued training (at once) and a running one (when the worker stops it)
    both report the model ``cancelled``, not ``failed``; ``?status=`` filters by it."""
    clip_id = _clip(client, grid_actor)
    train = lambda: client.post(f"/v1/actors/{grid_actor}/models",
                                json={"kind": "pdm", "clips": [clip_id]}).json()
    queued, running, failing = train(), train(), train()
    assert client.delete(f"/v1/jobs/{queued['job_id']}").json()["status"] == "cancelled"
    services = client.app.state.services
    with services.session() as session:
        for accepted in (running, failing):
            registry.claim_job(session, "w1", lease_seconds=60, max_retries=0,
                               job_id=accepted["job_id"])
        assert client.delete(f"/v1/jobs/{running['job_id']}").status_code == 202
        registry.finish_job(session, running["job_id"], "cancelled", worker="w1")
        registry.finish_job(session, failing["job_id"], "failed", worker="w1",
                            error={"code": "invalid_input", "message": "bad clip"})
    status = lambda m: client.get(f"/v1/models/{m['model_id']}").json()["status"]
    assert [status(m) for m in (queued, running, failing)] == ["cancelled", "cancelled", "failed"]
    listed = lambda s: [m["id"] for m in client.get(f"/v1/actors/{grid_actor}/models",
                                                    params={"status": s}).json()["items"]]
    assert listed("cancelled") == [queued["model_id"], running["model_id"]]
    assert listed("failed") == [failing["model_id"]]
    enum = client.get("/openapi.json").json()["components"]["schemas"]["Model"]["properties"]["status"]
    assert enum["enum"] == ["training", "ready", "failed", "cancelled"]

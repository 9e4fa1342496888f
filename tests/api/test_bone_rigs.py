"""POST /v1/actors/{actor_id}/bone-rig-jobs (Le & Deng 2012 as a job): 202 + Location, the
job run by the immediate (``memory://``) queue, its .npz and .glb artifacts (the glb loaded
with pygltflib and replayed as an engine skins it), and the refusals."""

from __future__ import annotations

import io

import numpy as np
import pygltflib as gl
import pytest

from models_store import registry
from service.io.usd_skel import skinned_points
from service.methods.bone_rig.rig import BoneRig
from tests.api.conftest import NPZ, assert_problem, npz, sheet, sheet_motion
from tests.api.test_transfer import app_client, upload_actor  # noqa: F401 (fixture)
from tests.io.test_gltf import replay

MARKERS = (0, 40, 100, 150)
PARAMS = {"bones": 6, "max_influences": 3, "iterations": 6, "seed": 1}


@pytest.fixture
def actor(app_client):
    """The 16×13 sheet with one 10-frame clip: (actor id, clip id, the clip's frames)."""
    V, F, uv = sheet(16, 13)
    frames = sheet_motion(V, 10, 0.0)
    actor_id, (clip_id,) = upload_actor(app_client, "rigged", V, F, uv, MARKERS, [frames])
    return actor_id, clip_id, frames.astype(np.float32).astype(np.float64)


def artifact_of(client, actor_id: str, arrays: dict) -> str:
    """An .npz artifact of a (finished) job of the actor, standing in for a synthesis
    job's result."""
    services = client.app.state.services
    with services.session() as session:
        job = registry.create_job(session, "synthesize", actor_id)
        return registry.add_artifact(session, services.blobs, job.id, npz(**arrays),
                                     media_type="application/x-npz").id


def test_a_bone_rig_job_stores_an_npz_and_a_glb_that_replay_the_same_skinning(
        app_client, actor, tmp_path):
    actor_id, clip_id, frames = actor
    response = app_client.post(f"/v1/actors/{actor_id}/bone-rig-jobs",
                               json={"clip_id": clip_id, "params": PARAMS, "fps": 24})
    assert response.status_code == 202, response.text
    job_id = response.json()["job_id"]
    assert response.headers["Location"] == f"/v1/jobs/{job_id}"
    job = app_client.get(f"/v1/jobs/{job_id}").json()
    assert (job["kind"], job["status"], job["progress"], job["actor_id"]) == (
        "bone_rig", "succeeded", 1.0, actor_id)
    assert [j["id"] for j in app_client.get("/v1/jobs", params={"kind": "bone_rig"}).json()[
        "items"]] == [job_id]
    npz_id, glb_id = job["result"]["artifact_ids"]
    listed = app_client.get(f"/v1/jobs/{job_id}/artifacts").json()["items"]
    assert {a["media_type"] for a in listed} == {"application/x-npz", "model/gltf-binary"}
    (tmp_path / "rig.npz").write_bytes(app_client.get(f"/v1/artifacts/{npz_id}").content)
    glb = app_client.get(f"/v1/artifacts/{glb_id}")
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    (tmp_path / "rig.glb").write_bytes(glb.content)
    rig = BoneRig.load_npz(tmp_path / "rig.npz")
    assert rig.frames == 10 and rig.bones <= 6 and rig.fps == 24.0
    np.testing.assert_allclose(rig.rest, sheet(16, 13)[0], atol=1e-5)   # the neutral
    assert ((rig.weight >= 0).all() and np.allclose(rig.weight.sum(axis=1), 1, atol=1e-6)
            and (np.count_nonzero(rig.weight, axis=1) <= 3).all())
    recon = rig.reconstruct()
    err = np.linalg.norm(recon - frames, axis=-1)
    metrics = job["result"]["metrics"]
    assert metrics["rms_mm"] == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-3, abs=1e-4)
    assert metrics["rms_mm"] < 0.2 * np.sqrt(np.mean(np.sum((frames - frames[:1]) ** 2, -1)))
    # the glb, read with pygltflib and skinned as an engine does, gives the npz's skinning
    g = gl.GLTF2().load(str(tmp_path / "rig.glb"))
    assert len(g.skins) == 1 and len(g.animations) == 1
    replayed, faces = replay(tmp_path / "rig.glb")
    np.testing.assert_array_equal(faces, sheet(16, 13)[1])
    assert np.abs(replayed - recon).max() < 1e-3        # float32 storage of ~40 mm positions


def test_usd_true_adds_a_usdskel_stage_that_usd_itself_skins_to_the_npz_rig(
        app_client, actor, tmp_path):
    actor_id, clip_id, _ = actor
    response = app_client.post(f"/v1/actors/{actor_id}/bone-rig-jobs",
                               json={"clip_id": clip_id, "params": PARAMS, "usd": True})
    assert response.status_code == 202, response.text
    job = app_client.get(f"/v1/jobs/{response.json()['job_id']}").json()
    assert job["status"] == "succeeded", job
    npz_id, _, usd_id = job["result"]["artifact_ids"]
    (tmp_path / "rig.npz").write_bytes(app_client.get(f"/v1/artifacts/{npz_id}").content)
    usd = app_client.get(f"/v1/artifacts/{usd_id}")
    assert usd.status_code == 200 and usd.content[:8] == b"PXR-USDC"     # a binary crate
    (tmp_path / "rig.usd").write_bytes(usd.content)
    recon = BoneRig.load_npz(tmp_path / "rig.npz").reconstruct()
    for f in (0, 5, 9):
        assert np.abs(skinned_points(tmp_path / "rig.usd", f) - recon[f]).max() < 1e-3


def test_an_artifact_performance_and_its_refusals(app_client, actor):
    actor_id, clip_id, frames = actor
    url = f"/v1/actors/{actor_id}/bone-rig-jobs"
    # a synthesis result's vertices: accepted, and the job succeeds
    good = artifact_of(app_client, actor_id, {"vertices": frames[:4].astype(np.float32)})
    response = app_client.post(url, json={"artifact_id": good, "params": PARAMS})
    assert response.status_code == 202, response.text
    assert app_client.get(f"/v1/jobs/{response.json()['job_id']}").json()["status"] == "succeeded"
    # NaN frames: accepted (the header is fine), the job fails with invalid_input naming it
    bad = frames[:4].copy()
    bad[2, 17] = np.nan
    nan_id = artifact_of(app_client, actor_id, {"vertices": bad})
    response = app_client.post(url, json={"artifact_id": nan_id, "params": PARAMS})
    assert response.status_code == 202, response.text
    job = app_client.get(f"/v1/jobs/{response.json()['job_id']}").json()
    assert job["status"] == "failed" and job["error"]["code"] == "invalid_input"
    assert "frame 2" in job["error"]["message"]
    # checked at submission: empty, wrong topology, no vertices, neither / both sources,
    # too many bones, unknown parameter
    for arrays, fragment in (({"vertices": np.zeros((0, 208, 3), np.float32)}, "F >= 1"),
                             ({"vertices": frames[:2, :100]}, "(F,208,3)"),
                             ({"markers": frames[:2, :4]}, "no 'vertices'")):
        artifact = artifact_of(app_client, actor_id, arrays)
        assert_problem(app_client.post(url, json={"artifact_id": artifact}), 422, fragment)
    assert_problem(app_client.post(url, json={}), 422)
    assert_problem(app_client.post(url, json={"clip_id": clip_id, "artifact_id": good}), 422)
    assert_problem(app_client.post(url, json={"clip_id": clip_id, "params": {"bones": 500}}),
                   422, "exceeds")
    assert_problem(app_client.post(url, json={"clip_id": clip_id, "params": {"bone": 5}}), 422)
    # another actor's clip or artifact: 404; an actor without a neutral: 409
    V, F, uv = sheet(16, 13)
    other, (other_clip,) = upload_actor(app_client, "other", V, F, uv, MARKERS,
                                        [sheet_motion(V, 3, 0.2)])
    assert_problem(app_client.post(url, json={"clip_id": other_clip}), 404)
    assert_problem(app_client.post(f"/v1/actors/{other}/bone-rig-jobs",
                                   json={"artifact_id": good}), 404)
    bare = app_client.post("/v1/actors", json={"name": "bare"}).json()["id"]
    assert_problem(app_client.post(f"/v1/actors/{bare}/bone-rig-jobs",
                                   json={"clip_id": clip_id}), 409, "neutral")
    assert_problem(app_client.post(url, content=b"{}", headers=NPZ), 415)


def test_a_queued_bone_rig_job_can_be_cancelled(client, grid_actor, submitted):
    services = client.app.state.services
    with services.session() as session:
        neutral = np.load(io.BytesIO(registry.read_neutral(session, services.blobs, grid_actor)))
        frames = np.repeat(neutral["vertices"][None], 3, axis=0)
    response = client.post(f"/v1/actors/{grid_actor}/clips", headers=NPZ, content=npz(
        vertices=frames.astype(np.float32), markers=frames[:, [0, 7, 14]].astype(np.float32)))
    clip_id = response.json()["clip_id"]
    response = client.post(f"/v1/actors/{grid_actor}/bone-rig-jobs",
                           json={"clip_id": clip_id, "params": {"bones": 2}})
    assert response.status_code == 202, response.text
    job_id = response.json()["job_id"]
    assert submitted == [job_id]
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert (job["kind"], job["status"]) == ("bone_rig", "queued")
    assert client.delete(f"/v1/jobs/{job_id}").json()["status"] == "cancelled"


def test_bone_rig_jobs_are_in_the_openapi_document(client):
    spec = client.get("/openapi.json").json()
    operation = spec["paths"]["/v1/actors/{actor_id}/bone-rig-jobs"]["post"]
    assert set(operation["responses"]) >= {"202", "404", "409", "422"}
    assert "Le & Deng 2012" in operation["description"]
    assert "max_influences" in str(spec["components"]["schemas"])

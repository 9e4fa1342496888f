"""Mesh-driven synthesis jobs through the runner: a ``shape_space`` model of a tiny actor
trained by the ``train`` job, its input rig registered by the ``register`` job, and
``synthesize`` jobs (submitted as the API submits them) enhancing frames given on the
actor's topology or on the rig's, which the job propagates with the registration it was
submitted with."""

from __future__ import annotations

import numpy as np
import pytest

from models_store import registry
from service.store import actors as actor_store
from service.app import operations
from service.app.services import Services
from service.io.npz import npz_arrays, npz_bytes
from service.jobs import runner
from service.methods.kinds import get_kind
from service.methods.shape_space.registration import RigRegistration
from tests.api.conftest import SHEET_MARKERS, SHEET_PARAMS, sheet, sheet_clips, sheet_motion

WORKER = "test-host:1:MainThread"
NPZ = "application/x-npz"


@pytest.fixture(scope="module")
def sheet_model(deployment):
    """(services, actor id, model id, rig neutral (v,3)) of the tiny actor added to the
    deployment, with its model trained and its rig "lod" registered by their jobs."""
    V, F, uv = sheet(16, 13)
    Vr, Fr, _ = sheet(9, 7)
    blobs = deployment.store.blobs
    markers = list(SHEET_MARKERS)
    triangle = np.array([np.flatnonzero((F == v).any(axis=1))[0] for v in markers])
    barycentric = (F[triangle] == np.array(markers)[:, None]).astype(np.float64)
    with deployment.session() as session:
        actor = registry.create_actor(session, "sheet")
        registry.set_neutral(session, blobs, actor.id, actor_store.neutral_npz(V, F, uv),
                             vertex_count=len(V), triangle_count=len(F))
        registry.set_markers(session, blobs, actor.id, actor_store.layout_json(
            [f"M{k}" for k in range(len(markers))], triangle, barycentric),
            marker_count=len(markers))
        clip_ids = [registry.add_clip(session, blobs, actor.id, data, name=name, frames=12).id
                    for name, data in sheet_clips(V).items()]
        model, train_job = registry.create_model(session, actor.id, "shape_space", SHEET_PARAMS,
                                                 clip_ids=clip_ids)
        rig = registry.put_input_rig(session, blobs, actor.id, "lod",
                                     npz_bytes(vertices=Vr, faces=Fr))
        register_job = registry.create_job(session, "register", actor.id,
                                           payload={"rig_id": rig.id, "rig": "lod",
                                                    "landmarks": []})
    assert runner.execute(deployment.settings, train_job.id, WORKER) == "succeeded"
    assert runner.execute(deployment.settings, register_job.id, WORKER) == "succeeded"
    services = Services.open(deployment.settings)
    try:
        yield services, actor.id, model.id, Vr
    finally:
        services.close()


def _submit(services: Services, model_id: str, frames: np.ndarray, rig: str | None):
    return operations.submit_synthesis_job(
        services, lambda job_id: None, model_id, NPZ, npz_bytes(vertices=frames), None,
        outputs=("mesh", "displacement"), result_format="npz", clamp=True, rig=rig)


def _result(deployment, job_id: str) -> dict[str, np.ndarray]:
    job = deployment.job(job_id)
    assert job.status == "succeeded", job.error
    (artifact_id,) = job.result["artifact_ids"]
    with deployment.session() as session:
        _, stream = registry.open_artifact(session, deployment.store.blobs, artifact_id)
        with stream:
            return npz_arrays(stream.read())


def _model(deployment, model_id: str):
    with deployment.session() as session:
        return get_kind("shape_space").load(
            registry.model_dir(session, deployment.store.blobs, model_id))


def test_synthesis_job_with_rig_propagates_then_enhances(deployment, sheet_model):
    services, actor_id, model_id, Vr = sheet_model
    frames = sheet_motion(Vr, 20, 0.1)                  # more than one chunk of 16 frames
    job = _submit(services, model_id, frames, "lod")
    assert (job.payload["rig"], job.payload["frames"]) == ("lod", 20)
    assert runner.execute(deployment.settings, job.id, WORKER) == "succeeded"
    result = _result(deployment, job.id)
    with deployment.session() as session:
        rig = registry.get_input_rig(session, actor_id, "lod")
        registration = RigRegistration.load(deployment.store.blobs.read_bytes(
            rig.registration_blob, rig.registration_sha256))
    stored = frames.astype(np.float32)                  # the job's input as stored
    expected = _model(deployment, model_id).enhance(registration.propagate(stored),
                                                    ("mesh", "displacement"))
    assert result["vertices"].shape == (20, 16 * 13, 3)
    assert set(result) == set(expected)
    for key in expected:
        np.testing.assert_array_equal(result[key], expected[key], err_msg=key)


def test_synthesis_job_on_the_actor_topology(deployment, sheet_model):
    services, _, model_id, _ = sheet_model
    V, _, _ = sheet(16, 13)
    frames = sheet_motion(V, 3, 0.4)
    job = _submit(services, model_id, frames, None)
    assert "rig" not in job.payload
    assert runner.execute(deployment.settings, job.id, WORKER) == "succeeded"
    expected = _model(deployment, model_id).enhance(frames.astype(np.float32), ("mesh",))
    np.testing.assert_array_equal(_result(deployment, job.id)["vertices"], expected["vertices"])


def test_a_job_whose_rig_was_uploaded_again_fails_with_a_reason(deployment, sheet_model):
    services, actor_id, model_id, Vr = sheet_model
    job = _submit(services, model_id, sheet_motion(Vr, 2, 0.2), "lod")
    Vs, Fs, _ = sheet(8, 6)
    with deployment.session() as session:      # replaces the registration the job names
        registry.put_input_rig(session, deployment.store.blobs, actor_id, "lod",
                               npz_bytes(vertices=Vs, faces=Fs))
    assert runner.execute(deployment.settings, job.id, WORKER) == "failed"
    error = deployment.job(job.id).error
    assert error["code"] == "invalid_input" and "uploaded again" in error["message"], error

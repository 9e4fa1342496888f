"""The ``register`` job through the runner: an input rig registered to the actor's neutral,
stored on the rig; a registration that cannot run marks the rig failed."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from models_store import registry
from models_store.schema import InputRig
from service.store import actors as actor_store
from service.jobs import runner
from service.methods.shape_space.registration import RigRegistration

WORKER = "test-host:1:MainThread"


@pytest.fixture(scope="module")
def rig_data(pdm_actor_dir):
    """The sample actor's input rig as stored (NPZ bytes) and its arrays."""
    data = (pdm_actor_dir / "input_rig.npz").read_bytes()
    with np.load(pdm_actor_dir / "input_rig.npz") as z:
        return data, z["vertices"].astype(np.float64), z["faces"].astype(np.int64)


def _queue(deployment, name: str, data: bytes, landmarks) -> tuple[str, str]:
    with deployment.session() as session:
        rig = registry.put_input_rig(session, deployment.store.blobs, deployment.actor_id, name, data)
        job = registry.create_job(session, "register", deployment.actor_id,
                                  payload={"rig_id": rig.id, "rig": name, "landmarks": landmarks})
        return rig.id, job.id


def _rig(deployment, rig_id: str) -> InputRig:
    with deployment.session() as session:
        rig = registry.get_input_rig_by_id(session, rig_id)
        session.expunge(rig)
        return rig


def test_a_rig_is_registered_and_stored(deployment, rig_data):
    data, vertices, faces = rig_data
    landmarks = [[i, i] for i in (0, 1000, 4000, 8000)]
    rig_id, job_id = _queue(deployment, "ict", data, landmarks)
    assert runner.execute(deployment.settings, job_id, WORKER) == "succeeded"
    job = deployment.job(job_id)
    assert (job.status, job.result, job.stage) == ("succeeded", {"rig_id": rig_id},
                                                   "storing the registration")
    rig = _rig(deployment, rig_id)
    assert rig.status == "ready" and rig.error is None
    registration = RigRegistration.load(
        deployment.store.blobs.read_bytes(rig.registration_blob, rig.registration_sha256))
    with deployment.session() as session:
        actor = actor_store.actor_from_blobs(
            registry.read_neutral(session, deployment.store.blobs, deployment.actor_id),
            registry.read_markers(session, deployment.store.blobs, deployment.actor_id))
    assert registration.operator.shape == (actor.n_vertices, len(vertices))
    # the level-0 sample actor's neutral is its rig's surface
    assert registration.stats["landmarks"] == 4 and registration.stats["actor_to_rig_rms"] < 0.01
    moved = vertices + np.array([0.0, 2.0, 0.0])
    np.testing.assert_allclose(registration.propagate(moved), actor.vertices + [0.0, 2.0, 0.0],
                               atol=1e-9)


def test_a_registration_that_cannot_run_marks_the_rig_failed(deployment, rig_data):
    data, vertices, _ = rig_data
    rig_id, job_id = _queue(deployment, "broken", data, [[len(vertices) + 5, 0]] * 3)
    assert runner.execute(deployment.settings, job_id, WORKER) == "failed"
    job = deployment.job(job_id)
    assert job.error["code"] == "invalid_input" and "landmark" in job.error["message"]
    rig = _rig(deployment, rig_id)
    assert rig.status == "failed" and rig.registration_blob is None
    assert rig.error["code"] == "invalid_input" and "landmark" in rig.error["message"]


def test_a_replaced_rig_is_left_to_the_new_upload(deployment, rig_data, monkeypatch):
    data, _, _ = rig_data
    rig_id, job_id = _queue(deployment, "replaced", data, [])
    task_module = sys.modules["service.jobs.tasks.register"]  # the package attribute is the function

    def replace_then_register(*args, **kwargs):
        with deployment.session() as session:  # the user uploads the rig again meanwhile
            registry.put_input_rig(session, deployment.store.blobs, deployment.actor_id,
                                   "replaced", data)
        raise task_module.InvalidInput("the first upload was unusable")

    monkeypatch.setattr(task_module, "register_rig", replace_then_register)
    assert runner.execute(deployment.settings, job_id, WORKER) == "failed"
    assert _rig(deployment, rig_id).status == "registering"

"""The ``register`` job: register an input rig's neutral to the actor's neutral.

Payload ``{"rig_id", "rig", "landmarks": [[rig_vertex, neutral_vertex], ...]}`` (as
:func:`service.app.operations.put_input_rig` writes it). Reads the rig's mesh blob and the
actor's neutral, runs :func:`service.methods.shape_space.registration.register_rig` and
stores its NPZ bytes with :func:`models_store.registry.mark_rig_ready`. Result
``{"rig_id"}``.

A registration that fails (unusable input, or an internal error) marks the rig ``failed``
with the job's error code and message before the job itself fails. A cancelled job leaves
the rig alone: it is cancelled when the rig is uploaded again, and the new upload's job
owns the rig's state. Likewise a job whose rig mesh was replaced while it ran stores
nothing.
"""

from __future__ import annotations

from typing import Any

from models_store import registry
from models_store.errors import NotFound
from service.store.actors import load_neutral_arrays
from service.io.mesh import read_npz
from service.jobs.running import RunningJob
from service.methods.inputs import InvalidInput
from service.methods.shape_space.registration import register_rig

# the job's progress: inputs, then the registration, then storing it
LOADED, REGISTERED = 0.05, 0.95


def register(job: RunningJob) -> dict[str, Any]:
    """Register the job's rig (``job.payload["rig_id"]``) and mark it ready (or failed)."""
    rig_id = job.payload["rig_id"]
    store = job.store
    with store.sessions() as session:
        rig = registry.get_input_rig_by_id(session, rig_id)
        if rig.status != "registering":
            return {"rig_id": rig_id}          # a retry after the result was stored
        mesh_blob = rig.mesh_blob
    try:
        job.progress(0.0, "loading inputs")
        with store.sessions() as session:
            rig = registry.get_input_rig_by_id(session, rig_id)
            mesh = read_npz(store.blobs.read_bytes(rig.mesh_blob, rig.mesh_sha256))
            neutral = load_neutral_arrays(session, store.blobs, rig.actor_id,
                                          "registering an input rig")
        landmarks = job.payload.get("landmarks") or []
        result = register_rig(mesh.vertices, mesh.faces, neutral["vertices"], neutral["faces"],
                              landmarks, job.sub_progress(LOADED, REGISTERED))
        job.progress(REGISTERED, "storing the registration")
        data = result.save()
    except InvalidInput as error:
        _fail(job, rig_id, mesh_blob, "invalid_input", str(error))
        raise
    except NotFound as error:
        _fail(job, rig_id, mesh_blob, "not_found", str(error))
        raise
    except (KeyError, ValueError, ArithmeticError, MemoryError) as error:
        _fail(job, rig_id, mesh_blob, "internal", f"{type(error).__name__}: {error}")
        raise
    with store.sessions() as session:
        rig = registry.get_input_rig_by_id(session, rig_id)
        if rig.mesh_blob == mesh_blob and rig.status == "registering":
            registry.mark_rig_ready(session, store.blobs, rig_id, data)
    return {"rig_id": rig_id}


def _fail(job: RunningJob, rig_id: str, mesh_blob: str, code: str, message: str) -> None:
    """Mark the rig failed unless it was deleted, re-uploaded or no longer registering."""
    with job.store.sessions() as session:
        try:
            rig = registry.get_input_rig_by_id(session, rig_id)
        except NotFound:
            return
        if rig.mesh_blob == mesh_blob and rig.status == "registering":
            registry.mark_rig_failed(session, rig_id, code, message)

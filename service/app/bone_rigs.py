"""Compression of a performance to a bone rig as an operation:
``POST /v1/actors/{actor_id}/bone-rig-jobs`` (Le & Deng 2012, the Digital Ira "Game Rig").

:func:`submit_bone_rig` checks what can be checked at once — the actor has a neutral (409),
the performance is one of its clips or a ``.npz`` artifact of one of its jobs (404) whose
``vertices`` are (F,V,3) with F ≥ 1 on the actor's topology (422, read from the array's
header, not its data), and no more bones than vertices (422) — then queues a ``bone_rig``
job (:mod:`service.jobs.tasks.bone_rig`). Non-finite frames are found by the job, which then
fails with ``invalid_input`` naming the first.
"""

from __future__ import annotations

import zipfile

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from models_store import registry
from models_store.errors import NotFound
from service.app.operations import submit
from service.app.services import Services, Submit
from service.errors import Conflict, InvalidInput
from service.jobs.tasks.bone_rig import BONE_RIG_JOB
from service.methods.bone_rig.params import BoneRigParams


class BoneRigBody(BaseModel):
    """JSON body of `POST /v1/actors/{actor_id}/bone-rig-jobs`: the performance (exactly one
    of `clip_id`, `artifact_id`) and the decomposition's parameters."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"clip_id": "clp_01jb3k7y4b6d8f0h2k4m6p8r0t", "params": {"bones": 70,
                                                                 "max_influences": 4}},
        {"artifact_id": "art_01jb3kc3x1z5b7d9f2h4k6m8p0", "params": {"bones": 40}, "fps": 60}]})

    clip_id: str | None = Field(None, description="A clip of the actor: its `vertices` "
                                                   "(F,V,3) are the animation.")
    artifact_id: str | None = Field(
        None, description="A `.npz` result of a synthesis job of the actor's model: its "
                          "`vertices` (F,V,3) are the animation.")
    params: BoneRigParams = Field(default_factory=BoneRigParams,
                                  description="Decomposition parameters (SSDR).")
    fps: float | None = Field(None, gt=0, le=1000,
                              description="Frame rate of the exported animation (default: "
                                          "the clip's, else the artifact's `fps`, else 30).")
    usd: bool = Field(False, description="Also store the rig as a UsdSkel stage (`.usd`: "
                                         "skeleton, skel animation, skinned mesh).")

    @model_validator(mode="after")
    def _one_source(self) -> BoneRigBody:
        if (self.clip_id is None) == (self.artifact_id is None):
            raise ValueError("give exactly one of clip_id and artifact_id")
        return self


def submit_bone_rig(services: Services, submit_job: Submit, actor_id: str,
                    body: BoneRigBody) -> str:
    """Queue a ``bone_rig`` job for one of the actor's performances; returns its job id.

    The job's payload is ``{"clip_id" | "artifact_id", "params", "fps"?}``.

    Raises
    ------
    NotFound       unknown actor; a clip or artifact that is not the actor's
    Conflict       the actor has no neutral (the rest pose)
    InvalidInput   an artifact without (F,V,3) ``vertices`` on the actor's topology, an empty
                   performance, more bones than vertices
    """
    with services.session() as session:
        actor = registry.get_actor(session, actor_id)
        if actor.neutral_blob is None:
            raise Conflict(f"actor {actor_id!r} has no neutral mesh yet (the rig's rest pose); "
                           f"PUT /v1/actors/{actor_id}/neutral first")
        V = actor.vertex_count
        if body.clip_id is not None:
            clip = registry.get_clip(session, body.clip_id, actor_id)
            if clip.frames < 1:
                raise InvalidInput(f"clip {clip.id!r} has no frames")
        else:
            artifact = registry.get_artifact(session, body.artifact_id)
            if registry.get_job(session, artifact.job_id).actor_id != actor_id:
                raise NotFound("artifact", artifact.id, f"it is not a result of a job of actor "
                                                        f"{actor_id!r}")
            shape = _vertices_shape(services.blobs.path(artifact.blob), artifact.id)
            if len(shape) != 3 or shape[2] != 3 or shape[0] < 1 or shape[1] != V:
                raise InvalidInput(f"artifact {artifact.id!r} has vertices of shape {shape}; a "
                                   f"bone rig of actor {actor_id!r} needs (F,{V},3) with F >= 1")
        if body.params.bones > V:
            raise InvalidInput(f"params.bones = {body.params.bones} exceeds the actor's vertex "
                               f"count {V}")
        payload = {"params": body.params.model_dump(mode="json"), "usd": body.usd}
        payload.update({"clip_id": body.clip_id} if body.clip_id is not None
                       else {"artifact_id": body.artifact_id})
        if body.fps is not None:
            payload["fps"] = body.fps
        job = registry.create_job(session, BONE_RIG_JOB, actor_id, payload=payload)
        submit(session, submit_job, job)
        return job.id


def _vertices_shape(path, artifact_id: str) -> tuple[int, ...]:
    """The shape of the ``vertices`` array of an ``.npz`` file, from its header only."""
    try:
        with zipfile.ZipFile(path) as archive, archive.open("vertices.npy") as member:
            major, _ = np.lib.format.read_magic(member)
            read = (np.lib.format.read_array_header_1_0 if major == 1
                    else np.lib.format.read_array_header_2_0)
            shape, _, _ = read(member)
    except KeyError:
        raise InvalidInput(f"artifact {artifact_id!r} has no 'vertices' array (a synthesis "
                           "job's .npz result has one)") from None
    except (zipfile.BadZipFile, ValueError, OSError) as error:
        raise InvalidInput(f"artifact {artifact_id!r} is not a readable .npz: {error}") from None
    return tuple(int(s) for s in shape)

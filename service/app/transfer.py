"""Detail transfer (bickel2008 §5.4) as an operation: ``POST /v1/models/{model_id}/transfer``.

:func:`submit_transfer` checks what can be checked at once — a ready ``psd``/``wpsd`` source
(409 otherwise), a target actor with a neutral and a marker layout (409), landmark pairs
within both neutrals' vertex ranges and without repeats (422), one pose weight per target
marker (422) — then creates the target's new model (status ``training``, the source's kind
and parameters) together with its queued ``transfer`` job in one commit, and submits the job
(:mod:`service.jobs.tasks.transfer`).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from models_store import registry
from service.app import schemas
from service.app.operations import submit
from service.app.services import Services, Submit
from service.errors import Conflict, InvalidInput
from service.jobs.tasks.transfer import TRANSFER_JOB, TRANSFER_KINDS, TransferParams
from service.methods.pose_space.transfer import MIN_LANDMARKS, check_landmarks

Pair = Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=2, max_length=2)]


class TransferBody(BaseModel):
    """JSON body of `POST /v1/models/{model_id}/transfer`."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "target_actor_id": "act_01jb3k5q8m2v7c4x6b1n0r8tea",
        "landmarks": [[812, 790], [4051, 3977], [9120, 8875], [2210, 2301]]}]})

    target_actor_id: str = Field(description="The actor the details go to (with its neutral "
                                              "and marker layout).")
    landmarks: list[Pair] = Field(
        min_length=MIN_LANDMARKS,
        description=f"Corresponding vertex pairs [source_vertex, target_vertex] on the two "
                    f"neutrals (at least {MIN_LANDMARKS}; the paper uses ~40 spread over the "
                    "face: eye and mouth corners, nose, brows, chin, jaw line). They drive "
                    "the rigid pre-alignment and the thin-shell fit of the source to the "
                    "target before the dense correspondence is found by projection.")
    params: TransferParams = Field(default_factory=TransferParams,
                                   description="Transfer parameters.")


def submit_transfer(services: Services, submit_job: Submit, model_id: str,
                    body: TransferBody) -> schemas.ModelAccepted:
    """Queue the transfer of model ``model_id``'s details to ``body.target_actor_id``.

    The job's payload is ``{"model_id" (the new model), "source_model_id", "landmarks",
    "params"}``.

    Raises
    ------
    NotFound       unknown source model or target actor
    Conflict       the source is not a ready psd/wpsd model; the target lacks its neutral
                   or marker layout
    InvalidInput   a landmark out of range or repeated; pose weights of the wrong count
    """
    with services.session() as session:
        source = registry.get_model(session, model_id)
        if source.kind not in TRANSFER_KINDS:
            raise Conflict(f"model {model_id!r} is a {source.kind} model; details transfer from "
                           f"{' and '.join(TRANSFER_KINDS)} models (bickel2008 §5.4)")
        if source.status != "ready":
            raise Conflict(f"model {model_id!r} is {source.status}, not ready; transfer it once "
                           "its training succeeds")
        source_actor = registry.get_actor(session, source.actor_id)
        target = registry.get_actor(session, body.target_actor_id)
        for what, blob, put in (("neutral mesh", target.neutral_blob, "neutral"),
                                ("marker layout", target.markers_blob, "markers")):
            if blob is None:
                raise Conflict(f"actor {target.id!r} has no {what} yet; PUT "
                               f"/v1/actors/{target.id}/{put} before transferring to it")
        landmarks = check_landmarks(body.landmarks, source_actor.vertex_count,
                                    target.vertex_count).tolist()
        weights = body.params.pose_weights
        if weights is not None:
            if len(weights) != target.marker_count:
                raise InvalidInput(f"params.pose_weights has {len(weights)} weights; actor "
                                   f"{target.id!r} has {target.marker_count} markers")
            if not all(np.isfinite(w) and w >= 0 for w in weights) or not any(weights):
                raise InvalidInput("params.pose_weights must be finite, >= 0 and not all zero")
        # the new model and its job belong to the target actor's tenant
        model, job = registry.create_model(
            session, target.id, source.kind, source.params, job_kind=TRANSFER_JOB,
            payload={"source_model_id": source.id, "landmarks": landmarks,
                     "params": body.params.model_dump(mode="json")})
        submit(session, submit_job, job)
        return schemas.ModelAccepted(model_id=model.id, job_id=job.id)

"""Bone rigs: a performance compressed to a linear-blend-skinned rig (a job whose result is
the rig as NPZ and as a binary glTF 2.0 skin)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Depends, Response, status
from fastapi.concurrency import run_in_threadpool

from service.api import bodies
from service.api.deps import ServicesDep, SubmitDep
from service.api.routes import problems, set_job_location
from service.app import schemas
from service.app.bone_rigs import BoneRigBody, submit_bone_rig

router = APIRouter(tags=["bone-rigs"])


@router.post(
    "/v1/actors/{actor_id}/bone-rig-jobs", status_code=status.HTTP_202_ACCEPTED,
    response_model=schemas.JobAccepted, summary="Compress a performance to a bone rig (a job)",
    dependencies=[Depends(bodies.require_json)],
    responses=problems(400, 404, 409, 415, 422, 503),
    description=(
        "The game rig of the Digital Ira course: smooth-skinning weights (sparse, at most "
        "`max_influences` per vertex, non-negative, summing to 1) and per-frame rigid bone "
        "transforms that best reproduce an animation on the actor's topology, by Smooth "
        "Skinning Decomposition with Rigid Bones (Le & Deng 2012). The animation is one of "
        "the actor's clips (`clip_id`) or the `.npz` result of a synthesis job of one of its "
        "models (`artifact_id`, its `vertices`); the rest pose is the actor's neutral.\n\n"
        "Answers 202 with `{job_id}` and `Location: /v1/jobs/{job_id}`; the job (kind "
        "`bone_rig`) reports its progress and can be cancelled. Its result holds two "
        "artifacts (`GET /v1/artifacts/{id}`): the rig as `.npz` (`rest` (V,3), `faces`, "
        "`joints` (V,K) uint16, `weights` (V,K), `rotations` (F,B,3,3) and `translations` "
        "(F,B,3) rest → frame, `joint_rest` (B,3), `fps`) and as `.glb` (`model/gltf-binary`: "
        "the skinned rest mesh, its joints with inverse bind matrices and one animation with "
        "a translation and rotation channel per joint), with `usd: true` a third, the rig as "
        "a UsdSkel stage (`.usd`: `/Rig` SkelRoot with a Skeleton, a SkelAnimation sampled "
        "per frame and the skinned mesh), plus `metrics` (reconstruction "
        "`rms_mm`, `max_mm`, bones kept, iterations, seconds).\n\n"
        "409: the actor has no neutral. 404: a clip or artifact that is not the actor's. 422: "
        "neither or both of `clip_id` and `artifact_id`, an artifact without (F,V,3) "
        "`vertices` on the actor's topology or with no frames, more bones than vertices. "
        "Frames with NaN or infinite vertices make the job fail with `invalid_input`."))
async def submit_bone_rig_job(actor_id: str, request_body: Annotated[BoneRigBody, Body()],
                              services: ServicesDep, submit: SubmitDep,
                              response: Response) -> schemas.JobAccepted:
    job_id = await run_in_threadpool(submit_bone_rig, services, submit, actor_id, request_body)
    set_job_location(response, job_id)
    return schemas.JobAccepted(job_id=job_id)

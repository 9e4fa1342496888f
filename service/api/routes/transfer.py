"""Detail transfer (bickel2008 §5.4): a pose-space model's details carried to another actor,
as a job that produces the target's new model."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Depends, Response, status
from fastapi.concurrency import run_in_threadpool

from service.api import bodies
from service.api.deps import ServicesDep, SubmitDep
from service.api.routes import problems, set_job_location
from service.app import schemas
from service.app.transfer import TransferBody, submit_transfer

router = APIRouter(tags=["models"])


@router.post(
    "/v1/models/{model_id}/transfer", status_code=status.HTTP_202_ACCEPTED,
    response_model=schemas.ModelAccepted, summary="Transfer a model's details to another actor (a job)",
    dependencies=[Depends(bodies.require_json)],
    responses=problems(400, 404, 409, 415, 422, 503),
    description=(
        "Detail transfer of Bickel et al. 2008 §5.4: the fine-scale details of a ready `psd` "
        "or `wpsd` model go to another actor's face, given corresponding landmark vertex "
        "pairs on the two neutrals. The job pre-aligns the source neutral rigidly to the "
        "target on the landmarks, fits it to the target with the linear thin shell, projects "
        "every target vertex onto it (dense barycentric correspondence), and interpolates "
        "the per-vertex RBF weights (rotated into the target's tangent frames) and the "
        "feature graph onto the target.\n\n"
        "Answers 202 with `{model_id, job_id}` and `Location: /v1/jobs/{job_id}`: `model_id` "
        "is the target actor's new model (the source's kind and parameters), `training` "
        "until the job (kind `transfer`) ends, then `ready` — drive it with the target's own "
        "markers through `POST /v1/models/{model_id}/synthesize` — or `failed`. Its "
        "`metrics.transfer` holds the correspondence's quality (landmark RMS after the rigid "
        "fit, projection distances in the actor's unit) and the source's ids.\n\n"
        "409: the source is not a ready `psd`/`wpsd` model, or the target actor has no "
        "neutral or marker layout. 422: fewer landmark pairs than needed, a landmark vertex "
        "out of range of its neutral or repeated, pose weights not one per target marker."))
async def transfer_model(model_id: str, request_body: Annotated[TransferBody, Body()],
                         services: ServicesDep, submit: SubmitDep,
                         response: Response) -> schemas.ModelAccepted:
    accepted = await run_in_threadpool(submit_transfer, services, submit, model_id, request_body)
    set_job_location(response, accepted.job_id)
    return accepted

"""An actor's low-resolution input rigs and their registration to the neutral."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from models_store import registry
from models_store.schema import InputRig
from service.api import bodies
from service.app import operations, schemas, uploads
from service.api.deps import ServicesDep, SessionDep, SubmitDep
from service.api.query import PageDep
from service.api.routes import body, problems, set_job_location

router = APIRouter(prefix="/v1/actors/{actor_id}/input-rigs", tags=["input-rigs"])

RigName = Annotated[str, Path(pattern=schemas.RIG_NAME_PATTERN,
                              description="Your name for the rig (letters, digits, `._-`).",
                              examples=["game-lod2"])]


@router.put(
    "/{rig}", status_code=status.HTTP_202_ACCEPTED, response_model=schemas.RigAccepted,
    summary="Upload an input rig and register it (a job)",
    responses=problems(400, 404, 409, 413, 415, 422, 503),
    openapi_extra=body(uploads.MESH_TYPES, multipart={
        "mesh": {"type": "string", "format": "binary",
                 "description": "The rig's neutral mesh (.npz or .obj)."},
        "landmarks": {"type": "string", "description": "JSON [[rig_vertex, neutral_vertex], ...] "
                                                       "correspondences to guide registration."}},
        description="The rig's neutral mesh as `.npz` / `.obj`, or multipart with `mesh` and "
                    "optional `landmarks`."))
async def put_input_rig(actor_id: str, rig: RigName, request: Request, services: ServicesDep,
                        submit: SubmitDep, response: Response) -> schemas.RigAccepted:
    """Store (or replace) the input rig ``rig`` and queue its registration to the actor's
    neutral; answers 202 with the job (``Location: /v1/jobs/{job_id}``)."""
    kind = bodies.require_media_type(request, uploads.MESH_TYPES + (uploads.MULTIPART,))
    if kind == uploads.MULTIPART:
        kind, data, landmarks = await bodies.read_rig_form(request)
        accepted = await run_in_threadpool(operations.put_input_rig, services, submit, actor_id,
                                           rig, kind, data, landmarks)
    else:
        async with bodies.body_source(request, uploads.MESH_TYPES) as (_, source):
            accepted = await run_in_threadpool(operations.put_input_rig, services, submit,
                                               actor_id, rig, kind, source, None)
    set_job_location(response, accepted.job_id)
    return accepted


@router.get("", response_model=schemas.RigList, summary="List an actor's input rigs",
            responses=problems(404))
def list_input_rigs(actor_id: str, session: SessionDep, page: PageDep) -> schemas.RigList:
    """The actor's input rigs by name, with their registration state, a page at a time
    (`limit`, `cursor`)."""
    rows, cursor = page.rows(registry.list_input_rigs(session, actor_id,
                                                      **page.fetch(InputRig)))
    return schemas.RigList(items=[schemas.InputRig.model_validate(r) for r in rows],
                           next_cursor=cursor)


@router.get("/{rig}", response_model=schemas.InputRig, summary="Get an input rig",
            responses=problems(404))
def get_input_rig(actor_id: str, rig: RigName, session: SessionDep) -> schemas.InputRig:
    """One input rig and its registration state (``registering``, ``ready``, ``failed``)."""
    return schemas.InputRig.model_validate(registry.get_input_rig(session, actor_id, rig))

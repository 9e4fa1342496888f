"""Models: training (a job), their records, their UV-space maps, and the model kinds."""

from __future__ import annotations

from typing import Annotated, Literal, Union

from fastapi import APIRouter, Body, Depends, Path, Query, Response, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field, create_model

from models_store import registry
from models_store.errors import NotFound
from models_store.schema import Model
from service.api import bodies
from service.app import operations, schemas
from service.api.deps import ServicesDep, SessionDep, SubmitDep
from service.api.query import PageDep
from service.api.routes import binary_response, problems, set_job_location
from service.methods.kinds import KINDS, Kind

router = APIRouter(tags=["models"])


def _training_body(kind: Kind) -> type[BaseModel]:
    """The request body that trains a model of ``kind``: its ``params`` are the kind's own
    pydantic model (defaults documented, unknown names refused)."""
    return create_model(
        f"Train{''.join(part.title() for part in kind.name.split('_'))}",
        __config__=ConfigDict(extra="forbid", title=f"Train a {kind.name} model"),
        __doc__=f"{kind.title}.\n\n{kind.description}",
        kind=(Literal[kind.name], Field(description=kind.title)),
        clips=(list[str], Field(min_length=1, description="Ids of the actor's training clips.",
                                examples=[["clp_01jb3k7y4b6d8f0h2k4m6p8r0t"]])),
        params=(kind.params, Field(default_factory=kind.params,
                                   description=f"Training parameters of `{kind.name}`.")),
    )


_BODIES = [_training_body(kind) for kind in KINDS.values()]
TrainBody = (_BODIES[0] if len(_BODIES) == 1 else
             Annotated[Union[tuple(_BODIES)], Field(discriminator="kind")])  # type: ignore[misc]

_KIND_DOCS = "\n\n".join(
    f"**`{kind.name}`** — {kind.title} (input: {kind.input}).\n\n{kind.description}"
    for kind in KINDS.values())


@router.post(
    "/v1/actors/{actor_id}/models", status_code=status.HTTP_202_ACCEPTED,
    response_model=schemas.ModelAccepted, summary="Train a model (a job)",
    dependencies=[Depends(bodies.require_json)],
    responses=problems(400, 404, 409, 415, 422, 503),
    description=("Create a model of the actor from its clips and queue its training. Answers "
                 "202 with `{model_id, job_id}` and `Location: /v1/jobs/{job_id}`; the model "
                 "is `training` until the job ends, then `ready`, `failed` or `cancelled` (the "
                 "job was cancelled). A misspelt or out-of-range parameter is a 422 naming it.\n\nKinds:\n\n" + _KIND_DOCS))
async def train_model(actor_id: str, request_body: Annotated[TrainBody, Body()],  # type: ignore[valid-type]
                      services: ServicesDep, submit: SubmitDep,
                      response: Response) -> schemas.ModelAccepted:
    accepted = await run_in_threadpool(operations.create_model, services, submit, actor_id,
                                       request_body.kind, request_body.clips, request_body.params)
    set_job_location(response, accepted.job_id)
    return accepted


@router.get("/v1/actors/{actor_id}/models", response_model=schemas.ModelList,
            summary="List an actor's models", responses=problems(404))
def list_models(actor_id: str, session: SessionDep, page: PageDep,
                status_filter: Annotated[schemas.ModelStatus | None,
                                         Query(alias="status")] = None) -> schemas.ModelList:
    """The actor's models, oldest first, optionally of one status, a page at a time
    (`limit`, `cursor`)."""
    rows, cursor = page.rows(registry.list_models(session, actor_id, status_filter,
                                                  **page.fetch(Model)))
    return schemas.ModelList(items=[schemas.Model.model_validate(m) for m in rows],
                             next_cursor=cursor)


@router.get("/v1/models/{model_id}", response_model=schemas.Model, summary="Get a model",
            responses=problems(404))
def get_model(model_id: str, session: SessionDep) -> schemas.Model:
    """A model's kind, status (`training`, `ready`, `failed`, `cancelled`), parameters and training
    metrics (fit errors)."""
    return schemas.Model.model_validate(registry.get_model(session, model_id))


@router.delete("/v1/models/{model_id}", status_code=status.HTTP_204_NO_CONTENT,
               summary="Delete a model", responses=problems(404))
async def delete_model(model_id: str, services: ServicesDep) -> Response:
    """Delete a model and its files; its queued or running jobs are cancelled."""
    await run_in_threadpool(operations.delete_model, services, model_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/v1/models/{model_id}/maps", response_model=schemas.MapList,
            summary="List a model's UV-space maps", responses=problems(404, 409))
async def list_maps(model_id: str, services: ServicesDep, page: PageDep) -> schemas.MapList:
    """The model's maps as multi-channel EXR files (e.g. a PDM's coefficient maps
    `x.a0 … z.a5` and `n.a0 … n.a5`), for evaluation in a renderer, a page at a time
    (`limit`, `cursor`)."""
    maps = await run_in_threadpool(operations.list_maps, services, model_id)
    items, cursor = page.items(maps, key=lambda m: m.name)
    return schemas.MapList(items=items, next_cursor=cursor)


@router.get("/v1/models/{model_id}/maps/{name}.exr", summary="Download a map (EXR)",
            response_class=FileResponse, responses={
                **binary_response("image/x-exr", description="The map, 32-bit float unless "
                                                             "`half=true`."),
                **problems(404, 409)})
async def get_map(model_id: str, name: Annotated[str, Path(max_length=128)],
                  services: ServicesDep, half: bool = False) -> Response:
    """One map as an OpenEXR file (range requests supported for the 32-bit file)."""
    file, digest = await run_in_threadpool(operations.map_file, services, model_id, name)
    if half:
        data = await run_in_threadpool(operations.half_exr, file)
        return Response(data, media_type="image/x-exr",
                        headers={"Content-Disposition": f'attachment; filename="{name}.exr"'})
    return FileResponse(file, media_type="image/x-exr", filename=f"{name}.exr",
                        headers={"ETag": f'"{digest}"'} if digest else None)


@router.get("/v1/kinds", response_model=schemas.KindList, summary="List model kinds")
def list_kinds(page: PageDep) -> schemas.KindList:
    """The model kinds this server trains, with their parameters' JSON Schema, a page at a
    time (`limit`, `cursor`)."""
    items, cursor = page.items([_kind_info(k) for k in KINDS.values()], key=lambda k: k.name)
    return schemas.KindList(items=items, next_cursor=cursor)


@router.get("/v1/kinds/{name}", response_model=schemas.KindInfo, summary="Get a model kind",
            responses=problems(404))
def get_kind(name: str) -> schemas.KindInfo:
    """One model kind (e.g. `pdm`), its description and parameters."""
    kind = KINDS.get(name)
    if kind is None:
        raise NotFound("model kind", name, f"known kinds: {', '.join(sorted(KINDS))}")
    return _kind_info(kind)


def _kind_info(kind: Kind) -> schemas.KindInfo:
    return schemas.KindInfo(name=kind.name, title=kind.title, description=kind.description,
                            input=kind.input, params_schema=kind.params.model_json_schema())

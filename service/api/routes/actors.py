"""Actors, their neutral mesh and their marker layout."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from models_store import registry
from models_store.schema import Actor
from service.api import bodies
from service.app import operations, schemas, uploads
from service.api.deps import ServicesDep, SessionDep
from service.api.query import PageDep
from service.api.routes import body, inline_schema, problems

router = APIRouter(prefix="/v1/actors", tags=["actors"])


@router.post("", status_code=status.HTTP_201_CREATED, response_model=schemas.Actor,
             summary="Create an actor", dependencies=[Depends(bodies.require_json)],
             responses=problems(400, 415, 422))
def create_actor(actor: schemas.ActorCreate, session: SessionDep, response: Response) -> schemas.Actor:
    """Create an actor; upload its neutral, marker layout and clips next."""
    row = registry.create_actor(session, actor.name, actor.metadata)
    response.headers["Location"] = f"/v1/actors/{row.id}"
    return schemas.Actor.model_validate(row)


@router.get("", response_model=schemas.ActorList, summary="List actors")
def list_actors(session: SessionDep, page: PageDep) -> schemas.ActorList:
    """Every actor, oldest first, a page at a time (`limit`, `cursor`)."""
    rows, cursor = page.rows(registry.list_actors(session, **page.fetch(Actor)))
    return schemas.ActorList(items=[schemas.Actor.model_validate(a) for a in rows],
                             next_cursor=cursor)


@router.get("/{actor_id}", response_model=schemas.Actor, summary="Get an actor",
            responses=problems(404))
def get_actor(actor_id: str, session: SessionDep) -> schemas.Actor:
    """One actor, with the counts of what has been uploaded for it."""
    return schemas.Actor.model_validate(registry.get_actor(session, actor_id))


@router.delete("/{actor_id}", status_code=status.HTTP_204_NO_CONTENT, summary="Delete an actor",
               responses=problems(404, 409))
async def delete_actor(actor_id: str, services: ServicesDep, cascade: bool = False) -> Response:
    """Delete an actor with its clips and input rigs; its queued and running jobs are
    cancelled. An actor with models is a 409 unless ``cascade=true``, which deletes them too."""
    await run_in_threadpool(operations.delete_actor, services, actor_id, cascade)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.put(
    "/{actor_id}/neutral", response_model=schemas.NeutralInfo,
    summary="Upload the high-resolution neutral mesh",
    responses=problems(400, 404, 409, 413, 415, 422),
    openapi_extra=body(uploads.MESH_TYPES, description=(
        "`.npz` (`application/x-npz`) with `vertices` (V,3), `faces` (T,3), `uv` (V,2) per "
        "vertex or (K,2) with `uv_faces` (T,3), optional `quad_split` (T,) and `region_<name>` "
        "(V,) bool vertex sets; or `.obj` (`model/obj`) with `vt` coordinates.")))
async def put_neutral(actor_id: str, request: Request, services: ServicesDep) -> schemas.NeutralInfo:
    """Store the actor's neutral with its UV layout. The vertex order is kept exactly (it is
    the correspondence every clip follows); polygons are fan-split into triangles and counted.

    Refused with 422 naming the first offender: non-finite coordinates, face indices out of
    range, degenerate (zero-area) triangles, edges shared by more than two triangles, no UVs
    or UVs outside [0,1]². With clips or a marker layout, only the positions may change (409).
    """
    async with bodies.body_source(request, uploads.MESH_TYPES) as (kind, source):
        return await run_in_threadpool(operations.put_neutral, services, actor_id, kind, source)


@router.put(
    "/{actor_id}/markers", response_model=schemas.MarkersInfo, summary="Upload the marker layout",
    responses=problems(400, 404, 409, 413, 415, 422),
    openapi_extra=body((), json_schema=inline_schema(schemas.MarkerLayout)))
async def put_markers(actor_id: str, request: Request, services: ServicesDep) -> schemas.MarkersInfo:
    """Where the markers sit on the neutral, each on a vertex, at barycentric coordinates in a
    triangle, or at a free position snapped to the nearest surface point. The order of the
    markers is the column order of every clip's and request's markers."""
    _, data = await bodies.read_body(request, (uploads.JSON_TYPE,))
    return await run_in_threadpool(operations.put_markers, services, actor_id, data)

"""An actor's training and database clips."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from models_store import registry
from models_store.schema import Clip
from service.api import bodies
from service.app import operations, schemas, uploads
from service.api.deps import ServicesDep, SessionDep
from service.api.query import PageDep
from service.api.routes import body, problems

router = APIRouter(prefix="/v1/actors/{actor_id}/clips", tags=["clips"])

_FILE = {"type": "string", "format": "binary"}


@router.post(
    "", status_code=status.HTTP_201_CREATED, response_model=schemas.ClipAdded,
    summary="Add a clip",
    responses=problems(400, 404, 409, 413, 415, 422),
    openapi_extra=body(uploads.NPZ_TYPES, multipart={
        "frames": {"type": "array", "items": _FILE,
                   "description": "One .obj per frame, in order, in vertex correspondence "
                                  "with the neutral."},
        "markers": {**_FILE, "description": "Marker file: .c3d, .trc, .csv or .json (named "
                                           "markers are matched to the layout by name)."},
        "fps": {"type": "number", "exclusiveMinimum": 0}},
        description="`.npz` with `vertices` (F,V,3), `markers` (F,M,3) in layout order (NaN: "
                    "occluded), optional `displacement` (F,H,H) relative to `vertices`, "
                    "`albedo` (F,A,A,3) linear RGB, `fps`; or multipart per-frame OBJs and a "
                    "marker file."))
async def add_clip(actor_id: str, request: Request, services: ServicesDep,
                   name: Annotated[str | None, Query(max_length=200)] = None) -> schemas.ClipAdded:
    """Store a captured clip. Every frame must have the neutral's vertex count (e.g. 422
    "clip frame 12 has 40000 vertices, the neutral has 40962") and the layout's marker
    count; vertices must be finite. Needs the neutral and the marker layout first (409).
    The answer's `notes` say what the marker file's reader accepted that you should know
    (e.g. a TRC whose `NumFrames` disagrees with its rows)."""
    kind = bodies.require_media_type(request, uploads.NPZ_TYPES + (uploads.MULTIPART,))
    if kind == uploads.MULTIPART:
        data = await bodies.read_clip_form(request)
        return await run_in_threadpool(operations.add_clip, services, actor_id, kind, data, name)
    async with bodies.body_source(request, uploads.NPZ_TYPES) as (_, source):
        return await run_in_threadpool(operations.add_clip, services, actor_id, kind, source,
                                       name)


@router.get("", response_model=schemas.ClipList, summary="List an actor's clips",
            responses=problems(404))
def list_clips(actor_id: str, session: SessionDep, page: PageDep) -> schemas.ClipList:
    """The actor's clips, oldest first, a page at a time (`limit`, `cursor`)."""
    rows, cursor = page.rows(registry.list_clips(session, actor_id, **page.fetch(Clip)))
    return schemas.ClipList(items=[schemas.Clip.model_validate(c) for c in rows],
                            next_cursor=cursor)


@router.get("/{clip_id}", response_model=schemas.Clip, summary="Get a clip",
            responses=problems(404))
def get_clip(actor_id: str, clip_id: str, session: SessionDep) -> schemas.Clip:
    """One clip of the actor."""
    registry.get_actor(session, actor_id)
    return schemas.Clip.model_validate(registry.get_clip(session, clip_id, actor_id))


@router.delete("/{clip_id}", status_code=status.HTTP_204_NO_CONTENT, summary="Delete a clip",
               responses=problems(404))
def delete_clip(actor_id: str, clip_id: str, services: ServicesDep, session: SessionDep) -> Response:
    """Delete a clip and its data (models already trained on it keep what they learnt)."""
    registry.get_actor(session, actor_id)
    registry.delete_clip(session, services.blobs, clip_id, actor_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)

"""Jobs: their state, cancellation, and a server-sent event stream of their progress."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Annotated, AsyncIterator

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from models_store import registry
from models_store.schema import JOB_FINAL_STATUSES, Artifact, Job
from service.app import limits, schemas
from service.api.deps import ServicesDep, SessionDep
from service.api.query import PageDep
from service.api.routes import problems
from service.app.services import Services
from service.app.tracking import cancel_spans

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])


@router.get("", response_model=schemas.JobList, summary="List jobs")
def list_jobs(session: SessionDep, page: PageDep,
              status_filter: Annotated[schemas.JobStatus | None, Query(alias="status")] = None,
              actor_id: str | None = None, kind: str | None = None,
              model_id: str | None = None) -> schemas.JobList:
    """Jobs, oldest first, filtered by any of `status`, `actor_id`, `kind`, `model_id`, a
    page at a time (`limit`, `cursor`)."""
    rows, cursor = page.rows(registry.list_jobs(session, status=status_filter,
                                                actor_id=actor_id, kind=kind, model_id=model_id,
                                                **page.fetch(Job)))
    return schemas.JobList(items=[schemas.Job.model_validate(j) for j in rows],
                           next_cursor=cursor)


@router.get("/{job_id}", response_model=schemas.Job, summary="Get a job",
            responses=problems(404))
def get_job(job_id: str, session: SessionDep) -> schemas.Job:
    """A job's status, progress (0..1), stage, and its error or result once it ended."""
    return schemas.Job.model_validate(registry.get_job(session, job_id))


@router.delete("/{job_id}", response_model=schemas.Job, summary="Cancel a job",
               responses={202: {"model": schemas.Job,
                                "description": "Cancellation requested; the running job "
                                               "stops at its next progress point."},
                          **problems(404)})
def cancel_job(job_id: str, session: SessionDep, response: Response) -> schemas.Job:
    """Cancel a job: a queued job is `cancelled` at once (200); a running one is flagged
    and becomes `cancelled` at its next progress point (202); a finished job is returned
    unchanged (200)."""
    job = registry.request_cancel(session, job_id)
    cancel_spans(session, job)          # a tracking job's span jobs end with it
    if job.status not in JOB_FINAL_STATUSES:
        response.status_code = status.HTTP_202_ACCEPTED
    return schemas.Job.model_validate(job)


@router.get("/{job_id}/artifacts", response_model=schemas.ArtifactList,
            summary="List a job's artifacts", responses=problems(404))
def list_artifacts(job_id: str, session: SessionDep, page: PageDep) -> schemas.ArtifactList:
    """The downloadable results of a job (`GET /v1/artifacts/{artifact_id}`), a page at a
    time (`limit`, `cursor`)."""
    rows, cursor = page.rows(registry.list_artifacts(session, job_id, **page.fetch(Artifact)))
    return schemas.ArtifactList(items=[schemas.Artifact.model_validate(a) for a in rows],
                                next_cursor=cursor)


@router.get(
    "/{job_id}/events", summary="Progress events (server-sent events)",
    response_class=StreamingResponse,
    responses={200: {"description": (
        "`text/event-stream`: an `event: progress` with the job as JSON whenever its status, "
        "progress or stage changes, then one `event: end` with the final job, after which "
        "the stream closes."),
        "content": {"text/event-stream": {"schema": {"type": "string"}, "example": (
            'event: progress\nid: 1\ndata: {"id": "job_…", "status": "running", '
            '"progress": 0.4, ...}\n\nevent: end\nid: 2\ndata: {"id": "job_…", '
            '"status": "succeeded", "progress": 1.0, ...}\n\n')}}},
        **problems(404)})
async def job_events(job_id: str, request: Request, services: ServicesDep) -> StreamingResponse:
    """Follow a job until it ends."""
    first = await run_in_threadpool(_job_json, services, job_id)
    return StreamingResponse(_events(request, services, job_id, first),
                             media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


def _job_json(services: Services, job_id: str) -> dict:
    with services.session() as session:
        return schemas.Job.model_validate(registry.get_job(session, job_id)).model_dump(mode="json")


async def _events(request: Request, services: Services, job_id: str,
                  job: dict) -> AsyncIterator[str]:
    """Poll the job and emit an event per change, until it ends or the client leaves."""
    last, number, sent = None, 0, time.monotonic()
    while True:
        state = (job["status"], job["progress"], job["stage"])
        final = job["status"] in JOB_FINAL_STATUSES
        if state != last or final:
            number += 1
            event = "end" if final else "progress"
            yield f"event: {event}\nid: {number}\ndata: {json.dumps(job)}\n\n"
            last, sent = state, time.monotonic()
            if final:
                return
        elif time.monotonic() - sent >= limits.EVENTS_KEEPALIVE_SECONDS:
            yield ": keep-alive\n\n"
            sent = time.monotonic()
        if await request.is_disconnected():
            return
        await asyncio.sleep(limits.EVENTS_POLL_SECONDS)
        job = await run_in_threadpool(_job_json, services, job_id)

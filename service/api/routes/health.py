"""``/healthz``, ``/readyz`` and ``/metrics`` (unauthenticated: probes and scrapers)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from service.api.deps import ServicesDep
from service.app.metrics import CONTENT_TYPE

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="The process is up",
            responses={200: {"content": {"application/json": {"example": {"status": "ok"}}}}})
def healthz() -> dict[str, str]:
    """Answers as long as the process serves requests (a liveness probe)."""
    return {"status": "ok"}


@router.get("/readyz", summary="Store, database and queue are reachable",
            responses={503: {"description": "Some component is not reachable, or the "
                                            "preloaded models are still loading.",
                             "content": {"application/json": {"example": {
                                 "status": "unavailable",
                                 "checks": {"database": "ok", "blobs": "ok",
                                            "queue": "unreachable: ConnectionError",
                                            "models": "loading: 0 of 1 preloaded"}}}}}})
def readyz(services: ServicesDep) -> JSONResponse:
    """200 with every check ``ok`` when the database, the blob store and the job queue are
    reachable; 503 naming what is not (a readiness probe). A server started with models to
    preload (``FACESYNTH_PRELOAD``) has the check ``models`` as well: not ready until they
    are loaded into the cache (``loading: …``), or if a load failed (``preload failed: …``)."""
    checks = services.check()
    ready = all(value == "ok" for value in checks.values())
    return JSONResponse({"status": "ok" if ready else "unavailable", "checks": checks},
                        status_code=200 if ready else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE: {"schema": {"type": "string"}}}}})
async def metrics(request: Request, services: ServicesDep) -> Response:
    """Request latency by route, queued jobs, job durations, synthesis frames and rate, and
    the model cache (models loaded, bytes, budget, hits, misses), in the Prometheus text
    format."""
    app_metrics = request.app.state.metrics

    def render() -> bytes:
        with services.session() as session:
            app_metrics.refresh_jobs(session)
        return app_metrics.render()

    return Response(await run_in_threadpool(render), media_type=CONTENT_TYPE)

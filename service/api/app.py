"""The FastAPI application of API.md: :func:`create_app`.

Settings are injected, never read at import time: ``create_app(Settings(data_dir=tmp))``
makes an independent app (its own database, blobs, cache and metrics), which is what the
tests do; ``create_app()`` uses :func:`service.config.get_settings`. The lifespan opens the
:class:`~service.app.services.Services` (migrating the database) unless they are given, as
``facesynth serve`` does to share them with the gRPC server.
"""

from __future__ import annotations

import contextlib
import inspect
from typing import Any, AsyncIterator

from fastapi import Depends, FastAPI, Request
from fastapi.openapi.utils import get_openapi

from service.api import docs, errors
from service.api.auth import check_bearer
from service.api.edge import UrlGuardMiddleware
from service.api.lean import LeanSynthesize
from service.api.logs import RequestContextMiddleware
from service.api.thread_handoff import ThreadHandoff
from service.api.errors import PROBLEM_JSON
from service.app.metrics import Metrics
from service.api.routes import (actors, artifacts, bone_rigs, clips, health, jobs, models, rigs,
                                scans, synthesis, tracking, transfer)
from service.api.schemas import Problem
from service.app.services import Services
from service.app.synthesis import Synthesizer
from service.api.bodies import BodyLimitMiddleware, LargeUploadLimiter
from service.api.query import reject_unknown_query
from service.config import Settings, get_settings

API_VERSION = "1"
#: FastAPI's native OpenTelemetry (FastAPI ≥ 0.165) with every signal off
TELEMETRY_OFF = {"tracing": False, "metrics": False, "logs": False}
DESCRIPTION = """\
facesynth learns, per actor, how fine skin detail (wrinkles, pores, albedo shifts) follows
large-scale facial motion, and turns sparse motion-capture markers or low-resolution meshes
into high-resolution meshes and UV-space maps.

Arrays travel as NumPy `.npz` (`application/x-npz`); errors are RFC 9457
`application/problem+json` (`{type, title, status, detail, errors?}`); long work is a job
(`202 Accepted`, `Location: /v1/jobs/{job_id}`). When the server has tokens, every `/v1`
route needs `Authorization: Bearer <token>`.

Query parameters are checked like JSON bodies: one a route does not declare is a 422 naming
it (`errors: [{"loc": ["query", "outptus"], "type": "extra_forbidden", ...}]`).

Every list route pages its `items`: `limit` (1–1000, default 100) and `cursor`. When more
items follow, the answer has `next_cursor`; send it back unchanged as `cursor` for the next
page. Cursors are keyset-based (the last item's sort key), so paging neither skips nor repeats
items while others are added or deleted.
"""
TAGS = [
    {"name": "health", "description": "Liveness, readiness and Prometheus metrics."},
    {"name": "actors", "description": "Actors with their high-resolution neutral mesh and "
                                      "marker layout."},
    {"name": "clips", "description": "Captured training and database clips of an actor."},
    {"name": "input-rigs", "description": "Low-resolution input topologies registered to the "
                                          "actor's neutral."},
    {"name": "models", "description": "Training (a job), trained models and their UV-space "
                                      "maps; the model kinds."},
    {"name": "synthesis", "description": "Meshes and maps from markers or meshes: "
                                         "synchronous for a few frames, jobs for performances."},
    {"name": "bone-rigs", "description": "Performances compressed to linear-blend-skinned bone "
                                         "rigs (NPZ and glTF 2.0), as jobs."},
    {"name": "jobs", "description": "Long work: state, progress events, cancellation."},
    {"name": "artifacts", "description": "Downloadable job results."},
    {"name": "scans", "description": "Facial scans as UV-space maps, and scan correspondence "
                                     "(a job)."},
]


def telemetry_argument(enabled: bool) -> dict[str, Any]:
    """``FastAPI(**...)``'s telemetry argument for ``Settings.opentelemetry``: FastAPI's
    defaults when enabled, else :data:`TELEMETRY_OFF` (its request wrapper then skips the
    global providers' lookup: server CPU per request of ``http_overhead.py``'s lean stub
    0.475 → 0.448 ms, 13.377 → 13.293 with ``--busy 12``, old and new servers interleaved);
    nothing for a FastAPI without native telemetry."""
    if enabled or "telemetry" not in inspect.signature(FastAPI.__init__).parameters:
        return {}
    return {"telemetry": TELEMETRY_OFF}


def create_app(settings: Settings | None = None, *, services: Services | None = None) -> FastAPI:
    """The HTTP API.

    Parameters
    ----------
    settings : Settings, optional   default: :func:`service.config.get_settings`
    services : Services, optional   already opened services to use (and not close); default:
                                    opened from ``settings`` by the app's lifespan

    Returns
    -------
    FastAPI   with ``app.state.services`` (during its lifespan), ``app.state.metrics``,
              ``app.state.synthesizer`` and ``app.state.synthesis_threads`` (the
              synchronous syntheses' :class:`~service.api.thread_handoff.ThreadHandoff`)
    """
    settings = settings if settings is not None else (
        services.settings if services is not None else get_settings())

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        own = services is None
        # one pool of synthesis slots with the synthesizer (and so with the gRPC streams)
        app.state.services = (Services.open(settings, app.state.synthesizer.pool) if own
                              else services)
        app.state.metrics.watch_cache(app.state.services.models)
        try:
            yield
        finally:
            if own:
                app.state.services.close()

    hidden = {} if settings.public_docs else {"openapi_url": None}
    app = FastAPI(title="facesynth", version=API_VERSION, description=DESCRIPTION,
                  openapi_tags=TAGS, lifespan=lifespan, docs_url=None, redoc_url=None,
                  dependencies=[Depends(reject_unknown_query)], **hidden,
                  **telemetry_argument(settings.opentelemetry))
    if settings.public_docs:
        docs.install(app)
    app.state.metrics = Metrics()
    app.state.synthesizer = Synthesizer(app.state.metrics, settings.max_concurrent_syntheses,
                                        settings.synthesis_queue_seconds,
                                        settings.synthesis_queue_depth,
                                        pool=services.synthesis if services is not None else None)
    # the synchronous syntheses' threads: each running, waiting for a slot, or being refused
    app.state.synthesis_threads = ThreadHandoff(
        app.state.synthesizer.limit + app.state.synthesizer.max_queue + 2,
        name="facesynth-request")
    errors.install(app)
    if settings.lean_synthesis:   # innermost: inside every middleware below
        app.add_middleware(LeanSynthesize)
    app.add_middleware(LargeUploadLimiter, limit=settings.max_concurrent_uploads,
                       threshold=settings.spool_body_bytes,
                       wait_seconds=settings.upload_queue_seconds)   # inside the size limit
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_body_bytes)
    app.add_middleware(UrlGuardMiddleware)
    app.add_middleware(RequestContextMiddleware, metrics=app.state.metrics)
    app.include_router(health.router, dependencies=[Depends(check_unless_public)])
    for module in (actors, clips, rigs, models, transfer, synthesis, bone_rigs, tracking, jobs,
                   artifacts, scans):
        app.include_router(module.router, dependencies=[Depends(check_bearer)])
    if not settings.public_docs:
        _protected_docs(app)
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


async def check_unless_public(request: Request) -> None:
    """Dependency of the health router: ``/healthz`` and ``/readyz`` are open unless
    ``public_health`` is false, ``/metrics`` unless ``public_metrics`` is (SECURITY.md)."""
    settings = request.app.state.services.settings
    public = settings.public_metrics if request.url.path == "/metrics" else settings.public_health
    if not public:
        await check_bearer(request)


def _protected_docs(app: FastAPI) -> None:
    """``/openapi.json`` and ``/docs`` behind the bearer token (``public_docs`` false); the
    page's assets are the bundled ones (:mod:`service.api.docs`), never a CDN."""
    from fastapi.responses import HTMLResponse, JSONResponse

    @app.get("/openapi.json", include_in_schema=False, dependencies=[Depends(check_bearer)])
    def openapi_json() -> JSONResponse:
        return JSONResponse(app.openapi())

    @app.get("/docs", include_in_schema=False, dependencies=[Depends(check_bearer)])
    def swagger() -> HTMLResponse:
        return docs.swagger_page(app, "/openapi.json")

    docs.mount_assets(app)


def _openapi(app: FastAPI) -> dict[str, Any]:
    """FastAPI's OpenAPI document with its default 422 responses (``HTTPValidationError``)
    replaced by the problem+json that :mod:`service.api.errors` actually answers."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description,
                             routes=app.routes, tags=app.openapi_tags)
        problem = {"$ref": "#/components/schemas/Problem"}
        for operation in (op for path in schema["paths"].values() for op in path.values()):
            response = operation.get("responses", {}).get("422")
            if response and "HTTPValidationError" in str(response):
                operation["responses"]["422"] = {
                    "description": "Well-formed but invalid (the problem is named in `detail`, "
                                   "per-field errors in `errors`).",
                    "content": {PROBLEM_JSON: {"schema": problem}}}
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        components.setdefault("Problem", Problem.model_json_schema(
            ref_template="#/components/schemas/{model}"))
        for name in ("HTTPValidationError", "ValidationError"):
            components.pop(name, None)
        app.openapi_schema = schema
    return app.openapi_schema

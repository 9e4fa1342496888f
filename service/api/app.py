"""The FastAPI application of API.md: :func:`create_app`.

Settings are injected, never read at import time: ``create_app(Settings(data_dir=tmp))``
makes an independent app (its own database, blobs, cache and metrics), which is what the
tests do; ``create_app()`` uses :func:`service.config.get_settings`. The lifespan opens the
:class:`~service.app.services.Services` (migrating the database) unless they are given, as
``facesynth serve`` does to share them with the gRPC server.
"""

from __future__ import annotations

import contextlib
from typing import Any, AsyncIterator

from fastapi import Depends, FastAPI
from fastapi.openapi.utils import get_openapi

from service.api import errors
from service.api.auth import check_bearer
from service.api.logs import RequestContextMiddleware
from service.api.errors import PROBLEM_JSON
from service.app.metrics import Metrics
from service.api.routes import (actors, artifacts, clips, health, jobs, models, rigs, scans,
                                synthesis)
from service.api.schemas import Problem
from service.app.services import Services
from service.app.synthesis import Synthesizer
from service.api.bodies import BodyLimitMiddleware
from service.config import Settings, get_settings

API_VERSION = "1"
DESCRIPTION = """\
facesynth learns, per actor, how fine skin detail (wrinkles, pores, albedo shifts) follows
large-scale facial motion, and turns sparse motion-capture markers or low-resolution meshes
into high-resolution meshes and UV-space maps.

Arrays travel as NumPy `.npz` (`application/x-npz`); errors are RFC 9457
`application/problem+json` (`{type, title, status, detail, errors?}`); long work is a job
(`202 Accepted`, `Location: /v1/jobs/{job_id}`). When the server has tokens, every `/v1`
route needs `Authorization: Bearer <token>`.
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
    {"name": "jobs", "description": "Long work: state, progress events, cancellation."},
    {"name": "artifacts", "description": "Downloadable job results."},
    {"name": "scans", "description": "Facial scans as UV-space maps, and scan correspondence "
                                     "(a job)."},
]


def create_app(settings: Settings | None = None, *, services: Services | None = None) -> FastAPI:
    """The HTTP API.

    Parameters
    ----------
    settings : Settings, optional   default: :func:`service.config.get_settings`
    services : Services, optional   already opened services to use (and not close); default:
                                    opened from ``settings`` by the app's lifespan

    Returns
    -------
    FastAPI   with ``app.state.services`` (during its lifespan), ``app.state.metrics`` and
              ``app.state.synthesizer``
    """
    settings = settings if settings is not None else (
        services.settings if services is not None else get_settings())

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        own = services is None
        app.state.services = Services.open(settings) if own else services
        try:
            yield
        finally:
            if own:
                app.state.services.close()

    app = FastAPI(title="facesynth", version=API_VERSION, description=DESCRIPTION,
                  openapi_tags=TAGS, lifespan=lifespan)
    app.state.metrics = Metrics()
    app.state.synthesizer = Synthesizer(app.state.metrics)
    errors.install(app)
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_body_bytes)
    app.add_middleware(RequestContextMiddleware, metrics=app.state.metrics)
    app.include_router(health.router)
    for module in (actors, clips, rigs, models, synthesis, jobs, artifacts, scans):
        app.include_router(module.router, dependencies=[Depends(check_bearer)])
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


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

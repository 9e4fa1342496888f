"""``POST /v1/models/{model_id}/synthesize`` on a lean ASGI path (issue 23, the per-frame
HTTP route).

FastAPI answers this route through its router (the app's included routers walked and
matched for every request), its dependency solver (the app-wide query check, the bearer
check, the services, four query parameters and a header validated by pydantic) and its
exception middleware. For a one-frame mesh request that is most of what the server spends
besides the synthesis and the encoding. Measured with the synthesis stubbed to a fixed
538 kB answer (``benchmarks/http_overhead.py``: uvicorn + httptools on uvloop, 2 cores, load
5.3, medians of 200 interleaved calls per pair), server CPU per request:

================================  =====================  ============================
server                            CPU ms (3 clients)     wall ms, SDK's client
================================  =====================  ============================
the app, FastAPI route            0.92 / 0.95 / 1.02     1.60
the app, this lean path           0.66 / 0.75 / 0.81     1.24
bare ASGI + thread hand-off       0.47 / 0.53 / 0.62     1.10
================================  =====================  ============================

In-process (the ASGI app called directly, no sockets) the route costs 0.29 ms CPU through
FastAPI and 0.13 ms here. With the real model (``benchmarks/realtime.py --against main``,
load 5, 60 frames), a mesh frame's server CPU went down by 0.4-1.4 ms on every variant and
parser.

:class:`LeanSynthesize` is the innermost middleware of the app. The request context (id,
access log, metrics), the URL guard, the body-size limit and the large-upload limiter are
outside it and apply as to every route. For a request that FastAPI would give this route
(``APIRoute.matches`` of the route itself, which no earlier route shadows: tested) whose
query string is plain, it does what FastAPI does for the route, in the same order, with the
same functions:

1. the scope gets the route's child scope (``route``, ``endpoint``, ``path_params``), so the
   metrics and the access log name the route's template;
2. the app-wide query check (:func:`service.api.query.reject_unknown_query`): here every
   parameter must be one the route declares, each flag (``clamp``, ``half``, ``topology``)
   given at most once as ``true``, ``false``, ``1`` or ``0`` (read as pydantic reads them);
3. :func:`service.api.auth.check_bearer` (401; the tenant scoped in the request's task, which
   the synthesis thread copies);
4. the route's endpoint, :func:`service.api.routes.synthesis.synthesize`, called with the
   services, the parsed query and the ``Accept`` header;
5. an error raised on the way goes to the app's own handler for it, looked up as
   Starlette's ``ExceptionMiddleware`` does (an ``int`` key for an HTTP status, else the
   error's MRO; ``Exception`` and 500 belong to the outermost error middleware); an error
   without one propagates as it would from FastAPI.

Everything else goes on to FastAPI, which answers it: another method (405), a query string
that is not plain (unknown or misspelt parameters, another spelling of a flag, which FastAPI
accepts or refuses with its own 422), an app whose ``dependency_overrides`` replace one of the
route's dependencies. So the answers are byte for byte FastAPI's (``tests/api/test_lean.py``
compares both over every refusal), and the route, still FastAPI's, keeps its OpenAPI entry.
``lean_synthesis=False`` (``FACESYNTH_LEAN_SYNTHESIS``) leaves the route to FastAPI alone.
"""

from __future__ import annotations

import inspect
from typing import Any, Callable

from fastapi.routing import APIRoute
from starlette.datastructures import QueryParams
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.routing import Match
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.auth import check_bearer
from service.api.deps import get_services
from service.api.query import declared_query, reject_unknown_query
from service.api.routes import synthesis

#: the spellings of a flag read here, as pydantic reads them; FastAPI takes any other
FLAGS = {"true": True, "false": False, "1": True, "0": False}
#: the route's flag parameters and their defaults (the endpoint's signature, checked by test)
FLAG_DEFAULTS = {"clamp": True, "half": False, "topology": True}
#: the route's dependencies that this path calls itself; an override of one leaves the
#: request to FastAPI
DEPENDENCIES = (reject_unknown_query, check_bearer, get_services)


def synthesize_route() -> APIRoute:
    """The FastAPI route of ``POST /v1/models/{model_id}/synthesize`` (the object FastAPI puts
    in a request's ``scope["route"]``)."""
    return next(route for route in synthesis.router.routes
                if isinstance(route, APIRoute) and route.endpoint is synthesis.synthesize)


def plain_query(query: QueryParams, known: frozenset[str]) -> dict[str, Any] | None:
    """The endpoint's query arguments (``outputs``, ``clamp``, ``half``, ``topology``) when
    the query string is plain (see the module docstring), else None (FastAPI answers).

    Parameters
    ----------
    query : QueryParams          the request's parsed query string (Starlette's parser)
    known : frozenset of str     the parameters the route declares
    """
    if any(name not in known for name in query.keys()):
        return None
    arguments: dict[str, Any] = {"outputs": query.getlist("outputs") or None}
    for name, default in FLAG_DEFAULTS.items():
        values = query.getlist(name)
        if not values:
            arguments[name] = default
        elif len(values) == 1 and values[0] in FLAGS:
            arguments[name] = FLAGS[values[0]]
        else:
            return None
    return arguments


def exception_handler(app: Any, error: Exception) -> Callable[..., Any] | None:
    """The handler of ``app`` (a Starlette app) that Starlette's ``ExceptionMiddleware``
    would call for ``error``: by HTTP status for an HTTP exception with a status handler,
    else the first class of the error's MRO with one; None for ``Exception`` itself and
    500, which the outermost error middleware handles."""
    handlers = app.exception_handlers
    status = getattr(error, "status_code", None)
    if isinstance(error, HTTPException) and status != 500 and status in handlers:
        return handlers[status]
    for cls in type(error).__mro__:
        if cls is Exception:
            return None
        if cls in handlers:
            return handlers[cls]
    return None


class LeanSynthesize:
    """ASGI middleware serving the synthesize route directly (see the module docstring)."""

    def __init__(self, app: ASGIApp):
        self.app = app
        self.route = synthesize_route()
        self.known = declared_query(self.route)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST":
            await self.app(scope, receive, send)
            return
        match, child_scope = self.route.matches(scope)
        if match is not Match.FULL:
            await self.app(scope, receive, send)
            return
        overrides = scope["app"].dependency_overrides
        arguments = None if overrides and any(d in overrides for d in DEPENDENCIES) else \
            plain_query(QueryParams(scope.get("query_string", b"")), self.known)
        if arguments is None:
            await self.app(scope, receive, send)
            return
        scope.update(child_scope)
        scope.setdefault("router", scope["app"].router)
        request = Request(scope, receive)
        try:
            await check_bearer(request)
            response = await synthesis.synthesize(
                scope["path_params"]["model_id"], request, await get_services(request),
                accept=request.headers.get("accept"), **arguments)
        except Exception as error:
            handler = exception_handler(scope["app"], error)
            if handler is None:
                raise
            response = handler(request, error)
            if inspect.isawaitable(response):
                response = await response
        await response(scope, receive, send)

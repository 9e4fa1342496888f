"""The ASGI middleware that gives every request an id, logs it and times it for the metrics
(the JSON log format itself is :mod:`service.logs`).

A request's id is its ``X-Request-ID`` header when that is a short token of safe characters,
else a fresh one; it is echoed in the response's ``X-Request-ID``, put in problem bodies
(``request_id``) and in every log record written while the request is served.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
import uuid

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.app.limits import REQUEST_ID_MAX_LENGTH
from service.app.metrics import Metrics
from service.logs import request_id_var

_SAFE_ID = re.compile(rf"[A-Za-z0-9._:-]{{1,{REQUEST_ID_MAX_LENGTH}}}")
access_log = logging.getLogger("facesynth.access")
error_log = logging.getLogger("facesynth.api")


def request_id_from(scope: Scope) -> str:
    """The client's ``X-Request-ID`` if it is safe to echo and log, else a new id."""
    for key, value in scope.get("headers", ()):
        if key == b"x-request-id":
            candidate = value.decode("latin-1")
            if _SAFE_ID.fullmatch(candidate):
                return candidate
            break
    return uuid.uuid4().hex


class RequestContextMiddleware:
    """Pure ASGI middleware (streaming responses pass through untouched): assigns the
    request id, adds ``X-Request-ID`` to the response, logs one access line per request and
    records its latency by route template in ``metrics``.

    An exception no handler took is logged with its traceback *and the request's id* and
    answered here as a 500 problem; every response of status 500 or more carries
    ``Connection: close`` (the server closes the connection after it, and a client's
    connection pool must not reuse it).

    The log line and the metrics come one event-loop iteration after the answer's last
    piece, once a coalesced transport has handed it to the socket: on the level-1 mesh
    frame they took 0.19 ms that the client otherwise waited for (timestamps on the
    server, median of 200 SDK calls).
    """

    def __init__(self, app: ASGIApp, metrics: Metrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = request_id_from(scope)
        scope.setdefault("state", {})["request_id"] = request_id
        token = request_id_var.set(request_id)
        start = time.perf_counter()
        status = 500
        started = False

        async def send_with_id(message: Message) -> None:
            nonlocal status, started
            if message["type"] == "http.response.start":
                status, started = message["status"], True
                headers = [*message.get("headers", []), (b"x-request-id", request_id.encode())]
                if status >= 500 and not any(k.lower() == b"connection" for k, _ in headers):
                    headers.append((b"connection", b"close"))   # the server will close it
                message["headers"] = headers
            await send(message)
            if message["type"] == "http.response.body" and not message.get("more_body", False):
                # the answer is complete; a coalesced transport hands it to the socket at the
                # end of this loop iteration (service.api.coalesced_writes): end the
                # iteration here, so the client reads it while the log line and the metrics
                # are written, not after them
                await asyncio.sleep(0)

        try:
            try:
                await self.app(scope, receive, send_with_id)
            except Exception:
                # logged here, while the request id is still set (Starlette's outermost
                # error middleware runs after it was reset), and answered here, so the
                # connection ends with 'Connection: close' instead of a reset
                error_log.exception("unhandled error on %s %s", scope["method"], scope["path"])
                if started:
                    raise
                from starlette.requests import Request

                from service.api.errors import problem

                await problem(Request(scope), 500, "internal error (see the server log for this "
                              "request id)", slug="internal")(scope, receive, send_with_id)
        finally:
            seconds = time.perf_counter() - start
            route = scope.get("route")
            template = getattr(route, "path", None) or "<unmatched>"
            self.metrics.observe_request(scope["method"], template, status, seconds)
            access_log.info("%s %s %d", scope["method"], scope["path"], status,
                            extra={"method": scope["method"], "path": scope["path"],
                                   "route": template, "status": status,
                                   "duration_ms": round(seconds * 1e3, 2)})
            request_id_var.reset(token)

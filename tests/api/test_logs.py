"""service.api.logs: the request context middleware's order of work around an answer."""

from __future__ import annotations

import asyncio
import logging

from service.api.logs import RequestContextMiddleware
from service.app.metrics import Metrics


class _Recorder(logging.Handler):
    def __init__(self, events: list[str]):
        super().__init__()
        self.events = events

    def emit(self, record: logging.LogRecord) -> None:
        self.events.append(f"logged {record.getMessage()}")


def test_the_answer_is_handed_on_before_the_access_line_is_written():
    """A transport that flushes at the end of the loop iteration (as CoalescedWrites does)
    gets the whole answer out before the middleware writes its log line; the pieces keep
    their order, and a piece with more to come does not yield."""
    events: list[str] = []

    async def app(scope, receive, send):
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"a", "more_body": True})
        events.append("app between pieces")
        await send({"type": "http.response.body", "body": b"b"})
        events.append("app done")

    async def run() -> None:
        loop = asyncio.get_running_loop()
        kept: list[bytes] = []

        async def send(message):
            if message["type"] == "http.response.body":
                if not kept:
                    loop.call_soon(lambda: events.append("flushed " + b"".join(kept).decode()))
                kept.append(message["body"])

        async def receive():
            return {"type": "http.request", "body": b"", "more_body": False}

        scope = {"type": "http", "method": "GET", "path": "/x", "headers": []}
        await RequestContextMiddleware(app, Metrics())(scope, receive, send)

    handler = _Recorder(events)
    logger = logging.getLogger("facesynth.access")
    logger.addHandler(handler)
    level, disabled = logger.level, logger.disabled    # as another test's log setup left them
    logger.setLevel(logging.INFO)
    logger.disabled = False
    try:
        asyncio.run(run())
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.disabled = disabled
    assert events == ["app between pieces", "flushed ab", "app done", "logged GET /x 200"]

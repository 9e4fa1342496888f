"""The edge of the HTTP API: what is refused before any route runs (issue 16, defect 7).

:class:`UrlGuardMiddleware` answers ``422`` problem+json when the request's path or query
string, percent-decoded, holds a NUL byte or is not valid UTF-8. Such text would otherwise
travel to the database (``GET /v1/jobs?kind=%00`` failed inside PostgreSQL as a 500) or
into stored names; no route takes NUL, and no id, name or filter value is binary.
"""

from __future__ import annotations

from urllib.parse import unquote_to_bytes

from starlette.requests import Request
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.errors import problem


def url_problem(scope: Scope) -> str | None:
    """What is wrong with the request's path or query string, or None."""
    raw_path = scope.get("raw_path") or scope.get("path", "").encode("utf-8", "surrogateescape")
    query = scope.get("query_string", b"")
    for where, raw in (("path", raw_path), ("query string", query)):
        # '+' is a space in a query string; it cannot hide a NUL, so plain unquoting suffices
        decoded = unquote_to_bytes(raw)
        if b"\x00" in decoded:
            return (f"the URL's {where} holds a NUL byte (%00) at decoded position "
                    f"{decoded.index(0)}; no parameter accepts one")
        try:
            decoded.decode("utf-8")
        except UnicodeDecodeError as error:
            return (f"the URL's {where} is not valid UTF-8 once percent-decoded (byte "
                    f"0x{decoded[error.start]:02x} at position {error.start})")
    return None


class UrlGuardMiddleware:
    """Refuses URLs with NUL bytes or invalid UTF-8 (see the module docstring)."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            reason = url_problem(scope)
            if reason is not None:
                await problem(Request(scope), 422, reason, slug="invalid-input")(scope, receive,
                                                                                send)
                return
        await self.app(scope, receive, send)

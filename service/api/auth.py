"""Bearer-token authentication (API.md: ``Authorization: Bearer <token>`` when the server
is configured with tokens; with none configured it only listens on loopback, which
``facesynth serve`` enforces)."""

from __future__ import annotations

import hmac
from typing import Sequence

from fastapi import Request

from service.api.errors import Unauthorized


def token_matches(given: str, tokens: Sequence[str]) -> bool:
    """Whether ``given`` is one of ``tokens``, compared in constant time (every token is
    compared, whatever matches first)."""
    given_bytes = given.encode()
    return sum(hmac.compare_digest(given_bytes, t.encode()) for t in tokens) > 0


def check_bearer(request: Request) -> None:
    """Dependency of every ``/v1`` route: refuse the request unless it carries a configured
    token (a no-op when no tokens are configured).

    Raises
    ------
    Unauthorized   401 with ``WWW-Authenticate: Bearer``
    """
    tokens = request.app.state.services.settings.tokens
    if not tokens:
        return
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise Unauthorized("this server requires 'Authorization: Bearer <token>'")
    if not token_matches(token.strip(), tokens):
        raise Unauthorized("the bearer token is not valid")

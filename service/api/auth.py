"""Bearer-token authentication and the tenant a request acts for (API.md: ``Authorization:
Bearer <token>`` when the server is configured with tokens; with none configured it only
listens on loopback, which ``facesynth serve`` enforces).

:func:`check_bearer` is the dependency of every ``/v1`` route (and of ``/healthz``,
``/readyz``, ``/metrics`` and the docs when their ``public_*`` setting is false). It finds
the token's :class:`~models_store.tenancy.Principal` in the configured
:class:`~models_store.tenancy.TokenTable` (constant-time, digests only) and scopes the rest
of the request to its tenant (:func:`models_store.registry.acting_for` semantics, through the
registry's context variables): listings show only the tenant's rows, another tenant's ids
answer 404, new actors belong to it. An admin token is scoped to every tenant. Without
tokens every request acts as :data:`~models_store.tenancy.ANONYMOUS` (an admin of
``default``).
"""

from __future__ import annotations

import hmac
from typing import Sequence

from fastapi import Request

from models_store.registry import TENANT_OWNER, TENANT_SCOPE
from service.api.errors import Unauthorized
from service.config import Settings
from models_store.tenancy import ANONYMOUS, Principal, TokenTable


def token_matches(given: str, tokens: Sequence[str]) -> bool:
    """Whether ``given`` is one of the plain ``tokens``, compared in constant time (every
    token is compared, whatever matches first)."""
    given_bytes = given.encode()
    return sum(hmac.compare_digest(given_bytes, t.encode()) for t in tokens) > 0


def token_table(request: Request) -> TokenTable:
    """The app's token table (made once from its settings)."""
    table = getattr(request.app.state, "token_table", None)
    if table is None:
        settings: Settings = request.app.state.services.settings
        table = request.app.state.token_table = TokenTable(settings.tokens)
    return table


def principal_of(request: Request) -> Principal:
    """Who the request acts for; :class:`Unauthorized` (401) without a valid token when
    tokens are configured."""
    table = token_table(request)
    if not table:
        return ANONYMOUS
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise Unauthorized("this server requires 'Authorization: Bearer <token>'")
    principal = table.authenticate(token.strip())
    if principal is None:
        raise Unauthorized("the bearer token is not valid")
    return principal


async def check_bearer(request: Request) -> Principal:
    """Dependency of every ``/v1`` route: authenticate, then scope the request to the token's
    tenant (see the module docstring).

    It is ``async`` on purpose: it runs in the request's own task, so the tenant it sets is
    seen by the route and by the threads the route hands work to (they copy the task's
    context), and by no other request.

    Raises
    ------
    Unauthorized   401 with ``WWW-Authenticate: Bearer``
    """
    principal = principal_of(request)
    request.state.principal = principal
    TENANT_OWNER.set(principal.tenant)
    TENANT_SCOPE.set(principal.scope)
    return principal

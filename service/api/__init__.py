"""The HTTP API (API.md): ``create_app(settings) -> FastAPI``.

HTTP only: :mod:`.app` (the app factory), :mod:`.routes` (thin routers, one per resource,
each calling one function of :mod:`service.app`), :mod:`.bodies` (media types, body reading
and its size limit), :mod:`.schemas` (the problem body), :mod:`.errors` (problem+json, the
one mapping of :mod:`service.errors` to statuses), :mod:`.auth`, :mod:`.deps`, :mod:`.logs`.
"""

from service.api.app import create_app

__all__ = ["create_app"]

"""The HTTP API (API.md): ``create_app(settings) -> FastAPI``.

Modules: :mod:`.app` (the app factory), :mod:`.routes` (thin routers, one per resource),
:mod:`.operations` (what each write does), :mod:`.uploads` (reading and validating bodies),
:mod:`.synthesis` (synchronous synthesis and its encodings), :mod:`.schemas` (pydantic
models), :mod:`.errors` (problem+json), :mod:`.auth`, :mod:`.deps`, :mod:`.services`
(database, blobs, model cache), :mod:`.metrics`, :mod:`.logs`, :mod:`.validation`,
:mod:`.limits`.
"""

from service.api.app import create_app

__all__ = ["create_app"]

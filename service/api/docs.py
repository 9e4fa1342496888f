"""``/docs`` (Swagger UI) and ``/redoc`` served without a CDN, for offline studio networks.

FastAPI's own pages load their scripts and styles from a public CDN, so they are blank where
the network has no way out. Here the assets come from the ``fastapi-offline`` package, which
bundles a current Swagger UI (5.x, which renders OpenAPI 3.1) and ReDoc as static files;
they are mounted at :data:`STATIC_URL` and the pages reference only that path.

The pages are plain Starlette routes (not API routes): no bearer token and no query check.
"""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import FastAPI
from fastapi.openapi.docs import (get_redoc_html, get_swagger_ui_html,
                                  get_swagger_ui_oauth2_redirect_html)
from fastapi.staticfiles import StaticFiles
from starlette.requests import Request
from starlette.responses import HTMLResponse

#: where the bundled assets are served
STATIC_URL = "/docs-static"
#: the package's directory of assets (swagger-ui-bundle.js, swagger-ui.css, redoc.standalone.js)
ASSETS = Path(fastapi_offline.__file__).parent / "static"


def mount_assets(app: FastAPI) -> None:
    """The bundled Swagger UI and ReDoc files at :data:`STATIC_URL`."""
    app.mount(STATIC_URL, StaticFiles(directory=ASSETS), name="docs-static")


def swagger_page(app: FastAPI, openapi_url: str, root: str = "") -> HTMLResponse:
    """The Swagger UI page for ``openapi_url``, loading only the bundled assets."""
    redirect = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"
    return get_swagger_ui_html(
        openapi_url=f"{root}{openapi_url}", title=f"{app.title} - Swagger UI",
        oauth2_redirect_url=f"{root}{redirect}",
        swagger_js_url=f"{root}{STATIC_URL}/swagger-ui-bundle.js",
        swagger_css_url=f"{root}{STATIC_URL}/swagger-ui.css",
        swagger_favicon_url=f"{root}{STATIC_URL}/favicon.png",
        swagger_ui_parameters=app.swagger_ui_parameters)


def install(app: FastAPI) -> None:
    """Serve ``/docs``, its OAuth2 redirect page and ``/redoc`` from local assets on ``app``
    (created with ``docs_url=None, redoc_url=None``)."""
    mount_assets(app)
    redirect = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"

    async def swagger(request: Request) -> HTMLResponse:
        return swagger_page(app, app.openapi_url, request.scope.get("root_path", ""))

    async def oauth2_redirect(request: Request) -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_redoc_html(openapi_url=f"{root}{app.openapi_url}", title=f"{app.title} - ReDoc",
                              redoc_js_url=f"{root}{STATIC_URL}/redoc.standalone.js",
                              redoc_favicon_url=f"{root}{STATIC_URL}/favicon.png",
                              with_google_fonts=False)

    app.add_route("/docs", swagger, include_in_schema=False)
    app.add_route(redirect, oauth2_redirect, include_in_schema=False)
    app.add_route("/redoc", redoc, include_in_schema=False)

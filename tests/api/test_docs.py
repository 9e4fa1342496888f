"""service/api/docs.py: /docs and /redoc reference no external host, and their assets are
served from the bundled package."""

from __future__ import annotations

import re
from urllib.parse import urlsplit

import pytest

#: src/href/url(...) attributes and string URLs in a page
_URL = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']|url:\s*["']([^"']+)["']|["'](https?://[^"']+)["']""")


def _references(html: str) -> list[str]:
    return [next(g for g in m.groups() if g) for m in _URL.finditer(html)]


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_reference_no_external_host(client, page):
    response = client.get(page)
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/html")
    refs = _references(response.text)
    assert refs, "the page references its assets"
    external = [r for r in refs if urlsplit(r).netloc or r.startswith("//")]
    assert external == [], external
    assert "cdn" not in response.text.lower() and "googleapis" not in response.text
    # every local asset the page loads is served, non-empty
    for ref in refs:
        if ref.startswith("/docs-static/"):
            asset = client.get(ref)
            assert asset.status_code == 200 and len(asset.content) > 1000, ref


def test_swagger_ui_bundle_renders_openapi_31(client):
    """FastAPI writes OpenAPI 3.1, which Swagger UI renders from 5.0 on."""
    assert client.get("/openapi.json").json()["openapi"].startswith("3.1")
    js = client.get("/docs-static/swagger-ui-bundle.js").text
    versions = [tuple(map(int, v.split("."))) for v in re.findall(r'"(5\.\d+\.\d+)"', js)]
    assert versions and max(versions) >= (5, 0, 0)

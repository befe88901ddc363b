"""``/docs`` and ``/redoc`` (service/api/routes/docs.py), in process: they load only files the
service serves itself (so they work offline), and those files are there with their types."""

from __future__ import annotations

import re
from collections.abc import Callable
from html.parser import HTMLParser

from fastapi.testclient import TestClient

from service.api.routes.docs import ASSET_PREFIX, ASSETS
from tests.service.conftest import assert_problem
from tests.service.routes.conftest import KEY


class _Urls(HTMLParser):
    """Every URL a page loads: ``src``, ``href`` and ReDoc's ``spec-url`` attributes, and
    URLs in its scripts."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.urls += [v for k, v in attrs if k in ("src", "href", "spec-url") and v]

    def handle_data(self, data: str) -> None:
        self.urls += re.findall(r"""["'`]((?:https?:)?//[^"'`]+|/[\w./-]+)["'`]""", data)


def page_urls(html: str) -> list[str]:
    parser = _Urls()
    parser.feed(html)
    return parser.urls


def test_docs_pages_load_only_local_files(make_client: Callable[..., TestClient]) -> None:
    client = make_client(api_key=KEY)  # the docs are public: no key sent
    loaded: set[str] = set()
    for path in ("/docs", "/redoc"):
        response = client.get(path)
        assert response.status_code == 200, path
        assert response.headers["content-type"].startswith("text/html")
        csp = response.headers["content-security-policy"]
        assert "default-src 'self'" in csp and "img-src 'self' data: blob:;" in csp
        urls = page_urls(response.text)
        assert urls, path
        for url in urls:
            assert url.startswith("/") and not url.startswith("//"), (path, url)
        assert "/openapi.json" in urls, path
        loaded |= {u for u in urls if u.startswith(ASSET_PREFIX)}
    # every vendored file is used by a page, and each is served with its type
    assert loaded == {f"{ASSET_PREFIX}/{name}" for name in ASSETS}
    for url in sorted(loaded):
        response = client.get(url)
        assert response.status_code == 200, url
        media_type = ASSETS[url.rsplit("/", 1)[1]][1]
        assert response.headers["content-type"] == media_type, url
        assert response.headers["x-content-type-options"] == "nosniff"
        assert len(response.content) > 500, url
    assert client.get("/openapi.json").status_code == 200


def test_docs_files_are_the_real_bundles(client: TestClient) -> None:
    swagger = client.get(f"{ASSET_PREFIX}/swagger-ui-bundle.js").text
    assert "SwaggerUIBundle" in swagger
    assert ".swagger-ui" in client.get(f"{ASSET_PREFIX}/swagger-ui.css").text
    assert "Redoc" in client.get(f"{ASSET_PREFIX}/redoc.standalone.js").text
    icon = client.get(f"{ASSET_PREFIX}/favicon-32x32.png").content
    assert icon.startswith(b"\x89PNG\r\n\x1a\n")


def test_oauth2_redirect_and_unknown_docs_file(client: TestClient) -> None:
    redirect = client.get("/docs/oauth2-redirect")
    assert redirect.status_code == 200
    assert "oauth2" in redirect.text.lower()
    for name in ("LICENSE", "swagger-ui.js", "nope.css"):
        problem = assert_problem(client.get(f"{ASSET_PREFIX}/{name}"), 404)
        assert problem["type"] == "/problems/not-found"

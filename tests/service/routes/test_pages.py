"""``/`` and ``/ui`` (service/api/routes/pages.py), in process."""

from __future__ import annotations

from collections.abc import Callable

from fastapi.testclient import TestClient

from service.api.routes.pages import ASSETS
from tests.service.conftest import assert_problem
from tests.service.routes.conftest import KEY


def test_root_redirects_to_the_page(client: TestClient) -> None:
    response = client.get("/", follow_redirects=False)
    assert response.status_code == 307
    assert response.headers["location"] == "/ui"


def test_page_and_its_files_are_public_with_their_types(
    make_client: Callable[..., TestClient],
) -> None:
    client = make_client(api_key=KEY)  # no key sent: the page asks for it
    page = client.get("/ui")
    assert page.status_code == 200
    assert page.headers["content-type"] == "text/html; charset=utf-8"
    assert "default-src 'self'" in page.headers["content-security-policy"]
    for name, media_type in ASSETS.items():
        assert f"/ui/{name}" in page.text, name
        response = client.get(f"/ui/{name}")
        assert response.status_code == 200, name
        assert response.headers["content-type"] == media_type
        assert response.headers["x-content-type-options"] == "nosniff"
        assert response.content
    assert_problem(client.get("/v1/collections"), 401)


def test_unknown_page_file_is_404(client: TestClient) -> None:
    for name in ("index.html", "nope.js"):
        problem = assert_problem(client.get(f"/ui/{name}"), 404)
        assert problem["type"] == "/problems/not-found"
        assert name in problem["detail"]
    assert_problem(client.get("/ui/..%2Fmain.py"), 404)
    assert_problem(client.get("/ui/static/app.js"), 404)

"""``/docs`` and ``/redoc`` in a real headless Chromium with every other host blocked: the API
docs must render their operations from the files the service serves itself (archives often
run without internet). Same browser set-up as the results page's test (Debian's Chromium
under Playwright; skipped without them unless ``REGTREE_REQUIRE_BROWSER=1``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

from tests.service.conftest import Service
from tests.service.test_page_browser import Browser, browser  # noqa: F401  (the fixture)


def _block_other_hosts(page: Any, base_url: str) -> list[str]:
    """Abort every request to another host than the service's; the list of those asked."""
    own = urlsplit(base_url).netloc
    blocked: list[str] = []

    def handle(route: Any) -> None:
        url = route.request.url
        if urlsplit(url).scheme in ("data", "blob") or urlsplit(url).netloc == own:
            route.continue_()
        else:
            blocked.append(url)
            route.abort()

    page.route("**/*", handle)
    return blocked


def test_docs_render_offline(
    browser: Browser,  # noqa: F811
    make_service: Callable[..., Service],
) -> None:
    from playwright.sync_api import expect

    svc = make_service(workers=0).start()
    page = browser.page
    blocked = _block_other_hosts(page, svc.base_url)
    with svc.client() as client:
        paths = client.get("/openapi.json").json()["paths"]
    n_operations = sum(
        1 for item in paths.values() for method in item if method in ("get", "post", "delete")
    )

    page.goto(f"{svc.base_url}/docs")
    operations = page.locator(".swagger-ui .opblock")
    expect(operations.first).to_be_visible()
    assert operations.count() == n_operations
    expect(page.locator(".swagger-ui .opblock-summary-path").first).to_be_visible()
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("regtree")

    page.goto(f"{svc.base_url}/redoc")
    expect(page.locator("h1").first).to_contain_text("regtree")
    expect(page.locator("[data-section-id^='operation/']").first).to_be_attached()
    assert page.locator("[data-section-id^='operation/']").count() == n_operations

    assert blocked == []
    # the page's CSP keeps ReDoc from asking a CDN for the logo of its badge (then left out)
    assert [e for e in browser.errors if "cdn.redoc.ly" not in e] == []

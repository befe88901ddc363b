"""The API docs, ``/docs`` (Swagger UI) and ``/redoc``, with their scripts served from the
package: archives often run without internet, where CDN-hosted docs pages stay blank.

The files are the unmodified distribution files of the npm packages ``swagger-ui-dist`` and
``redoc`` with their licences, in ``service/static/vendor/`` (its ``README.md`` says which
versions and how to update them). Like the API document, the pages and their files are
served without an API key (:data:`service.api.middleware.PUBLIC_PATHS`).
"""

from __future__ import annotations

from importlib import resources

from fastapi import APIRouter, FastAPI
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse, Response

from service.api.problems import ProblemError

ASSET_PREFIX = "/docs/assets"

#: URL name -> (folder under ``static/vendor``, media type).
ASSETS = {
    "swagger-ui-bundle.js": ("swagger-ui", "text/javascript; charset=utf-8"),
    "swagger-ui.css": ("swagger-ui", "text/css; charset=utf-8"),
    "favicon-32x32.png": ("swagger-ui", "image/png"),
    "redoc.standalone.js": ("redoc", "text/javascript; charset=utf-8"),
}
#: The docs pages and their files, answered without an API key.
DOCS_PATHS = frozenset(
    {"/docs", "/docs/oauth2-redirect", "/redoc", *(f"{ASSET_PREFIX}/{n}" for n in ASSETS)}
)

#: The pages load scripts, styles and the API document from this service only (their inline
#: start-up script aside): the CSP also keeps ReDoc from asking a CDN for its badge's logo,
#: which it then leaves out.
_PAGE_CSP = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data: blob:; font-src 'self' data:; worker-src 'self' blob:; "
    "object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
)

_ASSET_HEADERS = {
    # the files change only with the service's version
    "Cache-Control": "public, max-age=86400",
    "X-Content-Type-Options": "nosniff",
}


def _asset_url(name: str) -> str:
    return f"{ASSET_PREFIX}/{name}"


def _local_only(page: HTMLResponse) -> HTMLResponse:
    page.headers["Content-Security-Policy"] = _PAGE_CSP
    page.headers["X-Content-Type-Options"] = "nosniff"
    return page


def install_docs(app: FastAPI, openapi_url: str = "/openapi.json") -> None:
    """Add ``/docs``, ``/docs/oauth2-redirect``, ``/redoc`` and their files to ``app``
    (created with ``docs_url=None, redoc_url=None``)."""
    router = APIRouter(include_in_schema=False)
    title = app.title

    @router.get("/docs")
    def swagger_ui() -> HTMLResponse:
        return _local_only(get_swagger_ui_html(
            openapi_url=openapi_url,
            title=f"{title} - Swagger UI",
            oauth2_redirect_url="/docs/oauth2-redirect",
            swagger_js_url=_asset_url("swagger-ui-bundle.js"),
            swagger_css_url=_asset_url("swagger-ui.css"),
            swagger_favicon_url=_asset_url("favicon-32x32.png"),
            # the default validator badge asks a public validator about the document
            swagger_ui_parameters={"validatorUrl": None},
        ))

    @router.get("/docs/oauth2-redirect")
    def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @router.get("/redoc")
    def redoc() -> HTMLResponse:
        return _local_only(get_redoc_html(
            openapi_url=openapi_url,
            title=f"{title} - ReDoc",
            redoc_js_url=_asset_url("redoc.standalone.js"),
            redoc_favicon_url=_asset_url("favicon-32x32.png"),
            with_google_fonts=False,
        ))

    @router.get(ASSET_PREFIX + "/{name}")
    def asset(name: str) -> Response:
        if name not in ASSETS:
            raise ProblemError(404, f"no docs file {name}", type_="/problems/not-found")
        folder, media_type = ASSETS[name]
        path = resources.files("service") / "static" / "vendor" / folder / name
        try:
            body = path.read_bytes()
        except FileNotFoundError as e:  # an install without the package data
            raise ProblemError(404, f"docs file {name} is not installed") from e
        return Response(body, media_type=media_type, headers=_ASSET_HEADERS)

    app.include_router(router)

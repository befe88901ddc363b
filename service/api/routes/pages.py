"""The results page: plain HTML, CSS and JavaScript from ``service/static``, no build step.

The files hold no data, so they are served without an API key (their paths are in
:data:`service.api.middleware.PUBLIC_PATHS`); the page asks for the key when the API answers
401, keeps it in the tab's ``sessionStorage`` and sends it as ``X-API-Key``. Everything the
page shows comes from the ``/v1`` API, pictures included.
"""

from __future__ import annotations

from importlib import resources

from fastapi import APIRouter
from fastapi.responses import RedirectResponse, Response

from service.api.problems import ProblemError
from service.contract.names import ProblemType

router = APIRouter(include_in_schema=False)

#: The page's JavaScript: ES modules, ``app.js`` the entry (routing, lists, the job), the
#: others one part each (no build step; the browser resolves their imports).
SCRIPTS = ("app.js", "core.js", "tree.js", "search.js", "subjects.js", "grouping.js")
#: File name -> media type of what ``/ui/<name>`` serves.
ASSETS = {
    **{name: "text/javascript; charset=utf-8" for name in SCRIPTS},
    "app.css": "text/css; charset=utf-8",
    "favicon.svg": "image/svg+xml",
}
#: Paths of the page, answered without an API key.
PAGE_PATHS = frozenset({"/", "/ui", *(f"/ui/{name}" for name in ASSETS)})

_HEADERS = {
    # revalidate every time: the files change with the service, and they are small
    "Cache-Control": "no-cache",
    "X-Content-Type-Options": "nosniff",
}
_PAGE_HEADERS = {
    **_HEADERS,
    # everything the page loads comes from this service; pictures arrive as blob: URLs
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; "
    "style-src 'self' 'unsafe-inline'; object-src 'none'; base-uri 'none'; "
    "frame-ancestors 'none'",
    "Referrer-Policy": "no-referrer",
}


def _read(name: str) -> bytes:
    try:
        return (resources.files("service") / "static" / name).read_bytes()
    except FileNotFoundError as e:  # an install without the package data
        raise ProblemError(404, f"page file {name} is not installed") from e


@router.get("/")
def root() -> RedirectResponse:
    return RedirectResponse("/ui", status_code=307)


@router.get("/ui")
def page() -> Response:
    return Response(_read("index.html"), media_type="text/html; charset=utf-8",
                    headers=_PAGE_HEADERS)  # fmt: skip


@router.get("/ui/{name}")
def asset(name: str) -> Response:
    if name not in ASSETS:
        raise ProblemError(404, f"no page file {name}", type_=ProblemType.NOT_FOUND)
    return Response(_read(name), media_type=ASSETS[name], headers=_HEADERS)

"""How every picture route answers: key, revalidation, drawing and the response.

A succeeded job's result never changes, so each picture gets a strong ``ETag`` made of the job
id, its ``finished_at``, the picture's options and the renderer's version; a request whose
``If-None-Match`` matches is answered 304 without reading the result or drawing anything.
Nothing is cached on the server. ``Cache-Control: private, no-cache`` makes clients revalidate
(the job may be deleted; an API key may guard it), which costs one cheap 304.

:func:`cached_picture` is that sequence once; the routes (``routes/pictures.py``,
``routes/grouping.py``) say only which job, which key and what to draw.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

from fastapi import APIRouter, Query, Request, Response
from fastapi.types import DecoratedCallable
from sqlalchemy.orm import Session

from service import __version__
from service.api.deps import DbDep
from service.api.problems import problem_responses
from service.models import Job

if TYPE_CHECKING:  # matplotlib is imported on the first picture, not when the server starts
    from service.plots import Rendered

logger = logging.getLogger("regtree.pictures")

#: Bump when a picture changes for the same input, so clients do not keep a stale copy.
RENDER_VERSION = "3"

WidthQuery = Annotated[
    int | None,
    Query(ge=200, le=4000, description="Picture width in pixels; by default sized to fit."),
]

#: What :func:`cached_picture`'s ``locate`` found, handed on to its ``load``.
Found = TypeVar("Found")


def image_responses(media_type: str, *statuses: int) -> dict[int | str, dict[str, Any]]:
    """The ``responses=`` of a picture route: the picture, 304 and the problems it may give."""
    return {
        200: {
            "content": {media_type: {}},
            "description": "The picture.",
            "headers": {
                "ETag": {"schema": {"type": "string"}},
                "X-Picture-Size": {"description": "Width x height in pixels.",
                                   "schema": {"type": "string", "example": "900x640"}},
                "X-Missing-Glyphs": {
                    "description": "Only when some characters of the names have no installed "
                    "font and are drawn as boxes: their code points.",
                    "schema": {"type": "string", "example": "U+6C38"},
                },
            },
        },
        304: {"description": "Not modified (the `If-None-Match` ETag matches)."},
        **problem_responses(*statuses),
    }


def picture_route(router: APIRouter, path: str, summary: str, description: str | None = None,
                  *, media_type: str = "image/png", gone: bool = False
                  ) -> Callable[[DecoratedCallable], DecoratedCallable]:
    """``router.get`` for a picture: its media type, 304 and problems 404, 409 and 422 (and 410
    when it draws shapes that may have been ``gone`` since the job ran)."""
    statuses = (404, 409, 410, 422) if gone else (404, 409, 422)
    return router.get(path, response_class=Response, summary=summary, description=description,
                      responses=image_responses(media_type, *statuses))


def picture_etag(job: Job, *parts: object) -> str:
    """The strong ETag of one picture of ``job`` drawn with the options ``parts``."""
    finished = job.finished_at.isoformat() if job.finished_at else ""
    key = "|".join(str(p) for p in (job.id, finished, RENDER_VERSION, __version__, *parts))
    return '"' + hashlib.sha256(key.encode()).hexdigest()[:32] + '"'


def _matches(request: Request, etag: str) -> bool:
    header = request.headers.get("if-none-match")
    if not header:
        return False
    tags = [t.strip().removeprefix("W/") for t in header.split(",")]
    return "*" in tags or etag in tags


def _cache_headers(etag: str) -> dict[str, str]:
    return {"ETag": etag, "Cache-Control": "private, no-cache"}


def picture_response(rendered: Rendered, etag: str) -> Response:
    """The 200 response carrying ``rendered``, with its cache and safety headers."""
    headers = _cache_headers(etag)
    headers["X-Picture-Size"] = f"{rendered.width}x{rendered.height}"
    # an SVG opened on its own is a document: it may style itself, nothing more
    headers["Content-Security-Policy"] = "default-src 'none'; style-src 'unsafe-inline'"
    headers["X-Content-Type-Options"] = "nosniff"
    missing = str(rendered.meta.get("missing_glyphs", ""))
    if missing:
        # no installed font has these characters: they are drawn as boxes. Say which (as
        # code points: header values are Latin-1) and how to fix it.
        codes = " ".join(f"U+{ord(ch):04X}" for ch in missing)
        headers["X-Missing-Glyphs"] = codes
        logger.warning("picture drawn without a font for %s; install a font that has them "
                       "(CJK: Debian package fonts-noto-cjk)", codes)
    return Response(content=rendered.data, media_type=rendered.media_type, headers=headers)


def cached_picture(
    request: Request,
    db: DbDep,
    locate: Callable[[Session], tuple[Job, tuple[object, ...], Found]],
    load: Callable[[Session, Found], Callable[[], Rendered]],
) -> Response:
    """Answer a picture request: 304 when the client holds this picture, else draw it.

    In one read session, ``locate(session)`` finds the job (raising the route's 404/409/410
    problems) and returns it, the picture's options (its key beside the job) and whatever
    ``load`` needs; when the request's ``If-None-Match`` names the ETag the answer is 304 and
    nothing more is read. Otherwise ``load(session, found)`` reads what the drawing needs and
    returns the drawing, which runs after the session is closed (matplotlib is slow; the
    database is not held meanwhile).
    """
    with db.read() as session:
        job, key, found = locate(session)
        etag = picture_etag(job, *key)
        if _matches(request, etag):
            return Response(status_code=304, headers=_cache_headers(etag))
        draw = load(session, found)
    return picture_response(draw(), etag)

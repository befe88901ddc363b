"""Pictures of a job's result: the tree (SVG/PNG), the per-layer summary and a subject's overlay.

Rendering is CPU-bound matplotlib work, so the routes are plain ``def``: FastAPI runs them in
its thread pool, and :mod:`service.plots` serialises the drawing itself on one lock.

A succeeded job's result never changes, so each picture gets a strong ``ETag`` made of the job
id, its ``finished_at``, the picture's options and the renderer's version; a request whose
``If-None-Match`` matches is answered 304 without reading the result or drawing anything.
Nothing is cached on the server. ``Cache-Control: private, no-cache`` makes clients revalidate
(the job may be deleted; an API key may guard it), which costs one cheap 304.
"""

from __future__ import annotations

import hashlib
import logging
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response
from sqlalchemy.orm import Session

from service import __version__
from service.api.deps import DbDep
from service.api.problems import ProblemError, problem_responses
from service.api.routes.results import _subject, _succeeded_job
from service.contract.names import ProblemType
from service.models import Job, Result, Shape, made_from_image
from service.plots import Rendered, render_subject, render_summary, render_tree
from service.schemas import DbId

router = APIRouter(prefix="/jobs", tags=["pictures"])
logger = logging.getLogger("regtree.pictures")

#: Bump when a picture changes for the same input, so clients do not keep a stale copy.
RENDER_VERSION = "3"


WidthQuery = Annotated[
    int | None,
    Query(ge=200, le=4000, description="Picture width in pixels; by default sized to fit."),
]


def _image_responses(media_type: str, *statuses: int) -> dict[int | str, dict[str, Any]]:
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


def _etag(job: Job, *parts: object) -> str:
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


def _not_modified(etag: str) -> Response:
    return Response(status_code=304, headers=_cache_headers(etag))


def _picture(rendered: Rendered, etag: str) -> Response:
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


def _result_document(session: Session, job_id: int) -> dict[str, Any]:
    result = session.get(Result, job_id)
    if result is None:
        raise ProblemError(409, f"job {job_id} has no stored result")
    return dict(result.document)


def _tree(job_id: int, fmt: str, width: int | None, request: Request, db: DbDep) -> Response:
    with db.read() as session:
        job = _succeeded_job(session, job_id)
        etag = _etag(job, "tree", fmt, width)
        if _matches(request, etag):
            return _not_modified(etag)
        document = _result_document(session, job_id)
    return _picture(render_tree(document, fmt=fmt, width=width), etag)


@router.get(
    "/{job_id}/result/tree.svg",
    response_class=Response,
    responses=_image_responses("image/svg+xml", 404, 409, 422),
    summary="The registration tree as SVG",
    description="Shapes by layer (the model on top), edges coloured by the child's error e, "
    "low-confidence leaves on a dashed edge as hollow grey nodes (with a legend), shapes no "
    "member could register in a box apart. Each shape's name is a `<text>` in a "
    'group `<g id="node-<shape_id>">` (`unattached-<shape_id>` in the box), so a page can '
    "make the nodes clickable.",
)
def tree_svg(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None) -> Response:
    return _tree(job_id, "svg", width, request, db)


@router.get(
    "/{job_id}/result/tree.png",
    response_class=Response,
    responses=_image_responses("image/png", 404, 409, 422),
    summary="The registration tree as PNG",
)
def tree_png(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None) -> Response:
    """The same picture as `tree.svg`, as a PNG image."""
    return _tree(job_id, "png", width, request, db)


@router.get(
    "/{job_id}/result/summary.png",
    response_class=Response,
    responses=_image_responses("image/png", 404, 409, 422),
    summary="Error e per tree layer, tree against direct CPD",
    description="Mean (bar) and 95th percentile (whisker) of e for each layer, with direct "
    "CPD's e on the same subjects beside it when the job compared with it.",
)
def summary_png(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None) -> Response:
    with db.read() as session:
        job = _succeeded_job(session, job_id)
        etag = _etag(job, "summary", width)
        if _matches(request, etag):
            return _not_modified(etag)
        document = _result_document(session, job_id)
    options: dict[str, Any] = {"width": width} if width else {}
    return _picture(render_summary(document, fmt="png", **options), etag)


@router.get(
    "/{job_id}/result/subjects/{shape_id}/overlay.png",
    response_class=Response,
    responses=_image_responses("image/png", 404, 409, 410, 422),
    summary="A subject with the model warped onto it",
    description="The subject's points (grey), the model warped onto it through the tree (red) "
    "and a sample of correspondence lines (green), titled with its layer, e and confidence "
    "(and a low-confidence leaf's reason); beside it, on the same axes, direct CPD's "
    "registration when the job computed it. An unattached subject is drawn alone with the "
    "reason. 410 when the subject's shape was deleted after the job ran.",
)
def subject_overlay_png(
    job_id: DbId,
    shape_id: DbId,
    request: Request,
    db: DbDep,
    width: WidthQuery = None,
    y_down: Annotated[
        bool | None,
        Query(
            description="Draw y growing downwards. By default: yes for shapes traced from "
            "images (pixel coordinates), no for shapes uploaded as coordinates."
        ),
    ] = None,
) -> Response:
    with db.read() as session:
        job = _succeeded_job(session, job_id)
        row = _subject(session, job_id, shape_id)
        shape = session.get(Shape, shape_id)
        if shape is None:
            raise ProblemError(
                410,
                f"shape {shape_id} was deleted after job {job_id} ran; its points are needed "
                "to draw the overlay",
                type_=ProblemType.SHAPE_DELETED,
            )
        if y_down is None:
            y_down = made_from_image(shape.source_format)
        etag = _etag(job, "overlay", shape_id, shape.n_points, width, y_down)
        if _matches(request, etag):
            return _not_modified(etag)
        subject = row.document
        points = shape.points
        method = job.method
    options: dict[str, Any] = {"width": width} if width else {}
    rendered = render_subject(subject, points, fmt="png", method=method, y_down=y_down, **options)
    return _picture(rendered, etag)

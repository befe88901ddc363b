"""Pictures of a job's result: the tree (SVG/PNG), the per-layer summary and a subject's overlay.

Rendering is CPU-bound matplotlib work, so the routes are plain ``def``: FastAPI runs them in
its thread pool, and :mod:`service.plots` serialises the drawing itself on one lock. How each
is keyed, revalidated (ETag, 304) and answered is :mod:`service.api.picture_cache`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Annotated, Any

from fastapi import APIRouter, Query, Request, Response
from sqlalchemy.orm import Session

from service.api.deps import DbDep
from service.api.picture_cache import WidthQuery, cached_picture, picture_route
from service.api.problems import ProblemError
from service.api.routes.results import _subject, _succeeded_job
from service.contract.names import ProblemType, made_from_image
from service.models import Job, Result, ResultSubject, Shape
from service.schemas import DbId

if TYPE_CHECKING:  # service.plots (matplotlib): imported on the first picture
    from service.plots import Rendered

router = APIRouter(prefix="/jobs", tags=["pictures"])

#: What an overlay needs from the session: the job's method, the subject, its shape, y down.
_Overlay = tuple[str, ResultSubject, Shape, bool]


def _result_document(session: Session, job_id: int) -> dict[str, Any]:
    result = session.get(Result, job_id)
    if result is None:
        raise ProblemError(409, f"job {job_id} has no stored result")
    return dict(result.document)


def _result_picture(job_id: int, request: Request, db: DbDep, key: tuple[object, ...],
                    draw: Callable[[dict[str, Any]], Rendered]) -> Response:
    """A picture of the whole result: ``draw(document)`` unless the client holds it."""
    return cached_picture(
        request, db,
        lambda session: (_succeeded_job(session, job_id), key, None),
        lambda session, _: partial(draw, _result_document(session, job_id)),
    )


def _tree(job_id: int, fmt: str, width: int | None, request: Request, db: DbDep) -> Response:
    from service.plots import render_tree

    return _result_picture(job_id, request, db, ("tree", fmt, width),
                           partial(render_tree, fmt=fmt, width=width))


@picture_route(
    router, "/{job_id}/result/tree.svg", "The registration tree as SVG",
    "Shapes by layer (the model on top), edges coloured by the child's error e, "
    "low-confidence leaves on a dashed edge as hollow grey nodes (with a legend), shapes no "
    "member could register in a box apart. Each shape's name is a `<text>` in a "
    'group `<g id="node-<shape_id>">` (`unattached-<shape_id>` in the box), so a page can '
    "make the nodes clickable.",
    media_type="image/svg+xml",
)
def tree_svg(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None) -> Response:
    return _tree(job_id, "svg", width, request, db)


@picture_route(router, "/{job_id}/result/tree.png", "The registration tree as PNG")
def tree_png(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None) -> Response:
    """The same picture as `tree.svg`, as a PNG image."""
    return _tree(job_id, "png", width, request, db)


@picture_route(
    router, "/{job_id}/result/summary.png", "Error e per tree layer, tree against direct CPD",
    "Mean (bar) and 95th percentile (whisker) of e for each layer, with direct "
    "CPD's e on the same subjects beside it when the job compared with it.",
)
def summary_png(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None) -> Response:
    from service.plots import render_summary

    options: dict[str, Any] = {"width": width} if width else {}
    return _result_picture(job_id, request, db, ("summary", width),
                           partial(render_summary, fmt="png", **options))


@picture_route(
    router, "/{job_id}/result/subjects/{shape_id}/overlay.png",
    "A subject with the model warped onto it",
    "The subject's points (grey), the model warped onto it through the tree (red) "
    "and a sample of correspondence lines (green), titled with its layer, e and confidence "
    "(and a low-confidence leaf's reason); beside it, on the same axes, direct CPD's "
    "registration when the job computed it. An unattached subject is drawn alone with the "
    "reason. 410 when the subject's shape was deleted after the job ran.",
    gone=True,
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
    def locate(session: Session) -> tuple[Job, tuple[object, ...], _Overlay]:
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
        down = made_from_image(shape.source_format) if y_down is None else y_down
        key = ("overlay", shape_id, shape.n_points, width, down)
        return job, key, (job.method, row, shape, down)

    def load(_session: Session, found: _Overlay) -> Callable[[], Rendered]:
        from service.plots import render_subject

        method, row, shape, down = found
        options: dict[str, Any] = {"width": width} if width else {}
        return partial(render_subject, row.document, shape.points, fmt="png", method=method,
                       y_down=down, **options)

    return cached_picture(request, db, locate, load)

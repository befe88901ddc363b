"""A grouping job's result and pictures (issue 11): ``/v1/jobs/{job_id}/groups...``.

The JSON document is :class:`service.contract.result.GroupingDocument`; the pictures follow
the other picture routes (strong ETag from the finished job, 304 on ``If-None-Match``).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Request, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.api.deps import DbDep
from service.api.picture_cache import WidthQuery, cached_picture, picture_route
from service.api.problems import ProblemError, operation
from service.api.routes.results import stored_result
from service.contract.names import GROUPING_METHOD, ProblemType, made_from_image
from service.contract.result import GroupingDocument
from service.models import Job, Shape
from service.schemas import DbId

if TYPE_CHECKING:  # service.plots (matplotlib): imported on the first picture
    from service.plots import Rendered

router = APIRouter(prefix="/jobs", tags=["grouping"])


def grouping_of(session: Session, job_id: int) -> tuple[Job, dict[str, Any]]:
    """The succeeded grouping job and its document (404 / 409 otherwise)."""
    document = dict(stored_result(session, job_id).document)
    job = session.get(Job, job_id)
    assert job is not None  # stored_result checked it
    if document.get("kind") != GROUPING_METHOD:
        raise ProblemError(
            409,
            f"job {job_id} is a registration ({job.method}), not a grouping: its result is "
            f"at /v1/jobs/{job_id}/result",
            type_=ProblemType.NOT_A_GROUPING,
        )
    return job, document


@operation(
    router.get, "/{job_id}/groups", "Read a grouping job's groups", (404, 409, 422),
    response_model=GroupingDocument,
    description="Which shapes came from one mould: each shape's group (`labels` by shape id, "
    "`instances` with confidence and representative), the groups with their representative, "
    "the distance matrix in `shape_ids` order and the average-linkage tree. 409 while the "
    "job has not succeeded, or for a registration job.",
)
def get_groups(job_id: DbId, db: DbDep) -> dict[str, Any]:
    with db.read() as session:
        return grouping_of(session, job_id)[1]


def _y_down(session: Session, shape_ids: list[int]) -> bool:
    formats = session.scalars(select(Shape.source_format).where(Shape.id.in_(shape_ids))).all()
    return bool(formats) and all(made_from_image(f) for f in formats)


def _group_picture(job_id: int, request: Request, db: DbDep, key: tuple[object, ...],
                   load: Callable[[Session, dict[str, Any]], Callable[[], Rendered]]
                   ) -> Response:
    """A picture of a grouping: 304 when the client holds it, else ``load(session, doc)()``."""
    def locate(session: Session) -> tuple[Job, tuple[object, ...], dict[str, Any]]:
        job, document = grouping_of(session, job_id)
        return job, key, document

    return cached_picture(request, db, locate, load)


@picture_route(
    router, "/{job_id}/groups/gallery.png", "The groups as a gallery",
    "One row per group (the largest 60): the representative framed in red, "
    "then its members, each titled with its shape id and confidence.",
)
def gallery_png(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None
                ) -> Response:
    def load(session: Session, document: dict[str, Any]) -> Callable[[], Rendered]:
        from service.plots.grouping import render_gallery

        ids = [int(s) for s in document["shape_ids"]]
        rows = session.scalars(select(Shape).where(Shape.id.in_(ids))).all()
        points = {s.id: s.points for s in rows}
        return partial(render_gallery, document, points, width=width,
                       y_down=_y_down(session, ids))

    return _group_picture(job_id, request, db, ("gallery", width), load)


@picture_route(
    router, "/{job_id}/groups/dendrogram.png", "The grouping's dendrogram",
    "The average-linkage tree over the mould distances, leaves coloured by "
    "group, with the cut as a dashed line.",
)
def dendrogram_png(job_id: DbId, request: Request, db: DbDep, width: WidthQuery = None
                   ) -> Response:
    from service.plots.grouping import render_dendrogram

    return _group_picture(job_id, request, db, ("dendrogram", width),
                          lambda _session, document: partial(render_dendrogram, document,
                                                             width=width))


@picture_route(
    router, "/{job_id}/groups/instances/{shape_id}.png",
    "An instance beside its group's representative",
    "The shape aligned onto its group's representative, and where their "
    "outlines differ (ink spread discounted), the largest difference circled. 404 for a "
    "shape not in the job; 410 when it or the representative was deleted since.",
    gone=True,
)
def instance_png(job_id: DbId, shape_id: DbId, request: Request, db: DbDep) -> Response:
    def locate(session: Session) -> tuple[Job, tuple[object, ...], dict[str, Any]]:
        job, document = grouping_of(session, job_id)
        instance = next((i for i in document["instances"] if i["shape_id"] == shape_id), None)
        if instance is None:
            raise ProblemError(404, f"shape {shape_id} is not in grouping job {job_id}",
                               type_=ProblemType.NOT_FOUND)
        return job, ("instance", shape_id), instance

    def load(session: Session, instance: dict[str, Any]) -> Callable[[], Rendered]:
        rep_id = int(instance["representative_shape_id"])
        shape, rep = session.get(Shape, shape_id), session.get(Shape, rep_id)
        if shape is None or rep is None:
            gone = shape_id if shape is None else rep_id
            raise ProblemError(410, f"shape {gone} was deleted after job {job_id} ran; its "
                               "points are needed to draw the comparison",
                               type_=ProblemType.SHAPE_DELETED)
        from service.plots.grouping import render_instance

        y_down = made_from_image(shape.source_format)
        return partial(render_instance, instance, shape.points, rep.points, y_down=y_down)

    return cached_picture(request, db, locate, load)

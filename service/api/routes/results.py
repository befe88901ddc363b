"""``/v1/jobs/{id}/result``: a succeeded job's result, its subjects (the root too, with the
identity transform) and their transforms, forwards (model onto subject) and inverse."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.api.deps import DbDep, SettingsDep
from service.api.problems import ProblemError, not_found, operation
from service.api.routes.jobs import _get_job
from service.contract.names import GROUPING_METHOD, SUBJECT_SORTS, ProblemType, SubjectSort
from service.contract.result import ResultDocument, SubjectDetail
from service.models import Job, JobStatus, Result, ResultSubject, Shape
from service.schemas import DbId, InverseTransformOut, TransformOut, TransformRequest

router = APIRouter(prefix="/jobs", tags=["results"])


def _succeeded_job(session: Session, job_id: int) -> Job:
    job = _get_job(session, job_id)
    if job.status != JobStatus.succeeded.value:
        detail = f"job {job_id} is {job.status}; a result exists once it has succeeded"
        if job.error:
            detail += f" (error: {job.error[:500]})"
        raise ProblemError(409, detail, type_=ProblemType.RESULT_NOT_READY)
    return job


def stored_result(session: Session, job_id: int) -> Result:
    """The stored result of a succeeded job (404 / 409 otherwise)."""
    _succeeded_job(session, job_id)
    result = session.get(Result, job_id)
    if result is None:
        raise ProblemError(409, f"job {job_id} has no stored result")
    return result


def _with_full_transform(
    document: dict[str, Any], base_of: Callable[[int], Mapping[str, Any] | None]
) -> dict[str, Any]:
    """`document` (a stored subject) with its transform's every step: stored, a subject's
    transform holds only the steps after those it shares with its parent's and a ``base``
    naming them (``CollectionResult.to_dict(shared_steps=True)``); results stored before
    that hold every step and pass unchanged."""
    transform = document.get("transform")
    if not isinstance(transform, Mapping) or "base" not in transform:
        return document
    from registration import expand_shared_steps

    try:
        full = expand_shared_steps(transform, base_of)
    except ValueError as e:
        raise ProblemError(500, f"stored result of subject {document.get('shape_id')}: {e}",
                           type_=ProblemType.INTERNAL) from e
    return {**document, "transform": full}


def _transforms_by_position(rows: Sequence[ResultSubject]
                            ) -> Callable[[int], Mapping[str, Any] | None]:
    """The stored transform of each of `rows` by its position in the job's input (what a
    transform's ``base`` names)."""
    by_index = {int(r.document.get("index", r.position)): r.document.get("transform")
                for r in rows}
    return by_index.get


def full_subjects(session: Session, job_id: int) -> list[dict[str, Any]]:
    """Every subject of a result with its heavy arrays, in the job's input order."""
    rows = session.scalars(
        select(ResultSubject)
        .where(ResultSubject.job_id == job_id)
        .order_by(ResultSubject.position)
    ).all()
    base_of = _transforms_by_position(rows)
    return [_with_full_transform(r.document, base_of) for r in rows]


def _number(value: Any) -> float | None:
    """A subject's number for sorting and filtering: None unless a finite int or float."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if np.isfinite(value) else None


def select_subjects(
    subjects: Sequence[Mapping[str, Any]],
    *,
    sort: str = "position",
    min_confidence: float | None = None,
    leaf: bool | None = None,
) -> list[Mapping[str, Any]]:
    """The subjects a result request asks for, in the order it asks for.

    ``min_confidence`` keeps subjects whose ``confidence`` is at least that (a subject
    without one, e.g. unattached, is left out); ``leaf`` keeps only low-confidence leaves
    (True) or only the others (False). ``sort`` orders by ``position`` (the job's input
    order, as stored), or by ``confidence`` / ``error`` / ``disagreement``, ascending, or
    descending with a leading "-"; subjects without that value come last either way, and
    ties keep their position order.
    """
    if sort not in SUBJECT_SORTS:
        raise ValueError(f"sort must be one of {', '.join(SUBJECT_SORTS)}; got {sort!r}")
    chosen = [s for s in subjects if isinstance(s, Mapping)]
    if leaf is not None:
        chosen = [s for s in chosen if bool(s.get("leaf", False)) is leaf]
    if min_confidence is not None:
        chosen = [
            s
            for s in chosen
            if (c := _number(s.get("confidence"))) is not None and c >= min_confidence
        ]
    if sort == "position":
        return chosen
    key = sort.removeprefix("-")
    sign = -1.0 if sort.startswith("-") else 1.0

    def order(item: tuple[int, Mapping[str, Any]]) -> tuple[int, float, int]:
        k, s = item
        value = _number(s.get(key))
        return (1, 0.0, k) if value is None else (0, sign * value, k)

    return [s for _, s in sorted(enumerate(chosen), key=order)]


RESULT_DESCRIPTION = (
    "The tree and, per subject, its place (layer, parent, path), similarity D, error e, "
    "confidence (the estimated probability, 0 to 1, that its correspondences are right; null "
    "for an unattached subject), whether it is a low-confidence leaf (a subject the tree "
    "could not accept, given its best registration once the tree stopped growing; never a "
    "parent; its reason says why), and quality (the checks of its last registration). "
    "Subjects and the tree name shapes by shape id (shape_id, parent_shape_id, "
    "path_shape_ids, tree); index, parent and path are the same as positions in the job's "
    "input. "
    "The summary counts subjects, attached ones (leaves included), leaves and unattached "
    "ones over the whole result, whatever the subjects are filtered by. "
    "min_confidence, leaf and sort choose and order the subjects listed."
)

MinConfidenceQuery = Annotated[
    float | None,
    Query(
        ge=0,
        le=1,
        description="List only subjects whose confidence is at least this (0 to 1). "
        "Subjects without a confidence (unattached ones) are left out when it is given.",
    ),
]
LeafQuery = Annotated[
    bool | None,
    Query(
        description="true: list only low-confidence leaves; false: only the other "
        "subjects (tree members and unattached ones). Not given: all."
    ),
]
SortQuery = Annotated[
    SubjectSort,
    Query(
        description="Order of the subjects: position (the default: the order of the "
        "job's shapes), confidence, error or disagreement ascending, -confidence, -error or "
        "-disagreement descending. Subjects without that value (unattached ones; for "
        "disagreement also those no symmetric finish ran for) come last either way; ties keep "
        "the position order."
    ),
]


def result_document(
    session: Session,
    job_id: int,
    *,
    full: bool = False,
    sort: str = "position",
    min_confidence: float | None = None,
    leaf: bool | None = None,
) -> dict[str, Any]:
    """The result document a request asks for: subjects chosen, ordered, full or light."""
    document = dict(stored_result(session, job_id).document)
    if document.get("kind") == GROUPING_METHOD:
        raise ProblemError(
            409,
            f"job {job_id} is a grouping: its result is at /v1/jobs/{job_id}/groups",
            type_=ProblemType.NOT_A_REGISTRATION,
        )
    if full:
        document["subjects"] = full_subjects(session, job_id)
    document["subjects"] = select_subjects(
        document.get("subjects") or [], sort=sort, min_confidence=min_confidence, leaf=leaf
    )
    return document


FullQuery = Annotated[
    bool, Query(description="Include warped points, correspondences and transforms.")
]


@operation(
    router.get, "/{job_id}/result", "Read a job's result", (404, 409, 422),
    response_model=ResultDocument, response_model_exclude_unset=True,
    description=RESULT_DESCRIPTION,
)
def get_result(
    job_id: DbId,
    db: DbDep,
    full: FullQuery = False,
    min_confidence: MinConfidenceQuery = None,
    leaf: LeafQuery = None,
    sort: SortQuery = "position",
) -> dict[str, Any]:
    with db.read() as session:
        return result_document(
            session, job_id, full=full, sort=sort, min_confidence=min_confidence, leaf=leaf
        )


def root_subject(session: Session, job_id: int, document: Mapping[str, Any]) -> dict[str, Any]:
    """The model as a subject of its own result: layer 1, e 0, the identity transform and,
    while its shape exists, its points as ``warped`` (each point its own correspondence)."""
    from registration import ChainTransform, normalise

    root_id = int(document["root_shape_id"])
    position = int(document.get("root") or 0)
    shape = session.get(Shape, root_id)
    subject: dict[str, Any] = {
        "index": position,
        "position": position,
        "shape_id": root_id,
        "name": shape.name if shape is not None else str(root_id),
        "parent": None,
        "parent_shape_id": None,
        "layer": 1,
        "path": [position],
        "path_shape_ids": [root_id],
        "similarity": 0.0,
        "error": 0.0,
        "attached": True,
        "status": "tree",
        "confidence": 1.0,
        "leaf": False,
        "root": True,
        "reason": "the model (the root of the tree): the identity transform",
        "attempts": [],
    }
    names = document.get("names") or []
    if shape is None and 0 <= position < len(names):
        subject["name"] = str(names[position])
    if shape is not None:
        points = shape.points
        _, norm = normalise(points)
        subject["warped"] = points.tolist()
        subject["correspondence"] = list(range(len(points)))
        subject["probability"] = [1.0] * len(points)
    else:
        from registration import Normalization

        norm = Normalization(center=(0.0, 0.0), scale=1.0)
    transform = ChainTransform.identity(norm, position).to_dict()
    subject["transform"] = {**transform, "path_shape_ids": [root_id]}
    return subject


def _subject(session: Session, job_id: int, shape_id: int) -> ResultSubject:
    _succeeded_job(session, job_id)
    row = session.get(ResultSubject, (job_id, shape_id))
    if row is None:
        raise not_found(f"subject {shape_id} in the result of job", job_id)
    return row


def subject_document(session: Session, job_id: int, shape_id: int) -> dict[str, Any]:
    """One subject with its heavy arrays; the root's is :func:`root_subject`."""
    _succeeded_job(session, job_id)
    row = session.get(ResultSubject, (job_id, shape_id))
    if row is not None:
        return _with_full_transform(dict(row.document), _base_reader(session, job_id, row))
    result = session.get(Result, job_id)
    if result is not None and result.document.get("root_shape_id") == shape_id:
        return root_subject(session, job_id, result.document)
    raise not_found(f"subject {shape_id} in the result of job", job_id)


def _base_reader(session: Session, job_id: int, row: ResultSubject
                 ) -> Callable[[int], Mapping[str, Any] | None]:
    """The stored transforms `row`'s may refer to, by position: those of the subjects on
    its tree path, read in one query."""
    path = ((row.document.get("transform") or {}).get("path_shape_ids") or [])
    ids = [int(i) for i in path if isinstance(i, int)]
    found = session.scalars(
        select(ResultSubject).where(ResultSubject.job_id == job_id,
                                    ResultSubject.shape_id.in_(ids))
    ).all() if ids else []
    return _transforms_by_position(found)


@operation(
    router.get, "/{job_id}/result/subjects/{shape_id}",
    "Read one subject of a result: tree place, transform, correspondences, error", (404, 409),
    response_model=SubjectDetail, response_model_exclude_unset=True,
    description="The subject's place in the tree, e, confidence and quality, the model "
    "warped onto it (`warped`, the subject's coordinates), `correspondence`, and the "
    "`transform` (root normalisation, steps, subject normalisation). The model's own shape "
    "id answers too: layer 1, e 0, `root` true and the identity transform (no steps).",
)
def get_subject(job_id: DbId, shape_id: DbId, db: DbDep) -> dict[str, Any]:
    with db.read() as session:
        return subject_document(session, job_id, shape_id)


def _mapped(
    db: DbDep, job_id: int, shape_id: int, body: TransformRequest, limit: int, *, inverse: bool
) -> np.ndarray:
    """``body.points`` mapped by the subject's transform (or its inverse: NaN rows where no
    preimage was found)."""
    chain = _transform_of(db, job_id, shape_id, len(body.points), limit)
    points = np.asarray(body.points, dtype=float)
    try:
        mapped: np.ndarray = chain.apply_inverse(points) if inverse else chain.apply(points)
    except ValueError as e:
        raise ProblemError(422, str(e), type_=ProblemType.VALIDATION_ERROR) from e
    return mapped


def _transform_of(db: DbDep, job_id: int, shape_id: int, n_points: int, limit: int) -> Any:
    if n_points > limit:
        raise ProblemError(
            422,
            f"{n_points} points; at most {limit} are allowed",
            type_=ProblemType.VALIDATION_ERROR,
        )
    with db.read() as session:
        document = subject_document(session, job_id, shape_id)
    transform = document.get("transform")
    if not transform:
        raise ProblemError(
            409,
            f"shape {shape_id} has no transform in this result (it was not attached)",
            type_=ProblemType.NO_TRANSFORM,
        )
    from registration import ChainTransform

    try:
        return ChainTransform.from_dict(transform)
    except ValueError as e:
        raise ProblemError(422, str(e), type_=ProblemType.VALIDATION_ERROR) from e


@operation(
    router.post, "/{job_id}/result/subjects/{shape_id}/transform",
    "Map points from the model onto a subject with the stored transform", (404, 409, 422),
    response_model=TransformOut,
    description="The chain of registrations along the subject's tree path, applied to points "
    "in the model shape's coordinates. For the model's own shape id: the identity.",
)
def transform_points(
    job_id: DbId, shape_id: DbId, body: TransformRequest, db: DbDep, settings: SettingsDep
) -> TransformOut:
    mapped = _mapped(db, job_id, shape_id, body, settings.max_points_per_shape, inverse=False)
    if not np.isfinite(mapped).all():
        raise ProblemError(422, "the mapped points are not finite", type_=ProblemType.TRANSFORM)
    return TransformOut(
        job_id=job_id, shape_id=shape_id, points=[tuple(p) for p in mapped.tolist()]
    )


@operation(
    router.post, "/{job_id}/result/subjects/{shape_id}/inverse-transform",
    "Map points from a subject back onto the model (the inverse transform)", (404, 409, 422),
    response_model=InverseTransformOut,
    description="The inverse of the subject's transform, for points in the subject's "
    "coordinates. Affine steps are inverted exactly; CPD's warp has no closed-form inverse, "
    "so each point's preimage is solved for by Newton iterations. Each answer is checked by "
    "mapping it forwards again: it must land within 1e-6 of the subject's size of the given "
    "point (typically within 1e-12); a point for which no such preimage was found (far "
    "outside the region the warp was fitted on, or where it folds) is null, and `converged` "
    "says which.",
)
def inverse_transform_points(
    job_id: DbId, shape_id: DbId, body: TransformRequest, db: DbDep, settings: SettingsDep
) -> InverseTransformOut:
    mapped = _mapped(db, job_id, shape_id, body, settings.max_points_per_shape, inverse=True)
    ok = np.isfinite(mapped).all(axis=1)
    return InverseTransformOut(
        job_id=job_id,
        shape_id=shape_id,
        points=[(float(p[0]), float(p[1])) if k else None for p, k in zip(mapped, ok, strict=True)],
        converged=[bool(k) for k in ok],
    )

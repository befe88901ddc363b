"""``/v1/jobs``: submit, list, read and cancel registration jobs, and read their results."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response, status
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.api import idempotency
from service.api.deps import DbDep, IdempotencyKeyDep, PaginationDep, SettingsDep
from service.api.problems import ProblemError, not_found, operation
from service.contract.names import GROUPING_METHOD, ProblemType, made_from_image
from service.jobs import callbacks, wake
from service.jobs.queue import JobQueue, JobRefused, JobSpec, Outcome
from service.models import (
    Collection,
    Job,
    Shape,
    utcnow,
)
from service.progress import seconds_left
from service.schemas import (
    DbId,
    JobCreate,
    JobOut,
    JobStatusName,
    Page,
)

router = APIRouter(prefix="/jobs", tags=["jobs"])


def job_outs(session: Session, jobs: Sequence[Job]) -> list[JobOut]:
    """The jobs as the API shows them, with their collection's and model shape's names (two
    queries for the whole list; a name is null once its collection or shape is deleted)."""
    collection_ids = {j.collection_id for j in jobs}
    shape_ids = {j.model_shape_id for j in jobs if j.model_shape_id is not None}
    collections: dict[int, str] = {}
    shapes: dict[int, str] = {}
    if collection_ids:
        query = select(Collection.id, Collection.name).where(Collection.id.in_(collection_ids))
        collections = {i: name for i, name in session.execute(query).all()}
    if shape_ids:
        query = select(Shape.id, Shape.name).where(Shape.id.in_(shape_ids))
        shapes = {i: name for i, name in session.execute(query).all()}
    return [
        _job_out(j, collections.get(j.collection_id),
                 None if j.model_shape_id is None else shapes.get(j.model_shape_id))
        for j in jobs
    ]


def job_out(session: Session, job: Job) -> JobOut:
    """One job as the API shows it (names read through ``session``)."""
    return job_outs(session, [job])[0]


def _progress_out(job: Job) -> dict[str, Any]:
    """The job's progress with the worker's estimate of the share done and, while it runs,
    the time left."""
    fraction = 1.0 if job.status == "succeeded" else job.progress_fraction
    left = None
    if job.status == "running" and job.started_at is not None:  # UTCDateTime: aware
        left = seconds_left(fraction, (utcnow() - job.started_at).total_seconds())
    return {"stage": job.progress_stage, "done": job.progress_done,
            "total": job.progress_total, "fraction": fraction, "seconds_left": left}


def _job_out(job: Job, collection_name: str | None, model_name: str | None) -> JobOut:
    base = f"/v1/jobs/{job.id}"
    return JobOut.model_validate(
        {
            "id": job.id,
            "collection_id": job.collection_id,
            "collection_name": collection_name,
            "model_shape_id": job.model_shape_id,
            "model_name": model_name,
            "method": job.method,
            "params": job.params,
            "n_shapes": len(job.shape_ids),
            "status": job.status,
            "progress": _progress_out(job),
            "attempts": job.attempts,
            "max_attempts": job.max_attempts,
            "cancel_requested": job.cancel_requested,
            "error": job.error,
            "outcome": job.outcome,
            "next_attempt_at": job.next_attempt_at,
            "callback_url": job.callback_url,
            "created_at": job.created_at,
            "updated_at": job.updated_at,
            "started_at": job.started_at,
            "finished_at": job.finished_at,
            "links": {
                "self": base,
                "result": f"{base}/result",
                "cancel": f"{base}/cancel",
                "deliveries": f"{base}/deliveries",
            },
        }
    )


def _get_job(session: Session, job_id: int, *, for_update: bool = False) -> Job:
    job = session.get(Job, job_id, with_for_update=for_update)
    if job is None:
        raise not_found("job", job_id)
    return job


#: ``pose_source`` of a job's params: where its pose came from.
POSE_FROM_REQUEST = "request"
POSE_DEFAULT_IMAGES = "default for image collections"
POSE_DEFAULT = "default"


def resolve_pose(body: JobCreate, source_formats: list[str]) -> dict[str, Any]:
    """The pose a job runs with, for its params: ``pose``, ``max_rotation``, ``pose_source``.

    What the request gives, validated by the library's rule (``PoseSpec.resolve``). Without
    pose and max_rotation: "upright" (30 degrees) when every shape was made from an image,
    whose pose is the scan's, else the library's default ("rotation").
    """
    from registration._pose import DEFAULT_UPRIGHT_DEG, PoseSpec

    if body.pose is not None or body.max_rotation is not None:
        spec, source = PoseSpec.resolve(body.pose, body.max_rotation), POSE_FROM_REQUEST
    elif source_formats and all(made_from_image(f) for f in source_formats):
        spec, source = PoseSpec.resolve("upright", DEFAULT_UPRIGHT_DEG), POSE_DEFAULT_IMAGES
    else:
        spec, source = PoseSpec.resolve(None, None), POSE_DEFAULT
    return {**spec.to_dict(), "pose_source": source}


def _params(body: JobCreate, formats: list[str], points: list[int]) -> dict[str, Any]:
    """The job's params: the registration options and pose, or a grouping's threshold and
    max_rotation; and ``max_points``, the most points of any of its shapes (above
    ``working_points``, a job ends registering its tree at the stored resolution: its
    progress counts on that stage)."""
    if body.method == GROUPING_METHOD:
        return {"group_threshold": body.group_threshold, "max_rotation": body.max_rotation}
    return {
        "max_points": max(points, default=0),
        **body.model_dump(
            mode="json",
            include={"similarity_threshold", "error_threshold", "compare_direct", "cpd",
                     "working_points"},
        ),
        **resolve_pose(body, formats),
    }


def _unprocessable(detail: str, type_: str = ProblemType.INVALID_JOB) -> ProblemError:
    return ProblemError(422, detail, type_=type_)


@operation(
    router.post, "", "Submit a registration job", (401, 413, 422),
    status_code=status.HTTP_202_ACCEPTED, response_model=JobOut,
    description="Queues the job and answers 202 with a `Location` to poll. The job registers "
    "the model shape onto every shape the collection holds now. Without `pose` and "
    "`max_rotation`, a collection whose shapes were all uploaded as PNG or JPEG images is "
    "registered `upright` (within 30 degrees of the shapes as uploaded), any other with "
    "`rotation`; the job's `params` name the pose used and `pose_source` why. A "
    "`max_rotation` with a pose other than `upright` is a 422. A `callback_url` is called "
    "when the job ends (see `GET /v1/jobs/{job_id}/deliveries`); one on a host outside the "
    "setting `callback_allowed_hosts`, or on a server without `callback_secret`, is a 422.",
)
def create_job(
    body: JobCreate,
    request: Request,
    response: Response,
    db: DbDep,
    settings: SettingsDep,
    idempotency_key: IdempotencyKeyDep = None,
) -> JobOut:
    scope = f"POST {request.url.path}"
    # A body without pose (or callback_url) hashes as before they existed: a retry across
    # the upgrade matches.
    unset = {key for key in ("pose", "callback_url", "group_threshold")
             if getattr(body, key) is None}
    if "working_points" not in body.model_fields_set:
        unset.add("working_points")
    request_hash = idempotency.hash_json(body.model_dump(mode="json", exclude=unset or None))
    if body.callback_url is not None:
        try:
            callbacks.check_url(body.callback_url, settings)
        except ValueError as e:
            raise _unprocessable(str(e), ProblemType.CALLBACK_REFUSED) from None
    with db.write() as session:
        spec = JobSpec(
            collection_id=body.collection_id,
            # a grouping has no model: null, whatever the request said
            model_shape_id=None if body.method == GROUPING_METHOD else body.model_shape_id,
            method=body.method,
            params_for=lambda formats, points: _params(body, formats, points),
            callback_url=body.callback_url,
        )
        entry = idempotency.lookup(session, scope, idempotency_key, request_hash)
        if entry is not None:
            job = _get_job(session, entry.resource_ids[0])
        else:
            try:
                job = JobQueue.from_settings(db, settings).enqueue(spec, session=session)
            except JobRefused as e:
                raise _unprocessable(str(e)) from None
            idempotency.remember(
                session,
                scope,
                idempotency_key,
                request_hash,
                status_code=202,
                resource_type="job",
                resource_ids=[job.id],
            )
        out = job_out(session, job)
    if entry is None:
        wake.notify()  # committed: an idle embedded worker claims it now
    response.headers["Location"] = out.links.self
    return out


@router.get("", response_model=Page[JobOut], summary="List jobs, newest first")
def list_jobs(
    db: DbDep,
    page: PaginationDep,
    collection_id: Annotated[
        DbId | None, Query(description="Only the jobs of this collection.")
    ] = None,
    status_: Annotated[
        JobStatusName | None, Query(alias="status", description="Only the jobs in this status.")
    ] = None,
) -> Page[JobOut]:
    """Jobs, newest first, one page at a time, each with its status, progress and links;
    `collection_id` and `status` narrow the list."""
    query = select(Job)
    count = select(func.count(Job.id))
    if collection_id is not None:
        query = query.where(Job.collection_id == collection_id)
        count = count.where(Job.collection_id == collection_id)
    if status_ is not None:
        query = query.where(Job.status == status_)
        count = count.where(Job.status == status_)
    with db.read() as session:
        total = session.scalar(count) or 0
        jobs = session.scalars(
            query.order_by(Job.id.desc()).limit(page.limit).offset(page.offset)
        ).all()
        items = job_outs(session, jobs)
    return Page[JobOut](items=items, total=total, limit=page.limit, offset=page.offset)


@operation(router.get, "/{job_id}", "Read a job", (404,), response_model=JobOut)
def get_job(job_id: DbId, db: DbDep) -> JobOut:
    """The job's status (`queued`, `running`, `succeeded`, `failed`, `cancelled`), its
    `outcome` once ended, its progress (stage, steps done of the total), attempts, error and
    links to its result. Poll it until the status is `succeeded`, `failed` or `cancelled`."""
    with db.read() as session:
        return job_out(session, _get_job(session, job_id))


@operation(
    router.post, "/{job_id}/cancel", "Cancel a job", (404, 409),
    status_code=status.HTTP_202_ACCEPTED, response_model=JobOut,
    description="A queued job (waiting for its first attempt or a retry) is cancelled at "
    "once: status `cancelled`, outcome `cancelled`. A running job gets `cancel_requested`; its "
    "worker sees the request within the setting `cancel_poll_seconds` (1 s by default), stops "
    "the registrations in progress and ends the job with status `cancelled` and outcome "
    "`aborted` (never `succeeded`). A finished job: 409.",
)
def cancel_job(job_id: DbId, db: DbDep, settings: SettingsDep) -> JobOut:
    with db.write() as session:
        outcome = JobQueue.from_settings(db, settings).cancel(job_id, session=session)
        job = _get_job(session, job_id)
        if outcome is Outcome.finished:
            raise ProblemError(
                409, f"job {job_id} already {job.status}", type_=ProblemType.JOB_FINISHED
            )
        return job_out(session, job)

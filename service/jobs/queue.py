"""The job queue: claim with a lease, heartbeat, progress, finish, cancel, reclaim.

Every state change a worker makes is one conditional UPDATE, guarded by
``status = 'running' AND lease_owner = :me AND attempts = :attempt``. A worker whose lease
expired and whose job was claimed again (``attempts`` went up) therefore cannot write
anything: its UPDATE matches no row, and it learns that it lost the job. On SQLite all of it
runs in ``BEGIN IMMEDIATE`` transactions (:meth:`Database.write`), so claims are serialised.

On PostgreSQL (READ COMMITTED) the claim and the reaper select their rows with ``FOR UPDATE
SKIP LOCKED``: concurrent workers each lock a different job instead of queueing behind one
another's, and a job is claimed by one of them only. The guarded UPDATE stays as the fence.
SQLite compiles ``FOR UPDATE`` away; there ``BEGIN IMMEDIATE`` does that work.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, or_, select, update
from sqlalchemy.orm import Session

from service.db import Database
from service.models import Job, JobStatus, Result, ResultSubject, utcnow

logger = logging.getLogger("regtree.queue")


@dataclass(frozen=True)
class Claim:
    """A job held by one worker for one attempt."""

    job_id: int
    owner: str
    attempt: int


@dataclass(frozen=True)
class LeaseState:
    """What a conditional write found: whether we still hold the job, and cancel requests."""

    held: bool
    cancel_requested: bool = False


def _guard(claim: Claim) -> Any:
    return and_(
        Job.id == claim.job_id,
        Job.status == JobStatus.running.value,
        Job.lease_owner == claim.owner,
        Job.attempts == claim.attempt,
    )


def _update(session: Session, claim: Claim, **values: Any) -> bool:
    result = session.execute(
        update(Job)
        .where(_guard(claim))
        .values(updated_at=utcnow(), **values)
        .execution_options(synchronize_session=False)
    )
    return bool(getattr(result, "rowcount", 0) == 1)


def reap_expired(session: Session, now: datetime) -> list[int]:
    """Settle running jobs whose lease expired and that must not run again.

    A job with a pending cancel request ends ``cancelled``; a job that used all its attempts
    ends ``failed`` with an error saying so. Others stay claimable by :func:`claim`.
    """
    expired = session.scalars(
        select(Job)
        .where(Job.status == JobStatus.running.value, Job.lease_expires_at < now)
        .order_by(Job.id)
        .with_for_update(skip_locked=True)
    ).all()
    settled = []
    for job in expired:
        if job.cancel_requested:
            job.status = JobStatus.cancelled.value
            job.error = "cancelled; the worker stopped before it could confirm"
        elif job.attempts >= job.max_attempts:
            job.status = JobStatus.failed.value
            job.error = (
                f"the worker running this job stopped responding (lease expired) on each of "
                f"{job.attempts} attempt(s), the limit (setting max_attempts); last worker "
                f"{job.lease_owner}"
            )
        else:
            continue
        job.lease_owner = None
        job.lease_expires_at = None
        job.finished_at = now
        job.updated_at = now
        settled.append(job.id)
        logger.warning(
            "job settled after lease expiry",
            extra={"job_id": job.id, "status": job.status, "attempts": job.attempts},
        )
    return settled


def claim(db: Database, owner: str, *, lease_seconds: float) -> Claim | None:
    """Claim the oldest queued job, or a running one whose lease expired; None if none."""
    now = utcnow()
    with db.write() as session:
        reap_expired(session, now)
        claimable = or_(
            Job.status == JobStatus.queued.value,
            and_(
                Job.status == JobStatus.running.value,
                Job.lease_expires_at < now,
                Job.attempts < Job.max_attempts,
            ),
        )
        job = session.scalars(
            select(Job)
            .where(claimable)
            .order_by(Job.created_at, Job.id)
            .limit(1)
            .with_for_update(skip_locked=True)
        ).first()
        if job is None:
            return None
        previous_owner, attempt = job.lease_owner, job.attempts + 1
        result = session.execute(
            update(Job)
            .where(Job.id == job.id, Job.attempts == job.attempts, claimable)
            .values(
                status=JobStatus.running.value,
                lease_owner=owner,
                lease_expires_at=now + timedelta(seconds=lease_seconds),
                heartbeat_at=now,
                attempts=attempt,
                started_at=job.started_at or now,
                updated_at=now,
                error=None,
            )
            .execution_options(synchronize_session=False)
        )
        if getattr(result, "rowcount", 0) != 1:
            return None
    if previous_owner is not None:
        logger.warning(
            "job reclaimed after lease expiry",
            extra={"job_id": job.id, "attempt": attempt, "previous_owner": previous_owner},
        )
    logger.info("job claimed", extra={"job_id": job.id, "attempt": attempt, "owner": owner})
    return Claim(job_id=job.id, owner=owner, attempt=attempt)


def _state(session: Session, claim: Claim, held: bool) -> LeaseState:
    if not held:
        return LeaseState(held=False)
    cancel = session.scalar(select(Job.cancel_requested).where(Job.id == claim.job_id))
    return LeaseState(held=True, cancel_requested=bool(cancel))


def peek(db: Database, claim: Claim) -> LeaseState:
    """Whether we still hold the job and whether a cancel was requested: a read, no write.

    Cheap enough to poll every second or so between heartbeats (one row by primary key).
    """
    with db.read() as session:
        row = session.execute(
            select(Job.status, Job.lease_owner, Job.attempts, Job.cancel_requested).where(
                Job.id == claim.job_id
            )
        ).first()
    if row is None:
        return LeaseState(held=False)
    held = (
        row.status == JobStatus.running.value
        and row.lease_owner == claim.owner
        and row.attempts == claim.attempt
    )
    return LeaseState(held=held, cancel_requested=held and bool(row.cancel_requested))


def heartbeat(
    db: Database,
    claim: Claim,
    *,
    lease_seconds: float,
    progress: tuple[str, int, int] | None = None,
) -> LeaseState:
    """Extend the lease (and write the latest progress, if given)."""
    now = utcnow()
    values: dict[str, Any] = {
        "lease_expires_at": now + timedelta(seconds=lease_seconds),
        "heartbeat_at": now,
    }
    if progress is not None:
        values.update(
            progress_stage=progress[0][:100], progress_done=progress[1], progress_total=progress[2]
        )
    with db.write() as session:
        return _state(session, claim, _update(session, claim, **values))


def complete(
    db: Database,
    claim: Claim,
    document: dict[str, Any],
    subjects: list[dict[str, Any]],
    *,
    progress: tuple[str, int, int] | None = None,
    similarity: bytes | None = None,
) -> str:
    """Store the result and mark the job succeeded, atomically.

    ``similarity``: the job's similarity D as ``.npy`` bytes (:attr:`Result.similarity_npy`).

    Returns ``"succeeded"``, ``"cancelled"`` or ``"lost"`` (the lease was lost: nothing written).

    If a cancel was requested meanwhile, the job ends ``cancelled`` and the result is dropped:
    a cancel accepted while running always ends the job cancelled.
    """
    now = utcnow()
    with db.write() as session:
        # Locked (on PostgreSQL) so that a cancel cannot slip in between this read and the
        # update below: the cancel route locks the same row (see routes/jobs.py).
        cancel = session.scalar(
            select(Job.cancel_requested).where(Job.id == claim.job_id).with_for_update()
        )
        if cancel:
            cancelled = _update(
                session,
                claim,
                status=JobStatus.cancelled.value,
                lease_owner=None,
                lease_expires_at=None,
                finished_at=now,
            )
            return "cancelled" if cancelled else "lost"
        final: dict[str, Any] = {}
        if progress is not None:
            final = {
                "progress_stage": progress[0][:100],
                "progress_done": progress[1],
                "progress_total": progress[2],
            }
        held = _update(
            session,
            claim,
            status=JobStatus.succeeded.value,
            lease_owner=None,
            lease_expires_at=None,
            finished_at=now,
            **final,
        )
        if not held:
            return "lost"
        session.add(Result(job_id=claim.job_id, document=document, similarity_npy=similarity))
        for subject in subjects:
            session.add(
                ResultSubject(
                    job_id=claim.job_id,
                    shape_id=subject["shape_id"],
                    position=subject.get("position", 0),
                    parent_shape_id=subject.get("parent_shape_id"),
                    layer=subject.get("layer"),
                    error=subject.get("error"),
                    document=subject,
                )
            )
        return "succeeded"


def fail(db: Database, claim: Claim, error: str) -> bool:
    with db.write() as session:
        return _update(
            session,
            claim,
            status=JobStatus.failed.value,
            error=error[:4000],
            lease_owner=None,
            lease_expires_at=None,
            finished_at=utcnow(),
        )


def finish_cancelled(db: Database, claim: Claim) -> bool:
    with db.write() as session:
        return _update(
            session,
            claim,
            status=JobStatus.cancelled.value,
            lease_owner=None,
            lease_expires_at=None,
            finished_at=utcnow(),
        )


def release(db: Database, claim: Claim) -> bool:
    """Give a job back to the queue (worker shutting down); the attempt is not counted."""
    with db.write() as session:
        return _update(
            session,
            claim,
            status=JobStatus.queued.value,
            lease_owner=None,
            lease_expires_at=None,
            attempts=claim.attempt - 1,
        )


def request_cancel(session: Session, job: Job) -> bool:
    """Cancel a job inside the caller's write transaction; False if it already finished.

    A queued job is cancelled at once; a running one gets ``cancel_requested``: its worker
    sees it within ``cancel_poll_seconds``, stops the registrations in progress and ends the
    job ``cancelled`` (:mod:`service.jobs.runner`).
    """
    now = utcnow()
    if job.status == JobStatus.queued.value:
        job.status = JobStatus.cancelled.value
        job.cancel_requested = True
        job.finished_at = now
        job.updated_at = now
        return True
    if job.status == JobStatus.running.value:
        job.cancel_requested = True
        job.updated_at = now
        return True
    return False

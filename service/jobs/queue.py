"""The job lifecycle, owned by one object: :class:`JobQueue`.

Every transition of a job goes through it, and each returns an :class:`Outcome`::

    enqueue         -> queued
    claim           queued (due) -> running, attempt + 1       (a Claim, or None if none due)
    heartbeat       running: extend the lease, write progress  held | cancel_requested | lost
    complete        running -> succeeded (result stored)       succeeded | aborted | lost
    fail            running -> failed (bad input, a bug)       failed | lost
      transient     running -> queued after a backoff          retrying | failed | lost
    abort           running -> cancelled (worker confirms)     aborted | lost
    release         running -> queued, attempt not counted     released | lost
    cancel          queued -> cancelled                        cancelled
                    running -> cancel_requested                cancel_requested
                    ended                                      finished | not_found
    settle_stalled  running, lease expired -> queued after a backoff (retrying), failed at
                    max_attempts, or cancelled if a cancel was pending (aborted)

``status`` keeps five values (queued, running, succeeded, failed, cancelled); ``outcome``
says how a job ended, telling ``cancelled`` (while queued) from ``aborted`` (while running).

Retries. A transient failure is retried with exponential backoff (``next_attempt_at``) until
the job's ``max_attempts`` are used: the database was busy or locked, or the worker was lost
(its lease expired: killed, power loss, stuck). Anything else fails the job at once with its
message: a ``ValueError`` from the library is bad input, and running it again would only
fail again.

Fencing. Every state change a worker makes is one conditional UPDATE, guarded by
``status = 'running' AND lease_owner = :me AND attempts = :attempt``. A worker whose lease
expired and whose job was settled or claimed again therefore cannot write anything: its
UPDATE matches no row, and it learns that it lost the job. On SQLite all of it runs in
``BEGIN IMMEDIATE`` transactions (:meth:`Database.write`), so claims are serialised. On
PostgreSQL (READ COMMITTED) the claim and the settling select their rows with ``FOR UPDATE
SKIP LOCKED``: concurrent workers each lock a different job instead of queueing behind one
another's, and a job is claimed by one of them only; the guarded UPDATE stays as the fence.
``cancel`` and ``complete`` lock the job's row, so a cancel cannot slip in between.

A job that ends with a ``callback_url`` gets its callback delivery stored in the same
transaction (:func:`service.jobs.callbacks.schedule`).
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, or_, select, update
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.orm import Session

from service.contract.names import GROUPING_METHOD
from service.core.backoff import JOB_BACKOFF, Backoff
from service.core.config import Settings
from service.db import Database, lock_first
from service.jobs import callbacks
from service.jobs.wake import notify_in
from service.models import (
    Collection,
    Job,
    JobOutcome,
    JobStatus,
    Result,
    ResultSubject,
    Shape,
    utcnow,
)

logger = logging.getLogger("regtree.queue")


class Outcome(enum.StrEnum):
    """What a queue operation did."""

    held = "held"  # heartbeat, peek: the lease is still ours
    cancel_requested = "cancel_requested"  # ours, but stop (cancel: the worker will abort)
    lost = "lost"  # the worker no longer holds the job: nothing was written
    succeeded = "succeeded"
    failed = "failed"
    retrying = "retrying"  # queued again, claimable after a backoff
    released = "released"
    cancelled = "cancelled"  # cancelled while queued
    aborted = "aborted"  # cancelled while running
    finished = "finished"  # cancel: the job had already ended
    not_found = "not_found"


@dataclass(frozen=True)
class Claim:
    """A job held by one worker for one attempt."""

    job_id: int
    owner: str
    attempt: int


class JobRefused(ValueError):
    """A job that cannot be queued: the message says why (a 422 for the API)."""


@dataclass(frozen=True)
class JobSpec:
    """What :meth:`JobQueue.enqueue` needs: the request, validated as far as it can be
    without the database. ``params_for`` gives the job's params from the source formats of
    the collection's shapes (the default pose depends on them) and their point counts
    (whether a coarse-to-fine job has a stored-resolution stage)."""

    collection_id: int
    model_shape_id: int | None  # None: a job without a model (a grouping)
    method: str
    params_for: Callable[[list[str], list[int]], dict[str, Any]]
    callback_url: str | None = None


def is_transient(exc: BaseException) -> bool:
    """Whether an error is worth another attempt: the database was busy or locked, a
    serialisation failure or deadlock, or the connection to the server dropped."""
    if isinstance(exc, DBAPIError) and exc.connection_invalidated:
        return True
    if not isinstance(exc, OperationalError):
        return False
    message = str(exc.orig).lower()
    words = ("locked", "busy", "deadlock", "could not serialize", "connection", "terminat")
    return any(word in message for word in words)


def _progress(progress: tuple[str, int, int] | None,
              fraction: float | None = None) -> dict[str, Any]:
    if progress is None:
        return {}
    stage, done, total = progress
    out: dict[str, Any] = {"progress_stage": stage[:100], "progress_done": done,
                           "progress_total": total}
    if fraction is not None:
        out["progress_fraction"] = float(fraction)
    return out


class JobQueue:
    """The one owner of a job's lifecycle (see the module's notes)."""

    def __init__(
        self,
        db: Database,
        *,
        lease_seconds: float = 60.0,
        max_attempts: int = 3,
        backoff: Backoff = JOB_BACKOFF,
        callback_policy: callbacks.CallbackPolicy | None = None,
    ) -> None:
        self.db = db
        self.lease_seconds = lease_seconds
        self.max_attempts = max_attempts
        self.backoff = backoff
        self.callback_policy = callback_policy or callbacks.CallbackPolicy()

    @classmethod
    def from_settings(cls, db: Database, settings: Settings) -> JobQueue:
        return cls(
            db,
            lease_seconds=settings.worker_lease_seconds,
            max_attempts=settings.max_attempts,
            backoff=settings.retry_backoff,
            callback_policy=callbacks.CallbackPolicy.from_settings(settings),
        )

    @contextmanager
    def _writing(self, session: Session | None) -> Iterator[Session]:
        if session is not None:
            yield session
        else:
            with self.db.write() as own:
                yield own

    # -- the API's side ---------------------------------------------------------------------

    def enqueue(self, spec: JobSpec, *, session: Session | None = None) -> Job:
        """Queue a job over the collection's shapes as they are now; raises
        :class:`JobRefused` if the collection or model does not fit. Runs in ``session``
        (the caller's write transaction, e.g. with its idempotency record) when given."""
        with self._writing(session) as s:
            if s.get(Collection, spec.collection_id) is None:
                raise JobRefused(f"collection {spec.collection_id} does not exist")
            if spec.model_shape_id is None and spec.method != GROUPING_METHOD:
                raise JobRefused(f"model_shape_id is required by method {spec.method}")
            model = None if spec.model_shape_id is None else s.get(Shape, spec.model_shape_id)
            if spec.model_shape_id is not None and model is None:
                raise JobRefused(f"model shape {spec.model_shape_id} does not exist")
            if model is not None and model.collection_id != spec.collection_id:
                raise JobRefused(
                    f"model shape {spec.model_shape_id} belongs to collection "
                    f"{model.collection_id}, not to collection {spec.collection_id}"
                )
            rows = s.execute(
                select(Shape.id, Shape.source_format, Shape.n_points)
                .where(Shape.collection_id == spec.collection_id)
                .order_by(Shape.id)
            ).all()
            if len(rows) < 2:
                needs = ("the model and at least one other shape" if model is not None
                         else "at least two shapes")
                raise JobRefused(
                    f"collection {spec.collection_id} has {len(rows)} shape(s); a job "
                    f"needs {needs}"
                )
            job = Job(
                collection_id=spec.collection_id,
                model_shape_id=spec.model_shape_id,
                shape_ids=[row.id for row in rows],
                method=spec.method,
                params=spec.params_for([row.source_format for row in rows],
                                       [row.n_points for row in rows]),
                status=JobStatus.queued.value,
                max_attempts=self.max_attempts,
                callback_url=spec.callback_url,
            )
            s.add(job)
            s.flush()
            notify_in(s)  # PostgreSQL: listening workers wake at the commit
            logger.info("job queued", extra={"job_id": job.id})
            return job

    def cancel(self, job_id: int, *, session: Session | None = None) -> Outcome:
        """Cancel a job: a queued one (waiting for its first attempt or a retry) ends
        ``cancelled`` at once; a running one gets ``cancel_requested``, which its worker
        sees within ``cancel_poll_seconds``: it stops the registrations in progress and the
        job ends ``cancelled`` with outcome ``aborted``. Ended jobs: ``finished``."""
        with self._writing(session) as s:
            # Row-locked on PostgreSQL: a worker's claim or completion cannot interleave.
            job = s.get(Job, job_id, with_for_update=True)
            if job is None:
                return Outcome.not_found
            now = utcnow()
            if job.status == JobStatus.queued.value:
                job.cancel_requested = True
                self._end(s, job, JobOutcome.cancelled, now)
                return Outcome.cancelled
            if job.status == JobStatus.running.value:
                job.cancel_requested = True
                job.updated_at = now
                return Outcome.cancel_requested
            return Outcome.finished

    # -- the workers' side ------------------------------------------------------------------

    def claim(self, owner: str) -> Claim | None:
        """Settle stalled jobs, then claim the oldest queued job that is due; None if none."""
        with self.db.write() as session:
            # the time once the transaction holds the write lock (SQLite: BEGIN IMMEDIATE
            # waits for a writer that may be queueing a job): read before, a job created
            # and committed meanwhile could start before its own created_at
            session.connection()
            now = utcnow()
            self._settle(session, now)
            due = and_(
                Job.status == JobStatus.queued.value,
                or_(Job.next_attempt_at.is_(None), Job.next_attempt_at <= now),
            )
            job = lock_first(session, select(Job).where(due).order_by(Job.created_at, Job.id))
            if job is None:
                return None
            attempt = job.attempts + 1
            result = session.execute(
                update(Job)
                .where(Job.id == job.id, Job.attempts == job.attempts, due)
                .values(
                    status=JobStatus.running.value,
                    lease_owner=owner,
                    lease_expires_at=now + timedelta(seconds=self.lease_seconds),
                    heartbeat_at=now,
                    attempts=attempt,
                    next_attempt_at=None,
                    started_at=job.started_at or now,
                    updated_at=now,
                    error=None,
                    progress_fraction=None,  # each attempt estimates from its start
                )
                .execution_options(synchronize_session=False)
            )
            if getattr(result, "rowcount", 0) != 1:
                return None
        logger.info("job claimed", extra={"job_id": job.id, "attempt": attempt, "owner": owner})
        return Claim(job_id=job.id, owner=owner, attempt=attempt)

    def peek(self, claim: Claim) -> Outcome:
        """Whether we still hold the job and whether a cancel was requested: a read, no
        write. Cheap enough to poll every second or so between heartbeats."""
        with self.db.read() as session:
            row = session.execute(
                select(Job.status, Job.lease_owner, Job.attempts, Job.cancel_requested).where(
                    Job.id == claim.job_id
                )
            ).first()
        held = (
            row is not None
            and row.status == JobStatus.running.value
            and row.lease_owner == claim.owner
            and row.attempts == claim.attempt
        )
        if not held or row is None:
            return Outcome.lost
        return Outcome.cancel_requested if row.cancel_requested else Outcome.held

    def heartbeat(self, claim: Claim, *, progress: tuple[str, int, int] | None = None,
                  fraction: float | None = None) -> Outcome:
        """Extend the lease (and write the latest progress, if given, with the estimated
        share of the whole job done)."""
        now = utcnow()
        with self.db.write() as session:
            held = self._update(
                session,
                claim,
                lease_expires_at=now + timedelta(seconds=self.lease_seconds),
                heartbeat_at=now,
                **_progress(progress, fraction),
            )
            if not held:
                return Outcome.lost
            cancel = session.scalar(select(Job.cancel_requested).where(Job.id == claim.job_id))
            return Outcome.cancel_requested if cancel else Outcome.held

    def complete(
        self,
        claim: Claim,
        document: dict[str, Any],
        subjects: Sequence[dict[str, Any]],
        *,
        progress: tuple[str, int, int] | None = None,
        similarity: bytes | None = None,
    ) -> Outcome:
        """Store the result and end the job succeeded, atomically. If a cancel was
        requested meanwhile, the job ends aborted and the result is dropped: a cancel
        accepted while running always ends the job cancelled.

        ``similarity``: the job's similarity D as ``.npy`` bytes (:attr:`Result.similarity_npy`).
        """
        now = utcnow()
        with self.db.write() as session:
            # Locked (on PostgreSQL) so that a cancel cannot slip in between this read and
            # the update below: cancel() locks the same row.
            cancel = session.scalar(
                select(Job.cancel_requested).where(Job.id == claim.job_id).with_for_update()
            )
            if cancel:
                return self._finish(session, claim, JobOutcome.aborted, now)
            outcome = self._finish(session, claim, JobOutcome.succeeded, now, **_progress(progress))
            if outcome is Outcome.lost:
                return outcome
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
            return outcome

    def fail(self, claim: Claim, error: str, *, transient: bool = False) -> Outcome:
        """End the job failed with ``error``; a ``transient`` failure queues it again after
        a backoff instead, until its ``max_attempts`` are used."""
        now = utcnow()
        with self.db.write() as session:
            if transient:
                max_attempts = session.scalar(
                    select(Job.max_attempts).where(Job.id == claim.job_id)
                )
                if max_attempts is not None and claim.attempt < max_attempts:
                    delay = self.backoff.delay(claim.attempt)
                    held = self._update(
                        session,
                        claim,
                        **self._requeue(now, delay),
                        error=f"attempt {claim.attempt} of {max_attempts} failed ({error[:2000]}); "
                        f"retrying in {delay:g} s",
                    )
                    return Outcome.retrying if held else Outcome.lost
                error = f"{error} (on each of {claim.attempt} attempt(s), the limit)"
            return self._finish(session, claim, JobOutcome.failed, now, error=error[:4000])

    def abort(self, claim: Claim) -> Outcome:
        """The worker confirms a cancel: the job ends cancelled, outcome aborted."""
        with self.db.write() as session:
            return self._finish(session, claim, JobOutcome.aborted, utcnow())

    def release(self, claim: Claim) -> Outcome:
        """Give a job back to the queue (worker shutting down); the attempt is not counted."""
        with self.db.write() as session:
            held = self._update(
                session,
                claim,
                status=JobStatus.queued.value,
                lease_owner=None,
                lease_expires_at=None,
                attempts=claim.attempt - 1,
            )
            if held:
                notify_in(session)  # due again now: another worker may take it
            return Outcome.released if held else Outcome.lost

    def settle_stalled(self) -> dict[int, Outcome]:
        """Settle running jobs whose lease expired (their worker was lost); ``claim`` does it
        too. Returns what became of each: retrying, failed or aborted."""
        with self.db.write() as session:
            return self._settle(session, utcnow())

    # -- internals --------------------------------------------------------------------------

    def _requeue(self, now: datetime, delay: float) -> dict[str, Any]:
        return {
            "status": JobStatus.queued.value,
            "lease_owner": None,
            "lease_expires_at": None,
            "next_attempt_at": now + timedelta(seconds=delay),
        }

    def _settle(self, session: Session, now: datetime) -> dict[int, Outcome]:
        expired = session.scalars(
            select(Job)
            .where(Job.status == JobStatus.running.value, Job.lease_expires_at < now)
            .order_by(Job.id)
            .with_for_update(skip_locked=True)
        ).all()
        settled: dict[int, Outcome] = {}
        for job in expired:
            lost = f"the worker running this job ({job.lease_owner}) stopped responding"
            if job.cancel_requested:
                job.error = "cancelled; the worker stopped before it could confirm"
                self._end(session, job, JobOutcome.aborted, now)
                settled[job.id] = Outcome.aborted
            elif job.attempts >= job.max_attempts:
                job.error = (
                    f"{lost} (lease expired) on each of {job.attempts} attempt(s), the limit "
                    "(setting max_attempts)"
                )
                self._end(session, job, JobOutcome.failed, now)
                settled[job.id] = Outcome.failed
            else:
                delay = self.backoff.delay(job.attempts)
                for key, value in self._requeue(now, delay).items():
                    setattr(job, key, value)
                job.error = (
                    f"attempt {job.attempts} of {job.max_attempts}: {lost} (lease expired); "
                    f"retrying in {delay:g} s"
                )
                job.updated_at = now
                settled[job.id] = Outcome.retrying
            logger.warning(
                "stalled job settled",
                extra={"job_id": job.id, "outcome": settled[job.id], "attempts": job.attempts},
            )
        return settled

    def _end(self, session: Session, job: Job, outcome: JobOutcome, now: datetime) -> None:
        """End a loaded job (no lease to check: the caller holds its row)."""
        job.status = _STATUS[outcome].value
        job.outcome = outcome.value
        job.lease_owner = None
        job.lease_expires_at = None
        job.next_attempt_at = None
        job.finished_at = now
        job.updated_at = now
        session.flush()
        callbacks.schedule(session, job.id, now, self.callback_policy)

    def _finish(
        self, session: Session, claim: Claim, outcome: JobOutcome, now: datetime, **values: Any
    ) -> Outcome:
        """End the claimed job, fenced by the lease: ``outcome`` or ``lost``."""
        held = self._update(
            session,
            claim,
            status=_STATUS[outcome].value,
            outcome=outcome.value,
            lease_owner=None,
            lease_expires_at=None,
            finished_at=now,
            **values,
        )
        if not held:
            return Outcome.lost
        callbacks.schedule(session, claim.job_id, now, self.callback_policy)
        return Outcome(outcome.value)

    @staticmethod
    def _update(session: Session, claim: Claim, **values: Any) -> bool:
        """One UPDATE guarded by the lease: True if we still held the job."""
        result = session.execute(
            update(Job)
            .where(
                Job.id == claim.job_id,
                Job.status == JobStatus.running.value,
                Job.lease_owner == claim.owner,
                Job.attempts == claim.attempt,
            )
            .values(updated_at=utcnow(), **values)
            .execution_options(synchronize_session=False)
        )
        return bool(getattr(result, "rowcount", 0) == 1)


_STATUS = {
    JobOutcome.succeeded: JobStatus.succeeded,
    JobOutcome.failed: JobStatus.failed,
    JobOutcome.cancelled: JobStatus.cancelled,
    JobOutcome.aborted: JobStatus.cancelled,
}

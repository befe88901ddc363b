"""The job queue's lifecycle and fencing, in process: a worker that lost its lease cannot
write; a transient failure is retried after a backoff, bad input is not; a cancel while
queued and one while running end differently; the runner sees a cancel between heartbeats,
and a cancel always wins."""

from __future__ import annotations

import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select, text
from sqlalchemy.exc import OperationalError

from service import migrate
from service.core.backoff import Backoff
from service.core.config import Settings
from service.db import Database
from service.jobs.queue import JobQueue, Outcome, is_transient
from service.models import Collection, Job, JobStatus, Result, utcnow


@pytest.fixture
def db(tmp_path: Path) -> Database:
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'q.sqlite'}")
    migrate.upgrade(settings)
    database = Database(settings.database_url)
    with database.write() as session:
        collection = Collection(name="c", description="")
        session.add(collection)
        session.flush()
        session.add(direct_job(collection.id))
    return database


def direct_job(collection_id: int) -> Job:
    """A queued direct-CPD job of shapes 1 and 2, three attempts allowed (queue tests only:
    the shapes need not exist)."""
    return Job(collection_id=collection_id, model_shape_id=1, shape_ids=[1, 2],
               method="direct", params={}, max_attempts=3)


def queue(db: Database, lease: float = 10.0, backoff: float = 0.0) -> JobQueue:
    return JobQueue(db, lease_seconds=lease, backoff=Backoff(backoff, 3600.0))


def _expire(db: Database) -> None:
    """The running job's lease ran out (its worker stopped heartbeating)."""
    with db.write() as session:
        session.execute(
            text("UPDATE jobs SET lease_expires_at = :t WHERE status = 'running'"),
            {"t": (utcnow() - timedelta(seconds=1)).replace(tzinfo=None)},
        )


def _due(db: Database) -> None:
    """The backoff of a job queued for a retry is over."""
    with db.write() as session:
        session.execute(text("UPDATE jobs SET next_attempt_at = NULL"))


def _backoff(job: Job) -> float:
    assert job.next_attempt_at is not None
    return (job.next_attempt_at - job.updated_at).total_seconds()


def _job(db: Database) -> Job:
    with db.read() as session:
        job = session.get(Job, 1)
        assert job is not None
        return job


def test_expired_lease_fences_the_old_worker(db: Database) -> None:
    long = queue(db)
    a = long.claim("worker-a")
    assert a is not None and a.attempt == 1
    assert long.claim("worker-b") is None  # lease still held
    _expire(db)
    b = long.claim("worker-b")
    assert b is not None and b.attempt == 2

    # Everything the old holder tries is refused and changes nothing.
    assert long.heartbeat(a, progress=("x", 1, 2)) is Outcome.lost
    assert long.complete(a, {"stale": True}, []) is Outcome.lost
    assert long.fail(a, "stale") is Outcome.lost
    assert long.fail(a, "stale", transient=True) is Outcome.lost
    assert long.abort(a) is Outcome.lost
    assert long.release(a) is Outcome.lost
    job = _job(db)
    assert job.status == JobStatus.running and job.lease_owner == "worker-b"
    assert job.progress_stage is None and job.error is None and job.outcome is None

    assert long.heartbeat(b, progress=("stage", 3, 4)) is Outcome.held
    done = long.complete(b, {"ok": True}, [{"shape_id": 2, "position": 1}])
    assert done is Outcome.succeeded
    with db.read() as session:
        result = session.get(Result, 1)
        assert result is not None and result.document == {"ok": True}
    job = _job(db)
    assert job.status == JobStatus.succeeded and job.outcome == "succeeded"


def test_cancel_while_running_aborts_and_wins_over_completion(db: Database) -> None:
    q = queue(db)
    claim = q.claim("w")
    assert claim is not None
    assert q.cancel(1) is Outcome.cancel_requested
    assert _job(db).status == JobStatus.running  # the worker has not confirmed yet
    assert q.heartbeat(claim) is Outcome.cancel_requested
    assert q.peek(claim) is Outcome.cancel_requested
    assert q.complete(claim, {}, []) is Outcome.aborted
    job = _job(db)
    assert job.status == JobStatus.cancelled and job.outcome == "aborted"
    assert q.cancel(1) is Outcome.finished
    assert q.cancel(99) is Outcome.not_found


def test_cancel_while_queued_is_cancelled_not_aborted(db: Database) -> None:
    q = queue(db)
    assert q.cancel(1) is Outcome.cancelled
    job = _job(db)
    assert job.status == JobStatus.cancelled and job.outcome == "cancelled"
    assert job.finished_at is not None and job.started_at is None
    assert q.claim("w") is None


def test_a_stalled_job_is_retried_after_a_backoff_up_to_max_attempts(db: Database) -> None:
    q = queue(db, backoff=30.0)
    first = q.claim("w1")
    assert first is not None
    _expire(db)
    assert q.settle_stalled() == {1: Outcome.retrying}
    job = _job(db)
    assert job.status == JobStatus.queued and job.attempts == 1 and job.lease_owner is None
    assert _backoff(job) == 30.0 and "stopped responding" in (job.error or "")
    assert q.claim("w2") is None  # not due for 30 s
    _due(db)
    second = q.claim("w2")
    assert second is not None and second.attempt == 2
    job = _job(db)
    assert job.next_attempt_at is None and job.error is None
    assert q.heartbeat(first) is Outcome.lost  # the lost worker is fenced out

    # The backoff doubles: 60 s after the second attempt was lost.
    _expire(db)
    assert q.settle_stalled() == {1: Outcome.retrying}
    assert _backoff(_job(db)) == 60.0


def test_attempts_are_capped(db: Database) -> None:
    q = queue(db)
    for attempt in (1, 2, 3):
        claim = q.claim(f"w{attempt}")
        assert claim is not None and claim.attempt == attempt
        _expire(db)
    assert q.claim("w4") is None
    job = _job(db)
    assert job.status == JobStatus.failed and job.attempts == 3 and job.outcome == "failed"
    assert "max_attempts" in (job.error or "")


def test_a_stalled_job_with_a_cancel_request_ends_aborted(db: Database) -> None:
    q = queue(db)
    assert q.claim("w") is not None
    assert q.cancel(1) is Outcome.cancel_requested
    _expire(db)
    assert q.settle_stalled() == {1: Outcome.aborted}
    assert _job(db).outcome == "aborted"


def test_transient_failure_retries_and_bad_input_does_not(db: Database) -> None:
    q = queue(db, backoff=60.0)
    claim = q.claim("w")
    assert claim is not None
    assert q.fail(claim, "OperationalError: database is locked", transient=True) is (
        Outcome.retrying
    )
    job = _job(db)
    assert job.status == JobStatus.queued and job.attempts == 1
    assert job.next_attempt_at is not None and "database is locked" in (job.error or "")
    assert q.claim("w") is None and abs(_backoff(_job(db)) - 60.0) < 1  # a minute of backoff
    _due(db)
    claim = q.claim("w")
    assert claim is not None and claim.attempt == 2
    assert q.fail(claim, "ValueError: shapes[3] has zero size") is Outcome.failed
    job = _job(db)
    assert job.status == JobStatus.failed and job.outcome == "failed"
    assert job.error == "ValueError: shapes[3] has zero size" and job.attempts == 2


def test_a_transient_failure_on_the_last_attempt_fails(db: Database) -> None:
    q = queue(db)
    for attempt in (1, 2):
        claim = q.claim("w")
        assert claim is not None and claim.attempt == attempt
        assert q.fail(claim, "database is locked", transient=True) is Outcome.retrying
    claim = q.claim("w")
    assert claim is not None and claim.attempt == 3
    assert q.fail(claim, "database is locked", transient=True) is Outcome.failed
    job = _job(db)
    assert job.status == JobStatus.failed and "3 attempt(s)" in (job.error or "")


def test_transient_errors_are_recognised() -> None:
    import sqlite3

    locked = OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))
    assert is_transient(locked)
    missing = OperationalError("SELECT", {}, sqlite3.OperationalError("no such table: jobs"))
    assert not is_transient(missing)
    assert not is_transient(ValueError("shapes[3] has zero size"))


def test_release_requeues_without_counting(db: Database) -> None:
    q = queue(db)
    claim = q.claim("w")
    assert claim is not None and q.release(claim) is Outcome.released
    job = _job(db)
    assert job.status == JobStatus.queued and job.attempts == 0 and job.lease_owner is None


def test_peek_reads_the_cancel_request_and_the_lease(db: Database) -> None:
    long = queue(db)
    a = long.claim("worker-a")
    assert a is not None
    assert long.peek(a) is Outcome.held
    _expire(db)
    b = long.claim("worker-b")
    assert b is not None
    assert long.peek(a) is Outcome.lost  # settled and reclaimed: a lost it
    assert long.cancel(1) is Outcome.cancel_requested
    assert long.peek(b) is Outcome.cancel_requested
    assert long.peek(a) is Outcome.lost
    updated = _job(db).updated_at
    long.peek(b)
    assert _job(db).updated_at == updated  # a read: nothing written


def test_next_attempt_at_orders_nothing_else(db: Database) -> None:
    """A job waiting for its retry does not hold up a younger job that is due."""
    q = queue(db, backoff=60.0)
    with db.write() as session:
        session.add(direct_job(1))
    claim = q.claim("w")
    assert claim is not None and claim.job_id == 1
    assert q.fail(claim, "database is busy", transient=True) is Outcome.retrying
    other = q.claim("w")
    assert other is not None and other.job_id == 2
    assert _job(db).next_attempt_at is not None
    assert (_job(db).next_attempt_at or utcnow()) - utcnow() > timedelta(seconds=50)


# --- the runner: a cancel is seen between heartbeats and always wins -------------------------


@pytest.fixture
def job_with_shapes(db: Database) -> Database:
    import numpy as np

    from service.models import Shape, points_to_npy

    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    with db.write() as session:
        for k in (1, 2):
            session.add(
                Shape(
                    id=k,
                    collection_id=1,
                    name=f"s{k}",
                    source_format="json",
                    n_points=4,
                    min_x=0.0,
                    min_y=0.0,
                    max_x=1.0,
                    max_y=1.0,
                    points_npy=points_to_npy(square * k),
                )
            )
    return db


def _runner_settings(db: Database) -> Settings:
    # Heartbeats (and progress writes, which also read the cancel flag) far apart: only the
    # cancel poll can see the request in time.
    return Settings(
        database_url=db.url,
        worker_heartbeat_seconds=30,
        worker_lease_seconds=60,
        progress_min_interval_seconds=100,
        cancel_poll_seconds=0.05,
        executor="serial",
    )


def _request_cancel(db: Database) -> None:
    assert queue(db).cancel(1) is Outcome.cancel_requested


def test_runner_sees_a_cancel_between_heartbeats(
    job_with_shapes: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    from service.jobs import runner

    db = job_with_shapes
    seen: list[float] = []

    def run(*args: object, progress: Any, **kwargs: object) -> dict[str, Any]:
        _request_cancel(db)
        asked = time.monotonic()
        for done in range(1000):
            try:
                progress("layer 1", done, 1000)
            except runner.Cancelled:
                seen.append(time.monotonic() - asked)
                raise
            time.sleep(0.01)
        return {}

    monkeypatch.setattr(runner, "run_registration", run)
    q = queue(db, lease=60)
    claim = q.claim("w")
    assert claim is not None
    assert runner.run_claimed(q, _runner_settings(db), claim) is Outcome.aborted
    assert seen and seen[0] < 2.0, seen
    job = _job(db)
    assert job.status == JobStatus.cancelled and job.finished_at is not None


def test_an_error_after_a_cancel_ends_cancelled_not_failed(
    job_with_shapes: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Stopping a run may surface as any error (a task whose process was killed): once the
    cancel was seen, the job ends cancelled."""
    from concurrent.futures.process import BrokenProcessPool

    from service.jobs import runner

    db = job_with_shapes

    def run(*args: object, **kwargs: object) -> dict[str, Any]:
        _request_cancel(db)
        time.sleep(0.5)  # the cancel poll sees it meanwhile
        raise BrokenProcessPool("a process of the pool was terminated abruptly")

    monkeypatch.setattr(runner, "run_registration", run)
    q = queue(db, lease=60)
    claim = q.claim("w")
    assert claim is not None
    assert runner.run_claimed(q, _runner_settings(db), claim) is Outcome.aborted
    job = _job(db)
    assert job.status == JobStatus.cancelled and job.error is None


def test_a_success_after_a_cancel_ends_cancelled(
    job_with_shapes: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    from service.jobs import runner

    db = job_with_shapes

    def run(*args: object, **kwargs: object) -> dict[str, Any]:
        _request_cancel(db)  # too late for the poll: the run returns at once
        return {"subjects": [], "root": 0}

    monkeypatch.setattr(runner, "run_registration", run)
    q = queue(db, lease=60)
    claim = q.claim("w")
    assert claim is not None
    assert runner.run_claimed(q, _runner_settings(db), claim) is Outcome.aborted
    assert _job(db).status == JobStatus.cancelled
    with db.read() as session:
        assert session.get(Result, 1) is None


def test_runner_fails_bad_input_at_once_with_the_message(
    job_with_shapes: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    from service.jobs import runner

    def run(*args: object, **kwargs: object) -> dict[str, Any]:
        raise ValueError("shapes[1] has zero size")

    monkeypatch.setattr(runner, "run_registration", run)
    q = queue(job_with_shapes, lease=60)
    claim = q.claim("w")
    assert claim is not None
    assert runner.run_claimed(q, _runner_settings(job_with_shapes), claim) is Outcome.failed
    job = _job(job_with_shapes)
    assert job.status == JobStatus.failed and job.attempts == 1
    assert job.error == "ValueError: shape 2 's2' has zero size"  # named, not a position


def test_runner_retries_when_the_database_is_locked(
    job_with_shapes: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A real lock: another connection holds SQLite's write lock while the runner stores the
    result, past a short busy timeout; the job goes back to the queue with a backoff."""
    import sqlite3

    from service.jobs import runner

    db = job_with_shapes
    impatient = Database(db.url, busy_timeout_ms=50)
    blocker = sqlite3.connect(db.url.removeprefix("sqlite:///"), isolation_level=None)

    def run(*args: object, **kwargs: object) -> dict[str, Any]:
        blocker.execute("BEGIN IMMEDIATE")  # held while the runner stores the result
        return {"subjects": [], "root": 0}

    q = JobQueue(impatient, lease_seconds=60, backoff=Backoff(30.0, 60.0))
    store = q.complete

    def complete(*args: Any, **kwargs: Any) -> Outcome:
        try:
            return store(*args, **kwargs)
        finally:
            blocker.execute("ROLLBACK")  # the lock goes once storing gave up

    monkeypatch.setattr(runner, "run_registration", run)
    monkeypatch.setattr(q, "complete", complete)
    claim = q.claim("w")
    assert claim is not None
    try:
        assert runner.run_claimed(q, _runner_settings(db), claim) is Outcome.retrying
    finally:
        blocker.close()
        impatient.dispose()
    job = _job(db)
    assert job.status == JobStatus.queued and job.attempts == 1 and job.outcome is None
    assert "database is locked" in (job.error or "")
    assert abs(_backoff(job) - 30.0) < 1
    with db.read() as session:
        assert session.get(Result, 1) is None


def test_enqueue_needs_a_model_for_a_registration_not_for_a_grouping(db: Database) -> None:
    from service.jobs.queue import JobRefused, JobSpec
    from service.models import Shape

    with db.write() as s:
        collection = Collection(name="c")
        s.add(collection)
        s.flush()
        for name in ("a", "b"):
            s.add(Shape(collection_id=collection.id, name=name, source_format="txt",
                        n_points=0, min_x=0, min_y=0, max_x=0, max_y=0, points_npy=b""))
        cid = collection.id
    q = queue(db)

    def spec(model: int | None, method: str) -> JobSpec:
        return JobSpec(collection_id=cid, model_shape_id=model, method=method,
                       params_for=lambda formats, points: {})

    with pytest.raises(JobRefused, match="model_shape_id is required by method direct"):
        q.enqueue(spec(None, "direct"))
    grouping = q.enqueue(spec(None, "grouping"))
    with db.read() as s:
        assert s.get(Job, grouping.id).model_shape_id is None


def test_settings_give_each_backoff_whole(db: Database, monkeypatch: pytest.MonkeyPatch) -> None:
    """A backoff's two settings (its first wait, its cap) are read as one Backoff, with the
    defaults the queue and the callbacks use without settings."""
    from service.core.backoff import CALLBACK_BACKOFF, JOB_BACKOFF
    from service.jobs.callbacks import CallbackPolicy

    defaults = Settings(_env_file=None)  # type: ignore[call-arg]
    assert defaults.retry_backoff == JOB_BACKOFF == Backoff(5.0, 300.0)
    assert defaults.callback_backoff == CALLBACK_BACKOFF == Backoff(10.0, 600.0)
    assert "it doubles with each further attempt, up to retry_backoff_max_seconds" in (
        Settings.model_fields["retry_backoff_seconds"].description or "")
    for name, value in (("RETRY_BACKOFF_SECONDS", "2"), ("RETRY_BACKOFF_MAX_SECONDS", "7"),
                        ("CALLBACK_BACKOFF_SECONDS", "3"),
                        ("CALLBACK_BACKOFF_MAX_SECONDS", "9")):
        monkeypatch.setenv(f"REGTREE_{name}", value)
    settings = Settings(_env_file=None)  # type: ignore[call-arg]
    assert JobQueue.from_settings(db, settings).backoff == Backoff(2.0, 7.0)
    assert CallbackPolicy.from_settings(settings).backoff == Backoff(3.0, 9.0)
    monkeypatch.setenv("REGTREE_CALLBACK_BACKOFF_MAX_SECONDS", "-1")
    with pytest.raises(ValueError, match="callback_backoff_max_seconds"):
        Settings(_env_file=None)  # type: ignore[call-arg]


def test_a_claim_waiting_for_a_queueing_writer_starts_the_job_after_its_creation(
        db: Database) -> None:
    """A worker's claim that waits for SQLite's write lock while the API queues a job
    reads the time once it holds the lock: the job starts after it was created."""
    import threading

    q = queue(db)
    first = q.claim("w0")  # the fixture's job, out of the way
    assert first is not None
    claimed: list[Any] = []
    worker = threading.Thread(target=lambda: claimed.append(q.claim("w1")))
    with db.write() as session:
        collection = session.scalars(select(Collection)).first()  # holds the write lock
        assert collection is not None
        worker.start()
        time.sleep(0.2)  # the claim has begun and waits for the lock
        session.add(direct_job(collection.id))
        session.flush()  # created_at is set here, after the claim began
        time.sleep(0.1)
    worker.join(10)
    assert claimed and claimed[0] is not None
    with db.read() as session:
        job = session.get(Job, claimed[0].job_id)
        assert job is not None and job.started_at is not None
        assert job.started_at >= job.created_at

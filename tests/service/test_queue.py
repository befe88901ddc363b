"""The queue's fencing, in process: a worker that lost its lease cannot write; and the runner
sees a cancel between heartbeats, and a cancel always wins."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from service import migrate
from service.core.config import Settings
from service.db import Database
from service.jobs import queue
from service.models import Collection, Job, JobStatus, Result


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


def _job(db: Database) -> Job:
    with db.read() as session:
        job = session.get(Job, 1)
        assert job is not None
        return job


def test_expired_lease_fences_the_old_worker(db: Database) -> None:
    a = queue.claim(db, "worker-a", lease_seconds=0.05)
    assert a is not None and a.attempt == 1
    assert queue.claim(db, "worker-b", lease_seconds=10) is None  # lease still held
    time.sleep(0.1)
    b = queue.claim(db, "worker-b", lease_seconds=10)
    assert b is not None and b.attempt == 2

    # Everything the old holder tries is refused and changes nothing.
    assert not queue.heartbeat(db, a, lease_seconds=10, progress=("x", 1, 2)).held
    assert queue.complete(db, a, {"stale": True}, []) == "lost"
    assert not queue.fail(db, a, "stale")
    assert not queue.finish_cancelled(db, a)
    assert not queue.release(db, a)
    job = _job(db)
    assert job.status == JobStatus.running and job.lease_owner == "worker-b"
    assert job.progress_stage is None and job.error is None

    assert queue.heartbeat(db, b, lease_seconds=10, progress=("stage", 3, 4)).held
    assert queue.complete(db, b, {"ok": True}, [{"shape_id": 2, "position": 1}]) == "succeeded"
    with db.read() as session:
        result = session.get(Result, 1)
        assert result is not None and result.document == {"ok": True}
    assert _job(db).status == JobStatus.succeeded


def test_cancel_request_reaches_the_worker_and_wins_over_completion(db: Database) -> None:
    claim = queue.claim(db, "w", lease_seconds=10)
    assert claim is not None
    with db.write() as session:
        job = session.get(Job, 1)
        assert job is not None and queue.request_cancel(session, job)
    assert queue.heartbeat(db, claim, lease_seconds=10).cancel_requested
    assert queue.complete(db, claim, {}, []) == "cancelled"
    assert _job(db).status == JobStatus.cancelled


def test_attempts_are_capped(db: Database) -> None:
    for attempt in (1, 2, 3):
        claim = queue.claim(db, f"w{attempt}", lease_seconds=0.01)
        assert claim is not None and claim.attempt == attempt
        time.sleep(0.03)
    assert queue.claim(db, "w4", lease_seconds=10) is None
    job = _job(db)
    assert job.status == JobStatus.failed and job.attempts == 3
    assert "max_attempts" in (job.error or "")


def test_release_requeues_without_counting(db: Database) -> None:
    claim = queue.claim(db, "w", lease_seconds=10)
    assert claim is not None and queue.release(db, claim)
    job = _job(db)
    assert job.status == JobStatus.queued and job.attempts == 0 and job.lease_owner is None


def test_peek_reads_the_cancel_request_and_the_lease(db: Database) -> None:
    a = queue.claim(db, "worker-a", lease_seconds=0.05)
    assert a is not None
    assert queue.peek(db, a) == queue.LeaseState(held=True, cancel_requested=False)
    time.sleep(0.1)
    b = queue.claim(db, "worker-b", lease_seconds=10)
    assert b is not None
    assert not queue.peek(db, a).held  # reclaimed: a lost it
    with db.write() as session:
        job = session.get(Job, 1)
        assert job is not None and queue.request_cancel(session, job)
    assert queue.peek(db, b) == queue.LeaseState(held=True, cancel_requested=True)
    assert queue.peek(db, a) == queue.LeaseState(held=False)
    updated = _job(db).updated_at
    queue.peek(db, b)
    assert _job(db).updated_at == updated  # a read: nothing written


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
    with db.write() as session:
        job = session.get(Job, 1)
        assert job is not None and queue.request_cancel(session, job)


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
    claim = queue.claim(db, "w", lease_seconds=60)
    assert claim is not None
    assert runner.run_claimed(db, _runner_settings(db), claim) == "cancelled"
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
    claim = queue.claim(db, "w", lease_seconds=60)
    assert claim is not None
    assert runner.run_claimed(db, _runner_settings(db), claim) == "cancelled"
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
    claim = queue.claim(db, "w", lease_seconds=60)
    assert claim is not None
    assert runner.run_claimed(db, _runner_settings(db), claim) == "cancelled"
    assert _job(db).status == JobStatus.cancelled
    with db.read() as session:
        assert session.get(Result, 1) is None

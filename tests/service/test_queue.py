"""The queue's fencing, in process: a worker that lost its lease cannot write."""

from __future__ import annotations

import time
from pathlib import Path

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
        session.add(
            Job(
                collection_id=collection.id,
                model_shape_id=1,
                shape_ids=[1, 2],
                method="direct",
                params={},
                max_attempts=3,
            )
        )
    return database


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

"""The service on PostgreSQL: migrations, uploads, jobs, idempotency races, crash recovery.

Skipped unless ``REGTREE_TEST_POSTGRES_URL`` names a PostgreSQL database whose role may
create databases, e.g. ``postgresql+psycopg://regtree:regtree@127.0.0.1:5432/regtree`` as
printed by ``.ci/postgres.sh``. Each test gets a scratch database of its own, dropped at the
end. The servers are conftest's, only pointed at that database.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from tests.service.conftest import (
    POSTGRES_SKIP_REASON,
    POSTGRES_URL,
    Service,
    assert_problem,
    create_collection,
    family,
    npy_bytes,
    postgres_scratch_database,
    second_job_queued_seconds,
    submit_job,
    upload_family,
    wait_job,
)
from tests.service.test_migrations import assert_migration_roundtrip

pytestmark = pytest.mark.skipif(not POSTGRES_URL, reason=POSTGRES_SKIP_REASON)


@pytest.fixture
def pg_url() -> Iterator[str]:
    """The URL of a fresh, empty database, dropped after the test."""
    with postgres_scratch_database() as url:
        yield url


@pytest.fixture
def pg_service(make_service: Callable[..., Service], pg_url: str) -> Callable[..., Service]:
    """conftest's ``make_service``, on the scratch PostgreSQL database."""

    def make(**kwargs: Any) -> Service:
        return make_service(database_url=pg_url, **kwargs)

    return make


def test_migrations_upgrade_downgrade(tmp_path: Path, pg_url: str) -> None:
    assert_migration_roundtrip(tmp_path, pg_url)


def test_uploads_job_and_result(pg_service: Callable[..., Service]) -> None:
    svc = pg_service(workers=1).start()
    shapes = family(n_chains=2, chain_length=3, n_points=60)[:6]
    with svc.client() as client:
        cid = create_collection(client, "pg")
        # JSON batch.
        ids = upload_family(client, cid, shapes[:4])
        # Raw .npy: the stored bytes (bytea) come back as the same float64 points.
        name, points = shapes[4]
        response = client.post(
            f"/v1/collections/{cid}/shapes",
            params={"name": name},
            content=npy_bytes(points),
            headers={"content-type": "application/octet-stream"},
        )
        assert response.status_code == 201, response.text
        ids.append(response.json()["id"])
        # Multipart CSV.
        name, points = shapes[5]
        csv = "x,y\n" + "\n".join(f"{x!r},{y!r}" for x, y in points.tolist())
        response = client.post(
            f"/v1/collections/{cid}/shapes",
            files={"files": (f"{name}.csv", csv.encode(), "text/csv")},
        )
        assert response.status_code == 201, response.text
        assert response.json()["items"][0]["source_format"] == "csv"
        ids.append(response.json()["items"][0]["id"])

        for shape_id, (_, expected) in zip(ids, shapes, strict=True):
            detail = client.get(f"/v1/collections/{cid}/shapes/{shape_id}").json()
            np.testing.assert_array_equal(np.array(detail["points"]), expected)

        listed = client.get(f"/v1/collections/{cid}/shapes", params={"limit": 2, "offset": 1})
        assert [s["id"] for s in listed.json()["items"]] == ids[1:3]
        assert listed.json()["total"] == 6

        job = submit_job(client, cid, ids[0], compare_direct=True)
        done = wait_job(client, job["id"])
        assert done["status"] == "succeeded", done
        result = client.get(f"/v1/jobs/{job['id']}/result").json()
        assert sorted(s["shape_id"] for s in result["subjects"]) == sorted(ids[1:])
        subject = client.get(f"/v1/jobs/{job['id']}/result/subjects/{ids[1]}")
        assert subject.status_code == 200, subject.text
        assert client.get("/v1/jobs", params={"offset": 2**62}).json()["items"] == []
        # PostgreSQL cannot store NUL in text: refused up front, not a 500.
        assert_problem(client.post("/v1/collections", json={"name": "a\u0000"}), 422)
        nul_shape = {"name": "a\u0000", "points": shapes[0][1].tolist()}
        assert_problem(client.post(f"/v1/collections/{cid}/shapes", json=nul_shape), 422)

        assert client.delete(f"/v1/collections/{cid}").status_code == 204
        assert_problem(client.get(f"/v1/jobs/{job['id']}"), 404)  # cascaded


def test_ids_past_32_bits_are_404(tmp_path: Path, pg_url: str) -> None:
    # conftest's Service without make_service, whose teardown would also fail on the 500s.
    svc = Service(tmp_path, workers=0, database_url=pg_url).start()
    try:
        with svc.client() as client:
            cid = create_collection(client)
            for url in (
                f"/v1/collections/{2**31}",
                f"/v1/collections/{2**63 - 1}",
                f"/v1/jobs/{2**40}",
                f"/v1/collections/{cid}/shapes/{2**40}",
            ):
                assert_problem(client.get(url), 404)
            assert client.get("/v1/jobs", params={"collection_id": 2**40}).json()["total"] == 0
    finally:
        svc.stop()


def _post_concurrently(
    client: httpx.Client, n: int, path: str, **kwargs: Any
) -> list[httpx.Response]:
    barrier = threading.Barrier(n)
    responses: list[httpx.Response | None] = [None] * n

    def post(i: int) -> None:
        barrier.wait()
        responses[i] = client.post(path, **kwargs)

    threads = [threading.Thread(target=post, args=(i,)) for i in range(n)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert all(r is not None for r in responses)
    return [r for r in responses if r is not None]


def test_concurrent_posts_with_one_idempotency_key(pg_service: Callable[..., Service]) -> None:
    svc = pg_service(workers=0).start()
    n = 8
    limits = httpx.Limits(max_connections=n, max_keepalive_connections=n)
    with svc.client(limits=limits) as client:
        for attempt in range(3):  # the race is timing-dependent: run it a few times
            key = {"Idempotency-Key": f"collection-{attempt}"}
            responses = _post_concurrently(
                client, n, "/v1/collections", json={"name": "same"}, headers=key
            )
            assert {r.status_code for r in responses} == {201}, [r.text for r in responses]
            assert len({r.json()["id"] for r in responses}) == 1
        total = client.get("/v1/collections").json()["total"]
        assert total == 3

        cid = create_collection(client, "shapes")
        body = {"shapes": [{"name": n, "points": p.tolist()} for n, p in family()[:3]]}
        responses = _post_concurrently(
            client,
            n,
            f"/v1/collections/{cid}/shapes",
            json=body,
            headers={"Idempotency-Key": "shapes"},
        )
        assert {r.status_code for r in responses} == {201}, [r.text for r in responses]
        assert len({tuple(s["id"] for s in r.json()["items"]) for r in responses}) == 1
        assert client.get(f"/v1/collections/{cid}/shapes").json()["total"] == 3

        model = responses[0].json()["items"][0]["id"]
        responses = _post_concurrently(
            client,
            n,
            "/v1/jobs",
            json={"collection_id": cid, "model_shape_id": model},
            headers={"Idempotency-Key": "job"},
        )
        assert {r.status_code for r in responses} == {202}, [r.text for r in responses]
        assert len({r.json()["id"] for r in responses}) == 1
        assert client.get("/v1/jobs", params={"collection_id": cid}).json()["total"] == 1

        # The same key with another body is still refused.
        reused = client.post(
            "/v1/collections", json={"name": "other"}, headers={"Idempotency-Key": "collection-0"}
        )
        assert_problem(reused, 422)
    assert not svc.unhandled_errors(), svc.unhandled_errors()


def test_concurrent_workers_claim_each_job_once(pg_url: str) -> None:
    """Many in-process workers racing on PostgreSQL: every job is claimed exactly once."""
    from service import migrate
    from service.core.backoff import Backoff
    from service.core.config import Settings
    from service.db import Database
    from service.jobs.queue import JobQueue, Outcome
    from service.models import Collection
    from tests.service.test_queue import direct_job

    settings = Settings(database_url=pg_url)
    migrate.upgrade(settings)
    db = Database(pg_url)
    queue = JobQueue(db, lease_seconds=60, backoff=Backoff(0.0, 0.0))
    short = JobQueue(db, lease_seconds=0.05, backoff=Backoff(0.0, 0.0))
    try:
        n_jobs, n_workers = 40, 8
        with db.write() as session:
            collection = Collection(name="c", description="")
            session.add(collection)
            session.flush()
            for _ in range(n_jobs):
                session.add(direct_job(collection.id))
        claimed: list[list[int]] = [[] for _ in range(n_workers)]
        barrier = threading.Barrier(n_workers)

        def work(i: int) -> None:
            barrier.wait()
            while (claim := queue.claim(f"w{i}")) is not None:
                claimed[i].append(claim.job_id)
                assert queue.heartbeat(claim, progress=("x", 1, 1)) is Outcome.held
                assert queue.complete(claim, {"ok": True}, []) is Outcome.succeeded

        threads = [threading.Thread(target=work, args=(i,)) for i in range(n_workers)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
        every = [job_id for ids in claimed for job_id in ids]
        assert sorted(every) == sorted(set(every)) and len(every) == n_jobs
        assert sum(1 for ids in claimed if ids) > 1  # they really ran side by side

        # An expired lease fences its old holder on PostgreSQL too.
        with db.write() as session:
            session.add(direct_job(collection.id))
        old = short.claim("old")
        assert old is not None
        time.sleep(0.1)
        new = queue.claim("new")
        assert new is not None and new.job_id == old.job_id and new.attempt == 2
        assert queue.heartbeat(old) is Outcome.lost
        assert queue.complete(old, {}, []) is Outcome.lost
        assert queue.complete(new, {"ok": True}, []) is Outcome.succeeded
    finally:
        db.dispose()


def test_sigkilled_worker_job_is_reclaimed_once(pg_service: Callable[..., Service]) -> None:
    svc = pg_service(workers=0).start()
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(n_chains=4, chain_length=5, n_points=100))
        job = submit_job(client, cid, ids[0])
        doomed = svc.start_worker()
        wait_job(
            client,
            job["id"],
            until=lambda j: j["status"] == "running" and j["progress"]["done"] > 0,
            timeout=60,
        )
        doomed.send_signal(signal.SIGKILL)
        doomed.wait(10)

        svc.start_worker()
        svc.start_worker()  # two survivors race for the orphaned job
        done = wait_job(client, job["id"], timeout=120)
        assert done["status"] == "succeeded", done
        assert done["attempts"] == 2
        result = client.get(f"/v1/jobs/{job['id']}/result").json()
        assert sorted(s["shape_id"] for s in result["subjects"]) == sorted(ids[1:])


def test_queue_outcomes_retries_and_callbacks(pg_url: str) -> None:
    """The lifecycle on PostgreSQL: cancel while queued / while running, a transient retry,
    and callbacks stored with the job's end and delivered (500, then 200) by two racing
    deliverers, each try once."""
    from service import migrate
    from service.core.backoff import Backoff
    from service.core.config import Settings
    from service.db import Database
    from service.jobs.callbacks import Deliverer
    from service.jobs.queue import JobQueue, Outcome
    from service.models import CallbackAttempt, Collection, Job
    from tests.service.test_queue import direct_job

    settings = Settings(
        database_url=pg_url, callback_secret="s", callback_backoff_seconds=0  # type: ignore[arg-type]
    )
    migrate.upgrade(settings)
    db = Database(pg_url)
    try:
        with db.write() as session:
            collection = Collection(name="c", description="")
            session.add(collection)
            session.flush()
            for _ in range(3):
                job = direct_job(collection.id)
                job.callback_url = "http://hooks.test/x"
                session.add(job)
        queue = JobQueue(db, backoff=Backoff(0.0, 0.0))
        assert queue.cancel(1) is Outcome.cancelled
        running = queue.claim("w")
        assert running is not None and running.job_id == 2
        assert queue.cancel(2) is Outcome.cancel_requested
        assert queue.abort(running) is Outcome.aborted
        third = queue.claim("w")
        assert third is not None
        assert queue.fail(third, "database is locked", transient=True) is Outcome.retrying
        third = queue.claim("w")
        assert third is not None and third.attempt == 2
        assert queue.complete(third, {"ok": True}, []) is Outcome.succeeded
        with db.read() as session:
            outcomes = [session.get(Job, i).outcome for i in (1, 2, 3)]  # type: ignore[union-attr]
        assert outcomes == ["cancelled", "aborted", "succeeded"]

        answers: dict[str, list[int]] = {}

        def handler(request: httpx.Request) -> httpx.Response:
            job_id = request.headers["x-regtree-delivery"]
            answers.setdefault(job_id, []).append(1)
            return httpx.Response(500 if len(answers[job_id]) == 1 else 200)

        deliverers = [
            Deliverer(db, settings, f"d{i}", transport=httpx.MockTransport(handler))
            for i in range(2)
        ]

        def drain(deliverer: Deliverer) -> None:
            while deliverer.deliver_once() is not None:
                pass

        threads = [threading.Thread(target=drain, args=(d,)) for d in deliverers]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
        assert {k: len(v) for k, v in answers.items()} == {"1": 2, "2": 2, "3": 2}
        with db.read() as session:
            attempts = session.query(CallbackAttempt).count()
        assert attempts == 6
    finally:
        db.dispose()


def test_a_worker_on_another_machine_wakes_when_a_job_is_queued(
    pg_service: Callable[..., Service],
) -> None:
    """NOTIFY at the enqueue's commit wakes a `regtree worker` listening on its own
    connection: with a 30 s poll, the second job would otherwise wait 15-30 s."""
    svc = pg_service(workers=0, env={"REGTREE_WORKER_POLL_SECONDS": "30"}).start()
    svc.start_worker()
    with svc.client() as client:
        assert second_job_queued_seconds(client, first_timeout=90) < 5.0

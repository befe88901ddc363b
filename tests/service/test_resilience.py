"""Crash recovery: a worker SIGKILLed mid-job, a server restarted with queued jobs."""

from __future__ import annotations

import signal
from collections.abc import Callable

from tests.service.conftest import (
    Service,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)


def test_worker_killed_mid_job_is_recovered_once(make_service: Callable[..., Service]) -> None:
    """The lost worker's job waits out a backoff (2 s here), then runs again."""
    svc = make_service(workers=0, env={"REGTREE_RETRY_BACKOFF_SECONDS": "2"}).start()
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(n_chains=4, chain_length=5, n_points=100))
        job = submit_job(client, cid, ids[0])
        doomed = svc.start_worker()
        running = wait_job(
            client,
            job["id"],
            until=lambda j: j["status"] == "running" and j["progress"]["done"] > 0,
            timeout=60,
        )
        assert running["attempts"] == 1
        doomed.send_signal(signal.SIGKILL)
        doomed.wait(10)

        svc.start_worker()
        waiting = wait_job(
            client, job["id"], until=lambda j: j["status"] != "running", timeout=60
        )
        assert waiting["status"] == "queued" and waiting["next_attempt_at"], waiting
        assert "stopped responding" in waiting["error"] and waiting["attempts"] == 1
        done = wait_job(client, job["id"], timeout=120)
        assert done["status"] == "succeeded" and done["outcome"] == "succeeded", done
        assert done["attempts"] == 2 and done["next_attempt_at"] is None
        result = client.get(f"/v1/jobs/{job['id']}/result").json()
        shape_ids = [s["shape_id"] for s in result["subjects"]]
        assert sorted(shape_ids) == sorted(ids[1:])  # every subject, exactly once
        assert len(client.get("/v1/jobs", params={"collection_id": cid}).json()["items"]) == 1


def test_job_fails_clearly_after_max_attempts(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0, env={"REGTREE_MAX_ATTEMPTS": "1"}).start()
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(n_chains=4, chain_length=5, n_points=100))
        job = submit_job(client, cid, ids[0])
        doomed = svc.start_worker()
        wait_job(client, job["id"], until=lambda j: j["status"] == "running", timeout=60)
        doomed.send_signal(signal.SIGKILL)
        doomed.wait(10)
        svc.start_worker()
        done = wait_job(client, job["id"], timeout=60)
        assert done["status"] == "failed"
        assert "lease expired" in done["error"] and "max_attempts" in done["error"]


def test_restart_with_queued_jobs_runs_them_all(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0).start()
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(n_chains=1, chain_length=3, n_points=40))
        jobs = [
            submit_job(client, cid, ids[0], method=m)["id"]
            for m in ("dynamic_tree", "static_tree", "direct", "dynamic_tree")
        ]
    svc.stop()
    svc.workers = 1
    svc.start()
    with svc.client() as client:
        for job_id in jobs:
            done = wait_job(client, job_id, timeout=90)
            assert done["status"] == "succeeded", done
            assert done["attempts"] == 1


def test_sigterm_gives_the_running_job_back(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0).start()
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(n_chains=4, chain_length=5, n_points=100))
        job = submit_job(client, cid, ids[0])
        first = svc.start_worker()
        wait_job(
            client,
            job["id"],
            until=lambda j: j["status"] == "running" and j["progress"]["done"] > 0,
            timeout=60,
        )
        first.send_signal(signal.SIGTERM)
        assert first.wait(20) == 0
        requeued = client.get(f"/v1/jobs/{job['id']}").json()
        assert requeued["status"] == "queued" and requeued["attempts"] == 0
        svc.start_worker()
        done = wait_job(client, job["id"], timeout=120)
        assert done["status"] == "succeeded" and done["attempts"] == 1


def test_sigterm_to_serve_stops_its_workers_and_gives_jobs_back(
    make_service: Callable[..., Service],
) -> None:
    """``docker stop``: SIGTERM to ``regtree serve`` stops the embedded workers the graceful
    way (uvicorn raises the signal again once it has shut down: that must not end the
    process before its workers are stopped), and the running job goes back to the queue."""
    svc = make_service(workers=1, env={"REGTREE_LOG_LEVEL": "INFO"}).start()
    assert svc.server is not None
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(n_chains=4, chain_length=5, n_points=100))
        job = submit_job(client, cid, ids[0])
        wait_job(
            client,
            job["id"],
            until=lambda j: j["status"] == "running" and j["progress"]["done"] > 0,
            timeout=60,
        )
        svc.server.send_signal(signal.SIGTERM)
        assert svc.server.wait(20) == 0
    logs = svc.logs()
    assert '"signal received; finishing"' in logs and '"parent process gone' not in logs, logs
    assert '"msg": "stopped"' in logs
    restarted = make_service(workers=1, database_url=svc.database_url).start()
    with restarted.client() as client:
        requeued = client.get(f"/v1/jobs/{job['id']}").json()
        assert requeued["attempts"] <= 1, requeued
        done = wait_job(client, job["id"], timeout=120)
        assert done["status"] == "succeeded" and done["attempts"] == 1, done

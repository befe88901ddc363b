"""Jobs on a Dask cluster (``REGTREE_EXECUTOR=dask``): they run, and a cancel is prompt.

The cluster is a LocalCluster in the test process (worker threads, TCP, so that the
service's worker process reaches it).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from pydantic import ValidationError

from service.core.config import Settings
from tests.service.conftest import (
    Service,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)

distributed = pytest.importorskip(
    "distributed", reason="dask[distributed] is not installed (the 'dask' extra)")


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  protocol="tcp", host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


def _env(address: str) -> dict[str, str]:
    return {"REGTREE_EXECUTOR": "dask", "REGTREE_DASK_SCHEDULER": address,
            "REGTREE_CANCEL_POLL_SECONDS": "1"}


def test_dask_needs_a_scheduler_address() -> None:
    with pytest.raises(ValidationError, match="REGTREE_DASK_SCHEDULER"):
        Settings(executor="dask")


def test_a_job_runs_on_the_cluster(make_service: Callable[..., Service], scheduler: str) -> None:
    svc = make_service(workers=1, env=_env(scheduler)).start()
    with svc.client() as client:
        cid = create_collection(client, "on-dask")
        ids = upload_family(client, cid, family(n_chains=2, chain_length=3, n_points=60))
        job = submit_job(client, cid, ids[0], method="dynamic_tree")
        done = wait_job(client, job["id"], timeout=180)
        assert done["status"] == "succeeded", done
        subjects = client.get(f"/v1/jobs/{job['id']}/result").json()["subjects"]
        assert len(subjects) == len(ids) - 1
    svc.stop()


def test_an_unreachable_cluster_fails_the_job_clearly(
    make_service: Callable[..., Service],
) -> None:
    # the setting, not the 30 s default, bounds the wait for the scheduler
    env = {**_env("tcp://127.0.0.1:9"), "REGTREE_MAX_ATTEMPTS": "1",
           "REGTREE_DASK_CONNECT_SECONDS": "2"}
    svc = make_service(workers=1, env=env).start()
    with svc.client() as client:
        cid = create_collection(client, "no-dask")
        ids = upload_family(client, cid, family(n_chains=1, chain_length=2, n_points=30))
        job = submit_job(client, cid, ids[0], method="direct")
        done = wait_job(client, job["id"], timeout=180)
        assert done["status"] == "failed", done
        assert "Dask scheduler" in str(done["error"]), done
    svc.stop()


def test_cancel_of_a_running_job_on_dask_is_prompt(
    make_service: Callable[..., Service], scheduler: str
) -> None:
    svc = make_service(workers=1, env=_env(scheduler)).start()
    with svc.client() as client:
        cid = create_collection(client, "heavy")
        shapes = family(n_chains=4, chain_length=5, n_points=1500, seed=3)[:20]
        ids = upload_family(client, cid, shapes)
        job = submit_job(client, cid, ids[0], method="direct")
        running = wait_job(
            client, job["id"],
            until=lambda j: str(j["progress"]["stage"] or "").startswith("direct"), timeout=300,
        )
        assert running["status"] == "running", running
        started = time.monotonic()
        assert client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 202
        done: dict[str, Any] = wait_job(client, job["id"], timeout=120)
        seconds = time.monotonic() - started
        assert done["status"] == "cancelled", done
        # a registration in progress on a Dask worker ends on its own (seconds at 1500
        # points), the queued ones never start
        print(f"cancelled on dask after {seconds:.1f} s")
    svc.stop()

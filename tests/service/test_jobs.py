"""Jobs end to end: submit, poll, result, transform, cancel, concurrency."""

from __future__ import annotations

import threading
from collections.abc import Callable

import httpx
import numpy as np
import pytest

from tests.service.conftest import (
    Service,
    assert_problem,
    circle,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)

pytest.importorskip("registration._tree", reason="the registration library has not landed")


def test_job_runs_to_completion_and_result_reads_back(client: httpx.Client) -> None:
    shapes = family(n_chains=2, chain_length=3, n_points=60)
    cid = create_collection(client, "job")
    ids = upload_family(client, cid, shapes)
    job = submit_job(client, cid, ids[0], compare_direct=True)
    assert job["status"] == "queued" and job["n_shapes"] == len(ids)

    done = wait_job(client, job["id"])
    assert done["status"] == "succeeded", done
    assert done["attempts"] == 1 and done["finished_at"] and done["started_at"]
    assert done["progress"]["total"] > 0

    result = client.get(f"/v1/jobs/{job['id']}/result").json()
    assert result["job_id"] == job["id"] and result["root_shape_id"] == ids[0]
    assert result["method"] == "dynamic_tree"
    by_id = {s["shape_id"]: s for s in result["subjects"]}
    assert set(by_id) == set(ids[1:])
    assert all("warped" not in s for s in result["subjects"])
    attached = [s for s in result["subjects"] if s["attached"]]
    assert attached, result["summary"]
    for s in attached:
        assert s["path_shape_ids"][0] == ids[0] and s["path_shape_ids"][-1] == s["shape_id"]
        assert s["parent_shape_id"] in ids
        assert s["error"] >= 0

    full = client.get(f"/v1/jobs/{job['id']}/result", params={"full": "true"}).json()
    assert all("warped" in s for s in full["subjects"])

    subject = attached[0]
    detail = client.get(f"/v1/jobs/{job['id']}/result/subjects/{subject['shape_id']}").json()
    assert detail["shape_id"] == subject["shape_id"]
    assert len(detail["warped"]) == len(shapes[0][1])
    assert detail["transform"] and detail["direct_error"] is not None

    # The stored transform maps the model's points onto the subject: applied to the model
    # shape it gives the warped model.
    model_points = shapes[0][1]
    mapped = client.post(
        f"/v1/jobs/{job['id']}/result/subjects/{subject['shape_id']}/transform",
        json={"points": model_points.tolist()},
    )
    assert mapped.status_code == 200, mapped.text
    np.testing.assert_allclose(
        np.array(mapped.json()["points"]), np.array(detail["warped"]), atol=1e-6
    )

    assert_problem(
        client.post(
            f"/v1/jobs/{job['id']}/result/subjects/{subject['shape_id']}/transform",
            json={"points": []},
        ),
        422,
    )
    assert_problem(client.get(f"/v1/jobs/{job['id']}/result/subjects/{ids[0] + 10_000}"), 404)
    listed = client.get("/v1/jobs", params={"collection_id": cid, "status": "succeeded"}).json()
    assert [j["id"] for j in listed["items"]] == [job["id"]]


def test_job_validation(client: httpx.Client) -> None:
    a = create_collection(client, "a")
    b = create_collection(client, "b")
    ids_a = upload_family(client, a, [("x", circle(20)), ("y", circle(20, 2.0))])
    ids_b = upload_family(client, b, [("z", circle(20))])
    problem = assert_problem(
        client.post("/v1/jobs", json={"collection_id": a, "model_shape_id": ids_b[0]}), 422
    )
    assert f"collection {b}" in problem["detail"]
    # A collection with only the model shape has nothing to register.
    assert_problem(
        client.post("/v1/jobs", json={"collection_id": b, "model_shape_id": ids_b[0]}), 422
    )
    # Same Idempotency-Key, same body: the same job; different body: 422.
    body = {"collection_id": a, "model_shape_id": ids_a[0], "method": "direct"}
    first = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "job-k"})
    again = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "job-k"})
    assert first.status_code == again.status_code == 202
    assert first.json()["id"] == again.json()["id"]
    assert_problem(
        client.post(
            "/v1/jobs", json={**body, "method": "static_tree"}, headers={"Idempotency-Key": "job-k"}
        ),
        422,
    )
    done = wait_job(client, first.json()["id"])
    assert done["status"] == "succeeded", done
    # Upright collections: max_rotation reaches the library and is bounded to [0, 180].
    upright = submit_job(client, a, ids_a[0], method="direct", max_rotation=30)
    assert upright["params"]["max_rotation"] == 30
    assert wait_job(client, upright["id"])["status"] == "succeeded"
    assert client.get(f"/v1/jobs/{upright['id']}/result").json()["options"]["max_rotation"] == 30
    assert_problem(client.post("/v1/jobs", json={**body, "max_rotation": 200}), 422)
    # A finished job cannot be cancelled; a result of an unfinished one is a 409 problem.
    assert_problem(client.post(f"/v1/jobs/{done['id']}/cancel"), 409)


def test_result_before_success_is_409(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0).start()
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(1, 2, 30))
        job = submit_job(client, cid, ids[0])
        problem = assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 409)
        assert "queued" in problem["detail"]
        # Cancel of a queued job is immediate.
        cancelled = client.post(f"/v1/jobs/{job['id']}/cancel")
        assert cancelled.status_code == 202 and cancelled.json()["status"] == "cancelled"
        # A worker started afterwards does not run it.
        svc.start_worker()
        other = submit_job(client, cid, ids[0], method="direct")
        assert wait_job(client, other["id"])["status"] == "succeeded"
        assert client.get(f"/v1/jobs/{job['id']}").json()["status"] == "cancelled"
        assert client.get(f"/v1/jobs/{job['id']}").json()["attempts"] == 0


def test_cancel_running_job(client: httpx.Client) -> None:
    cid = create_collection(client, "cancel-running")
    ids = upload_family(client, cid, family(n_chains=4, chain_length=5, n_points=100))
    job = submit_job(client, cid, ids[0], compare_direct=True)
    wait_job(
        client,
        job["id"],
        until=lambda j: j["status"] == "running" and j["progress"]["done"] > 0,
        timeout=60,
    )
    response = client.post(f"/v1/jobs/{job['id']}/cancel")
    assert response.status_code == 202
    assert response.json()["cancel_requested"] is True
    done = wait_job(client, job["id"], timeout=10)
    assert done["status"] == "cancelled", done
    assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 409)


def test_concurrent_uploads_while_a_job_runs(client: httpx.Client, service: Service) -> None:
    cid = create_collection(client, "busy")
    ids = upload_family(client, cid, family(n_chains=3, chain_length=4, n_points=80))
    job = submit_job(client, cid, ids[0])
    target = create_collection(client, "uploads")
    errors: list[str] = []
    created: list[int] = []
    lock = threading.Lock()

    def upload(i: int) -> None:
        with service.client() as c:
            r = c.post(
                f"/v1/collections/{target}/shapes",
                json={"name": f"s{i}", "points": circle(40, 1 + i).tolist()},
            )
            with lock:
                if r.status_code == 201:
                    created.append(r.json()["id"])
                else:
                    errors.append(r.text)

    threads = [threading.Thread(target=upload, args=(i,)) for i in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    listing = client.get(f"/v1/collections/{target}/shapes", params={"limit": 100}).json()
    assert listing["total"] == 20 and sorted(i["id"] for i in listing["items"]) == sorted(created)
    assert sorted(i["name"] for i in listing["items"]) == sorted(f"s{i}" for i in range(20))
    assert wait_job(client, job["id"])["status"] == "succeeded"

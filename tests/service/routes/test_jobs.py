"""``/v1/jobs`` (service/api/routes/jobs.py), in process; a job's result comes from one worker
step in this process (``Finished``)."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient

from tests.service.conftest import (
    assert_problem,
    circle,
    create_collection,
    submit_job,
    upload_family,
)
from tests.service.routes.conftest import Finished


def _collection(client: TestClient, n: int = 3) -> tuple[int, list[int]]:
    cid = create_collection(client)
    ids = upload_family(client, cid, [(f"s{i}", circle(r=1 + i)) for i in range(n)])
    return cid, ids


def test_submit_answers_202_queued_with_location(client: TestClient) -> None:
    cid, ids = _collection(client)
    job = submit_job(client, cid, ids[0])
    assert job["status"] == "queued"
    assert (job["collection_id"], job["model_shape_id"], job["n_shapes"]) == (cid, ids[0], 3)
    assert client.get(f"/v1/jobs/{job['id']}").json()["status"] == "queued"


def test_submit_refuses_what_cannot_run(client: TestClient) -> None:
    cid, ids = _collection(client)
    other, other_ids = _collection(client)
    lonely = create_collection(client, "lonely")
    (single,) = upload_family(client, lonely, [("only", circle())])
    cases = [
        ({"collection_id": 999, "model_shape_id": ids[0]}, "collection 999"),
        ({"collection_id": cid, "model_shape_id": 999}, "model shape 999"),
        ({"collection_id": cid, "model_shape_id": other_ids[0]}, f"collection {other}"),
        ({"collection_id": lonely, "model_shape_id": single}, "at least one other shape"),
    ]
    for body, words in cases:
        problem = assert_problem(client.post("/v1/jobs", json=body), 422)
        assert problem["type"] == "/problems/invalid-job"
        assert words in problem["detail"], problem
    bad_method = {"collection_id": cid, "model_shape_id": ids[0], "method": "nope"}
    assert any(
        e["loc"][-1] == "method"
        for e in assert_problem(client.post("/v1/jobs", json=bad_method), 422)["errors"]
    )
    assert client.get("/v1/jobs").json()["total"] == 0


def test_list_filters_and_newest_first(client: TestClient) -> None:
    cid, ids = _collection(client)
    other, other_ids = _collection(client)
    first = submit_job(client, cid, ids[0])["id"]
    second = submit_job(client, other, other_ids[0])["id"]
    client.post(f"/v1/jobs/{first}/cancel")
    listed = client.get("/v1/jobs").json()
    assert [j["id"] for j in listed["items"]] == [second, first]
    by_collection = client.get("/v1/jobs", params={"collection_id": other}).json()
    assert [j["id"] for j in by_collection["items"]] == [second]
    cancelled = client.get("/v1/jobs", params={"status": "cancelled"}).json()
    assert [j["id"] for j in cancelled["items"]] == [first]
    assert_problem(client.get("/v1/jobs", params={"status": "lost"}), 422)


def test_cancel_queued_then_finished(client: TestClient) -> None:
    cid, ids = _collection(client)
    job_id = submit_job(client, cid, ids[0])["id"]
    response = client.post(f"/v1/jobs/{job_id}/cancel")
    assert response.status_code == 202
    assert response.json()["status"] == "cancelled"
    problem = assert_problem(client.post(f"/v1/jobs/{job_id}/cancel"), 409)
    assert problem["type"] == "/problems/job-finished"
    assert_problem(client.post("/v1/jobs/999/cancel"), 404)


def test_unknown_and_unfinished_jobs_have_no_result(client: TestClient) -> None:
    assert_problem(client.get("/v1/jobs/999"), 404)
    assert_problem(client.get("/v1/jobs/999/result"), 404)
    assert_problem(client.get("/v1/jobs/abc"), 422)
    cid, ids = _collection(client)
    job_id = submit_job(client, cid, ids[0])["id"]
    problem = assert_problem(client.get(f"/v1/jobs/{job_id}/result"), 409)
    assert problem["type"] == "/problems/result-not-ready"
    assert "queued" in problem["detail"]
    assert_problem(client.get(f"/v1/jobs/{job_id}/result/subjects/{ids[1]}"), 409)


def test_result_and_subjects_of_a_finished_job(finished: Finished) -> None:
    client, result = finished.client, finished.result
    subjects = result["subjects"]
    assert sorted(s["shape_id"] for s in subjects) == sorted(finished.shape_ids[1:])
    sid = subjects[0]["shape_id"]
    subject = client.get(f"/v1/jobs/{finished.job_id}/result/subjects/{sid}")
    assert subject.status_code == 200
    assert subject.json()["shape_id"] == sid
    # the model answers as the root of the tree, with the identity transform
    root = client.get(f"/v1/jobs/{finished.job_id}/result/subjects/{finished.shape_ids[0]}")
    assert root.status_code == 200, root.text
    assert root.json()["root"] is True and root.json()["transform"]["steps"] == []
    # an unknown shape is not found
    assert_problem(client.get(f"/v1/jobs/{finished.job_id}/result/subjects/99999"), 404)
    assert_problem(client.get(f"/v1/jobs/{finished.job_id}/result", params={"sort": "x"}), 422)


def test_transform_maps_points_and_refuses_bad_input(finished: Finished) -> None:
    client = finished.client
    attached = next(s for s in finished.result["subjects"] if s["attached"])
    url = f"/v1/jobs/{finished.job_id}/result/subjects/{attached['shape_id']}/transform"
    points = circle(12).tolist()
    response = client.post(url, json={"points": points})
    assert response.status_code == 200, response.text
    mapped = np.asarray(response.json()["points"])
    assert mapped.shape == (12, 2) and np.isfinite(mapped).all()
    assert not np.allclose(mapped, points)  # a registration moves the model
    assert_problem(client.post(url, json={"points": [[0, 0, 0]]}), 422)
    assert_problem(client.post(url, json={}), 422)
    unknown = f"/v1/jobs/{finished.job_id}/result/subjects/99999/transform"
    assert_problem(client.post(unknown, json={"points": points}), 404)

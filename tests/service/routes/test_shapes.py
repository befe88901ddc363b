"""``/v1/collections/{id}/shapes`` (service/api/routes/shapes.py), in process."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fastapi.testclient import TestClient

from tests.service.conftest import (
    assert_problem,
    circle,
    create_collection,
    npy_bytes,
    submit_job,
    upload_family,
)


def test_one_json_shape_answers_201_with_location_and_keeps_the_points(
    client: TestClient,
) -> None:
    cid = create_collection(client)
    points = circle(40)
    response = client.post(
        f"/v1/collections/{cid}/shapes", json={"name": "ring", "points": points.tolist()}
    )
    assert response.status_code == 201, response.text
    shape = response.json()
    assert response.headers["location"] == f"/v1/collections/{cid}/shapes/{shape['id']}"
    assert (shape["name"], shape["n_points"]) == ("ring", 40)
    detail = client.get(f"/v1/collections/{cid}/shapes/{shape['id']}").json()
    np.testing.assert_allclose(np.asarray(detail["points"]), points)


def test_batch_csv_and_npy_uploads(client: TestClient) -> None:
    cid = create_collection(client)
    ids = upload_family(client, cid, [("a", circle()), ("b", circle(r=2))])
    assert len(ids) == 2
    csv = "\n".join(f"{x},{y}" for x, y in circle(30)).encode()
    response = client.post(
        f"/v1/collections/{cid}/shapes",
        params={"name": "from-csv"},
        content=csv,
        headers={"content-type": "text/csv"},
    )
    assert response.status_code == 201, response.text
    assert response.json()["n_points"] == 30
    files = [("files", ("disc.npy", npy_bytes(circle(25)), "application/octet-stream"))]
    response = client.post(f"/v1/collections/{cid}/shapes", files=files)
    assert response.status_code == 201, response.text
    assert [s["name"] for s in response.json()["items"]] == ["disc"]
    listed = client.get(f"/v1/collections/{cid}/shapes").json()
    assert listed["total"] == 4
    assert "points" not in listed["items"][0]  # metadata only


def test_bad_uploads_are_problems_and_store_nothing(
    make_client: Callable[..., TestClient],
) -> None:
    client = make_client(max_body_bytes=64 * 1024)
    cid = create_collection(client)
    url = f"/v1/collections/{cid}/shapes"
    too_few = assert_problem(client.post(url, json={"name": "x", "points": [[0, 0], [1, 1]]}), 422)
    assert "point" in too_few["detail"]
    not_pairs = assert_problem(client.post(url, json={"name": "x", "points": [[0, 0, 0]] * 5}), 422)
    assert not_pairs["type"] == "/problems/invalid-shape"
    empty_batch = assert_problem(client.post(url, json={"shapes": []}), 422)
    assert "non-empty" in empty_batch["detail"]
    unsupported = assert_problem(
        client.post(url, content=b"x", headers={"content-type": "application/xml"}), 415
    )
    assert "application/xml" in unsupported["detail"]
    big = {"name": "big", "points": circle(5000).tolist()}
    problem = assert_problem(client.post(url, json=big), 413)
    assert "max_body_bytes" in problem["detail"] or "limit" in problem["detail"]
    assert_problem(client.post(url, params={"target_points": 1}, json={"shapes": []}), 422)
    assert client.get(url).json()["total"] == 0


def test_unknown_collection_and_shape(client: TestClient) -> None:
    body = {"name": "x", "points": circle().tolist()}
    assert_problem(client.post("/v1/collections/999/shapes", json=body), 404)
    assert_problem(client.get("/v1/collections/999/shapes"), 404)
    cid = create_collection(client)
    other = create_collection(client, "other")
    (sid,) = upload_family(client, other, [("a", circle())])
    # a shape is found only in its own collection
    assert_problem(client.get(f"/v1/collections/{cid}/shapes/{sid}"), 404)
    assert_problem(client.delete(f"/v1/collections/{cid}/shapes/{sid}"), 404)
    assert_problem(client.get(f"/v1/collections/{cid}/shapes/abc"), 422)


def test_delete_refuses_a_shape_an_unfinished_job_uses(client: TestClient) -> None:
    cid = create_collection(client)
    ids = upload_family(
        client, cid, [("a", circle()), ("b", circle(r=2)), ("c", circle(r=3))]
    )
    job = submit_job(client, cid, ids[0])
    problem = assert_problem(client.delete(f"/v1/collections/{cid}/shapes/{ids[1]}"), 409)
    assert problem["type"] == "/problems/shape-in-use"
    assert str(job["id"]) in problem["detail"]
    assert client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 202
    assert client.delete(f"/v1/collections/{cid}/shapes/{ids[1]}").status_code == 204
    assert_problem(client.get(f"/v1/collections/{cid}/shapes/{ids[1]}"), 404)

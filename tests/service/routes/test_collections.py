"""``/v1/collections`` (service/api/routes/collections.py), in process."""

from __future__ import annotations

from collections.abc import Callable

from fastapi.testclient import TestClient

from tests.service.conftest import assert_problem, circle, upload_family
from tests.service.routes.conftest import KEY


def test_create_answers_201_with_location_and_counts(client: TestClient) -> None:
    response = client.post("/v1/collections", json={"name": "leaves", "description": "d"})
    assert response.status_code == 201, response.text
    body = response.json()
    assert response.headers["location"] == f"/v1/collections/{body['id']}"
    assert (body["name"], body["description"], body["n_shapes"]) == ("leaves", "d", 0)

    upload_family(client, body["id"], [("a", circle()), ("b", circle(r=2))])
    again = client.get(f"/v1/collections/{body['id']}")
    assert again.status_code == 200
    assert again.json()["n_shapes"] == 2


def test_create_refuses_a_bad_body_with_a_problem(client: TestClient) -> None:
    problem = assert_problem(client.post("/v1/collections", json={"description": "x"}), 422)
    assert any(e["loc"][-1] == "name" for e in problem["errors"])
    malformed = client.post(
        "/v1/collections", content=b"{not json", headers={"content-type": "application/json"}
    )
    # a 422, as the schema states (test_openapi.py checks every operation)
    assert "not valid JSON" in assert_problem(malformed, 422)["detail"]
    assert client.get("/v1/collections").json()["total"] == 0  # nothing stored


def test_idempotency_key_returns_the_first_collection(client: TestClient) -> None:
    headers = {"Idempotency-Key": "k-1"}
    first = client.post("/v1/collections", json={"name": "a"}, headers=headers)
    second = client.post("/v1/collections", json={"name": "a"}, headers=headers)
    assert first.status_code == second.status_code == 201
    assert first.json()["id"] == second.json()["id"]
    assert_problem(client.post("/v1/collections", json={"name": "b"}, headers=headers), 422)
    assert client.get("/v1/collections").json()["total"] == 1


def test_list_pages_and_bounds(client: TestClient) -> None:
    ids = [client.post("/v1/collections", json={"name": f"c{i}"}).json()["id"] for i in range(3)]
    page = client.get("/v1/collections", params={"limit": 2, "offset": 1}).json()
    assert page["total"] == 3
    assert (page["limit"], page["offset"]) == (2, 1)
    assert [c["id"] for c in page["items"]] == ids[1:]
    assert_problem(client.get("/v1/collections", params={"limit": 0}), 422)
    assert_problem(client.get("/v1/collections", params={"offset": -1}), 422)
    problem = assert_problem(client.get("/v1/collections", params={"limit": 10_000}), 422)
    assert "max_page_size" in problem["errors"][0]["msg"]


def test_read_and_delete_unknown_or_invalid_ids(client: TestClient) -> None:
    for method in ("GET", "DELETE"):
        problem = assert_problem(client.request(method, "/v1/collections/999"), 404)
        assert "999" in problem["detail"]
        assert_problem(client.request(method, f"/v1/collections/{2**63}"), 422)
        assert_problem(client.request(method, "/v1/collections/abc"), 422)


def test_delete_removes_the_collection_and_its_shapes(client: TestClient) -> None:
    cid = client.post("/v1/collections", json={"name": "gone"}).json()["id"]
    upload_family(client, cid, [("a", circle()), ("b", circle(r=2))])
    response = client.delete(f"/v1/collections/{cid}")
    assert response.status_code == 204
    assert response.content == b""
    assert_problem(client.get(f"/v1/collections/{cid}"), 404)
    assert_problem(client.get(f"/v1/collections/{cid}/shapes"), 404)


def test_api_key_is_required_when_set(make_client: Callable[..., TestClient]) -> None:
    client = make_client(api_key=KEY)
    problem = assert_problem(client.get("/v1/collections"), 401)
    assert "X-API-Key" in problem["detail"]
    assert client.get("/v1/collections", headers={"X-API-Key": KEY}).status_code == 200
    bearer = {"Authorization": f"Bearer {KEY}"}
    assert client.get("/v1/collections", headers=bearer).status_code == 200
    assert_problem(client.get("/v1/collections", headers={"X-API-Key": "wrong"}), 401)

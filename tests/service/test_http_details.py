"""HTTP details the schemathesis fuzz found: a 405's ``Allow`` header and the upload bounds the
schema states, checked against the real server."""

from __future__ import annotations

import httpx
import pytest

from tests.service.conftest import assert_problem, create_collection


@pytest.mark.parametrize(
    ("method", "path", "allow"),
    [
        ("PUT", "/v1/collections", "GET, POST"),
        ("DELETE", "/v1/collections", "GET, POST"),
        ("PATCH", "/v1/collections/1", "GET, DELETE"),
        ("PUT", "/v1/collections/1/shapes", "GET, POST"),
        ("POST", "/v1/collections/1/shapes/1", "GET, DELETE"),
        ("DELETE", "/v1/jobs", "GET, POST"),
        ("GET", "/v1/jobs/1/cancel", "POST"),
        ("POST", "/healthz", "GET"),
    ],
)
def test_405_allow_lists_every_method_of_the_path(
    client: httpx.Client, method: str, path: str, allow: str
) -> None:
    response = client.request(method, path)
    assert_problem(response, 405)
    assert response.headers["allow"] == allow
    assert len(response.headers.get_list("allow")) == 1


def test_schema_states_the_upload_bounds(client: httpx.Client) -> None:
    document = client.get("/openapi.json").json()
    schemas = document["components"]["schemas"]
    points = schemas["ShapeJSON"]["properties"]["points"]
    assert (points["minItems"], points["maxItems"]) == (3, 20000)
    assert points["items"]["prefixItems"][0]["maximum"] == 1e7
    assert schemas["ShapeBatchJSON"]["properties"]["shapes"]["minItems"] == 1
    upload = document["paths"]["/v1/collections/{collection_id}/shapes"]["post"]
    (query,) = [p for p in upload["parameters"] if p["name"] == "target_points"]
    assert (query["schema"]["minimum"], query["schema"]["maximum"]) == (3, 20000)
    form = upload["requestBody"]["content"]["multipart/form-data"]["schema"]["properties"]
    assert (form["target_points"]["minimum"], form["target_points"]["maximum"]) == (3, 20000)


def test_upload_bounds_keep_their_precise_problems(client: httpx.Client) -> None:
    cid = create_collection(client, "bounds")
    url = f"/v1/collections/{cid}/shapes"
    triangle = b"0 0\n1 0\n0 1\n"
    for target in (0, 2, 20001):
        response = client.post(
            url,
            params={"target_points": target},
            content=triangle,
            headers={"content-type": "text/plain"},
        )
        body = assert_problem(response, 422)
        assert body["type"] == "/problems/invalid-shape"
        assert "target_points must be an integer between 3 and 20000" in body["detail"]
    response = client.post(
        url, files={"files": ("a.txt", triangle, "text/plain")}, data={"target_points": "2"}
    )
    assert "between 3 and 20000" in assert_problem(response, 422)["detail"]
    assert (
        "at least 3" in assert_problem(client.post(url, json={"points": [[0, 0]]}), 422)["detail"]
    )
    ok = client.post(
        url, params={"target_points": 3}, content=triangle, headers={"content-type": "text/plain"}
    )
    assert ok.status_code == 201, ok.text


def test_names_with_nul_are_refused(client: httpx.Client) -> None:
    """PostgreSQL cannot store NUL in text; every database refuses it the same way."""
    assert_problem(client.post("/v1/collections", json={"name": "a\u0000b"}), 422)
    assert_problem(client.post("/v1/collections", json={"name": "a", "description": "\u0000"}), 422)
    cid = create_collection(client, "nul")
    url = f"/v1/collections/{cid}/shapes"
    triangle = [[0, 0], [1, 0], [0, 1]]
    body = assert_problem(client.post(url, json={"name": "x\u0000", "points": triangle}), 422)
    assert "NUL" in body["detail"]
    response = client.post(
        url,
        params={"name": "x\u0000"},
        content=b"0 0\n1 0\n0 1\n",
        headers={"content-type": "text/plain"},
    )
    assert_problem(response, 422)
    # A raw NUL in a multipart file name (httpx would percent-encode it) is dropped.
    multipart = (
        b"--b\r\n"
        b'Content-Disposition: form-data; name="files"; filename="tri\x00angle.txt"\r\n'
        b"Content-Type: text/plain\r\n\r\n"
        b"0 0\n1 0\n0 1\n\r\n"
        b"--b--\r\n"
    )
    response = client.post(
        url, content=multipart, headers={"content-type": "multipart/form-data; boundary=b"}
    )
    assert response.status_code == 201, response.text
    assert response.json()["items"][0]["name"] == "triangle"

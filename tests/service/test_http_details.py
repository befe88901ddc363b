"""HTTP details the schemathesis fuzz found: a 405's ``Allow`` header and the upload bounds the
schema states, checked against the real server; and the limits are the operator's settings,
stated by the schema and enforced alike."""

from __future__ import annotations

import io
import json
import re
from collections.abc import Callable, Iterator
from typing import Any

import httpx
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


# --- limits are settings: the schema states the configured ones, the server enforces them ---

#: Non-default limits, set as an operator would (REGTREE_* environment variables).
LIMITS = {
    "max_body_bytes": 20_000,
    "min_points": 4,
    "max_points_per_shape": 50,
    "max_coordinate": 1000.0,
    "max_image_pixels": 64 * 48,
    "max_batch_files": 3,
    "max_shapes_per_collection": 12,
    "max_page_size": 7,
}
UPLOAD_PATH = "/v1/collections/{collection_id}/shapes"


@pytest.fixture(scope="module")
def limited(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    env = {f"REGTREE_{name.upper()}": str(value) for name, value in LIMITS.items()}
    svc = Service(tmp_path_factory.mktemp("limited"), workers=1, env=env).start()
    yield svc
    svc.stop()
    assert not svc.unhandled_errors(), svc.unhandled_errors()


def polygon(n: int, r: float = 1.0) -> list[list[float]]:
    return [[float(x), float(y)] for x, y in circle(n, r)]


def png(width: int, height: int) -> bytes:
    from PIL import Image, ImageDraw

    image = Image.new("L", (width, height), 255)
    ImageDraw.Draw(image).ellipse((8, 8, width - 8, height - 8), fill=0)
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def test_openapi_states_the_configured_limits(limited: Service) -> None:
    with limited.client() as client:
        response = client.get("/openapi.json")
    text = response.text
    document = response.json()
    # Every placeholder was filled in from the settings.
    assert "x-regtree" not in text
    assert not re.search(r"\{(max|min|default)_\w+(:[^}]*)?\}", text), text
    schemas = document["components"]["schemas"]

    points = schemas["ShapeJSON"]["properties"]["points"]
    assert (points["minItems"], points["maxItems"]) == (4, 50)
    for coordinate in points["items"]["prefixItems"]:
        assert (coordinate["minimum"], coordinate["maximum"]) == (-1000, 1000)
    assert "4 to 50 points" in points["description"] and "±1000" in points["description"]
    (example,) = schemas["ShapeJSON"]["examples"]
    assert len(example["points"]) == 4
    assert schemas["ShapeBatchJSON"]["properties"]["shapes"]["maxItems"] == 3
    assert schemas["TransformRequest"]["properties"]["points"]["maxItems"] == 50

    upload = document["paths"][UPLOAD_PATH]["post"]
    (query,) = [p for p in upload["parameters"] if p["name"] == "target_points"]
    assert (query["schema"]["minimum"], query["schema"]["maximum"]) == (4, 50)
    content = upload["requestBody"]["content"]
    form = content["multipart/form-data"]["schema"]["properties"]
    assert (form["target_points"]["minimum"], form["target_points"]["maximum"]) == (4, 50)
    assert form["files"]["maxItems"] == 3
    examples = content["application/json"]["examples"]
    assert len(examples["single"]["value"]["points"]) == 4
    assert [len(s["points"]) for s in examples["batch"]["value"]["shapes"]] == [4, 4]
    assert content["text/csv"]["example"].count("\n") == 5  # header and 4 points
    assert "3072 pixels" in content["image/png"]["description"]
    for phrase in ("20000 bytes", "4 to 50 points", "±1000", "3072 pixels", "at most 3", "12"):
        assert phrase in upload["description"], phrase

    for path in ("/v1/collections", "/v1/jobs", UPLOAD_PATH):
        (limit,) = [p for p in document["paths"][path]["get"]["parameters"] if p["name"] == "limit"]
        assert (limit["schema"]["maximum"], limit["schema"]["default"]) == (7, 7)

    # A body over the limit is refused on every operation that takes one, and documented.
    for path, item in document["paths"].items():
        for method, operation in item.items():
            if "requestBody" in operation:
                refusal = operation["responses"]["413"]
                assert "20000 bytes" in refusal["description"], (method, path)
                assert "application/problem+json" in refusal["content"]

    description = document["info"]["description"]
    for phrase in (
        "20000 bytes",
        "4 to 50",
        "±1000",
        "3072 pixels",
        "at most 3 files",
        "at most 12 shapes",
        "at most 7 items",
    ):
        assert phrase in description, phrase


def _documented(document: dict[str, Any], method: str, path: str, status: int) -> None:
    responses = document["paths"][path][method]["responses"]
    assert str(status) in responses, (method, path, status, sorted(responses))


def test_configured_limits_are_enforced_as_documented(limited: Service) -> None:
    """At each limit the request passes; one past it, the documented problem, and nothing is
    stored."""
    with limited.client() as client:
        document = client.get("/openapi.json").json()
        cid = create_collection(client, "limits")
        url = f"/v1/collections/{cid}/shapes"

        def count() -> int:
            return int(client.get(url).json()["total"])

        def refused(send: Callable[[], httpx.Response], status: int, *phrases: str) -> None:
            before = count()
            _documented(document, "post", UPLOAD_PATH, status)
            detail = assert_problem(send(), status)["detail"]
            for phrase in phrases:
                assert phrase in detail, (phrase, detail)
            assert count() == before

        def stored(response: httpx.Response) -> None:
            assert response.status_code == 201, response.text

        # Points per shape, both ends.
        stored(client.post(url, json={"points": polygon(50)}))
        refused(
            lambda: client.post(url, json={"points": polygon(51)}),
            422,
            "51 points; at most 50",
            "max_points_per_shape",
        )
        stored(client.post(url, json={"points": polygon(4)}))
        refused(
            lambda: client.post(url, json={"points": polygon(3)}), 422, "at least 4", "min_points"
        )
        # Coordinates.
        stored(client.post(url, json={"points": [[1000, 0], [-1000, 0], [0, 1000], [0, -1]]}))
        refused(
            lambda: client.post(url, json={"points": [[1000.5, 0], [-1, 0], [0, 1], [0, -1]]}),
            422,
            "±1000",
            "max_coordinate",
        )
        assert count() == 3

        # Shapes (JSON batch) and files (multipart) in one upload.
        batch = [{"name": f"s{i}", "points": polygon(4 + i)} for i in range(4)]
        stored(client.post(url, json={"shapes": batch[:3]}))
        refused(
            lambda: client.post(url, json={"shapes": batch}),
            422,
            "4 shapes in one upload; at most 3",
            "max_batch_files",
        )
        files = [("files", (f"f{i}.txt", b"0 0\n1 0\n1 1\n0 1\n", "text/plain")) for i in range(5)]
        stored(client.post(url, files=files[:3]))
        for n in (4, 5):  # one past the limit, and past what the parser reads
            refused(
                lambda n=n: client.post(url, files=files[:n]),  # type: ignore[misc]
                422,
                "in one upload; at most 3",
                "max_batch_files",
            )
        assert count() == 9

        # target_points and the image size.
        square = b"0 0\n1 0\n1 1\n0 1\n"
        raw = {"content-type": "text/plain"}
        client.delete(f"{url}/{client.get(url).json()['items'][0]['id']}")
        stored(client.post(url, params={"target_points": 50}, content=square, headers=raw))
        refused(
            lambda: client.post(url, params={"target_points": 51}, content=square, headers=raw),
            422,
            "between 4 and 50",
        )
        image = {"content-type": "image/png"}
        params = {"target_points": 20}
        client.delete(f"{url}/{client.get(url).json()['items'][0]['id']}")
        stored(client.post(url, params=params, content=png(64, 48), headers=image))
        refused(
            lambda: client.post(url, params=params, content=png(65, 48), headers=image),
            422,
            "65x48 = 3120 pixels; the limit is 3072 pixels",
            "max_image_pixels",
        )

        # Shapes in a collection: this one holds 9, the limit is 12 (names repeat: keep).
        keep = {"on_conflict": "keep"}
        stored(client.post(url, json={"shapes": batch[:3]}, params=keep))
        assert count() == 12
        refused(
            lambda: client.post(url, json={"points": polygon(4)}, params=keep),
            422,
            "limit of 12",
            "max_shapes_per_collection",
        )

        # The request body: the limit itself passes (JSON may end in white space), one past
        # it is 413.
        other = create_collection(client, "body")
        body = json.dumps({"points": polygon(4)}).encode()
        exact = body + b" " * (int(LIMITS["max_body_bytes"]) - len(body))
        json_type = {"content-type": "application/json"}
        stored(client.post(f"/v1/collections/{other}/shapes", content=exact, headers=json_type))
        refused(
            lambda: client.post(
                f"/v1/collections/{other}/shapes", content=exact + b" ", headers=json_type
            ),
            413,
            "larger than the limit of 20000 bytes",
        )

        # Page size, on every list.
        for path in ("/v1/collections", "/v1/jobs", url):
            page = client.get(path, params={"limit": 7})
            assert page.status_code == 200, page.text
            assert client.get(path).json()["limit"] == 7  # the default is capped too
            _documented(document, "get", path if path != url else UPLOAD_PATH, 422)
            problem = assert_problem(client.get(path, params={"limit": 8}), 422)
            assert problem["type"] == "/problems/validation-error"
            assert "query.limit" in problem["detail"] and "7" in problem["detail"]
        assert len(client.get(url, params={"limit": 7}).json()["items"]) == 7


def test_transform_points_limit_is_enforced_as_documented(limited: Service) -> None:
    with limited.client() as client:
        document = client.get("/openapi.json").json()
        cid = create_collection(client, "transform")
        ids = upload_family(client, cid, family(n_chains=1, chain_length=2, n_points=40))
        job = wait_job(client, submit_job(client, cid, ids[0], method="direct")["id"])
        assert job["status"] == "succeeded", job
        path = "/v1/jobs/{job_id}/result/subjects/{shape_id}/transform"
        url = f"/v1/jobs/{job['id']}/result/subjects/{ids[1]}/transform"
        ok = client.post(url, json={"points": polygon(50)})
        assert ok.status_code == 200, ok.text
        assert len(ok.json()["points"]) == 50
        _documented(document, "post", path, 422)
        problem = assert_problem(client.post(url, json={"points": polygon(51)}), 422)
        assert "51 points; at most 50" in problem["detail"]


def test_client_lists_with_the_configured_page_size(limited: Service) -> None:
    """The Python client asks for pages of 500; a server with a smaller max_page_size answers
    422 naming its limit, and the client goes on with pages of that size."""
    from service.client import RegtreeClient

    with RegtreeClient(limited.base_url, timeout=30) as rt:
        names = {f"paged-{i}" for i in range(9)}
        for name in sorted(names):
            rt.create_collection(name)
        listed = {c.name for c in rt.list_collections()}
    assert names <= listed


def test_inconsistent_point_limits_are_refused_at_start() -> None:
    """Not at the first upload (ingest.Limits would raise there: a 500 on every upload)."""
    from pydantic import ValidationError

    from service.core.config import Settings

    with pytest.raises(ValidationError, match=r"min_points .* must not exceed"):
        Settings(min_points=51, max_points_per_shape=50)
    assert Settings(min_points=50, max_points_per_shape=50).min_points == 50

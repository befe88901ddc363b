"""The HTTP API against a real server: uploads in every format, listing, errors."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from PIL import Image, ImageDraw

from tests.service.conftest import (
    Service,
    assert_problem,
    circle,
    create_collection,
    npy_bytes,
)


def png_ellipse(fmt: str = "PNG") -> bytes:
    image = Image.new("L", (90, 70), 255)
    ImageDraw.Draw(image).ellipse((10, 12, 80, 58), fill=0)
    buffer = io.BytesIO()
    image.save(buffer, fmt)
    return buffer.getvalue()


TRIANGLE = [[0, 0], [1, 0], [0, 1]]


def csv_text(points: np.ndarray) -> str:
    return "x,y\n" + "\n".join(f"{x:.6f},{y:.6f}" for x, y in points)


def test_healthz(client: httpx.Client) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}


def test_collection_crud_and_pagination(client: httpx.Client) -> None:
    ids = [create_collection(client, f"page-{i}") for i in range(3)]
    page = client.get("/v1/collections", params={"limit": 2, "offset": 1}).json()
    assert page["limit"] == 2 and page["offset"] == 1 and page["total"] >= 3
    assert len(page["items"]) == 2
    one = client.get(f"/v1/collections/{ids[0]}").json()
    assert one["name"] == "page-0" and one["n_shapes"] == 0
    assert client.delete(f"/v1/collections/{ids[0]}").status_code == 204
    assert_problem(client.get(f"/v1/collections/{ids[0]}"), 404)
    assert_problem(client.delete(f"/v1/collections/{ids[0]}"), 404)


def test_upload_every_format(client: httpx.Client) -> None:
    cid = create_collection(client, "formats")
    pts = circle(50)
    url = f"/v1/collections/{cid}/shapes"

    r = client.post(url, json={"name": "json", "points": pts.tolist()})
    assert r.status_code == 201, r.text
    assert r.headers["location"] == f"{url}/{r.json()['id']}"
    assert r.json()["source_format"] == "json" and r.json()["n_points"] == 50

    raw = [
        ("text/csv", csv_text(pts).encode(), "csv"),
        ("text/plain", csv_text(pts).replace(",", " ").encode(), "txt"),
        ("application/octet-stream", npy_bytes(pts), "npy"),
        ("image/png", png_ellipse("PNG"), "png:contour"),
        ("image/jpeg", png_ellipse("JPEG"), "jpeg:contour"),
    ]
    for content_type, body, fmt in raw:
        r = client.post(
            url,
            params={"name": f"raw-{fmt}", "target_points": 80},
            content=body,
            headers={"content-type": content_type},
        )
        assert r.status_code == 201, (content_type, r.text)
        assert r.json()["source_format"] == fmt and r.json()["name"] == f"raw-{fmt}"

    files = [
        ("files", ("a.json", json.dumps(pts.tolist()), "application/json")),
        ("files", ("b.csv", csv_text(pts), "text/csv")),
        ("files", ("c.txt", csv_text(pts).replace(",", "\t"), "text/plain")),
        ("files", ("d.npy", npy_bytes(pts), "application/octet-stream")),
        ("files", ("e.png", png_ellipse("PNG"), "image/png")),
        ("files", ("f.jpg", png_ellipse("JPEG"), "image/jpeg")),
    ]
    for mode in ("contour", "edges", "skeleton"):  # the same names thrice: keep them all
        r = client.post(
            url,
            files=files,
            data={"mode": mode, "target_points": "40"},
            params={"on_conflict": "keep"},
        )
        assert r.status_code == 201, r.text
        items = r.json()["items"]
        assert [i["name"] for i in items] == ["a", "b", "c", "d", "e", "f"]
        assert items[4]["source_format"] == f"png:{mode}"
        assert all(3 <= i["n_points"] <= 50 for i in items)

    batch = {"shapes": [{"name": "b1", "points": pts.tolist()}, {"points": (pts * 2).tolist()}]}
    r = client.post(url, json=batch)
    assert r.status_code == 201 and r.json()["count"] == 2

    listing = client.get(url, params={"limit": 100}).json()
    assert listing["total"] == 1 + len(raw) + 3 * len(files) + 2
    assert all("points" not in item for item in listing["items"])
    first = listing["items"][0]
    detail = client.get(f"{url}/{first['id']}").json()
    np.testing.assert_allclose(np.array(detail["points"]), pts)
    assert detail["bbox"] == {
        "min_x": pytest.approx(pts[:, 0].min()),
        "min_y": pytest.approx(pts[:, 1].min()),
        "max_x": pytest.approx(pts[:, 0].max()),
        "max_y": pytest.approx(pts[:, 1].max()),
    }
    assert client.get(f"/v1/collections/{cid}").json()["n_shapes"] == listing["total"]
    assert client.delete(f"{url}/{first['id']}").status_code == 204
    assert_problem(client.get(f"{url}/{first['id']}"), 404)


def test_deleting_a_collection_deletes_its_shapes(client: httpx.Client) -> None:
    cid = create_collection(client, "doomed")
    url = f"/v1/collections/{cid}/shapes"
    shape = client.post(url, json={"name": "s", "points": circle(10).tolist()}).json()
    assert client.delete(f"/v1/collections/{cid}").status_code == 204
    assert_problem(client.get(f"{url}/{shape['id']}"), 404)
    assert_problem(client.get(url), 404)


def test_batch_is_all_or_nothing(client: httpx.Client) -> None:
    cid = create_collection(client, "atomic")
    url = f"/v1/collections/{cid}/shapes"
    good = csv_text(circle(30))
    files = [
        ("files", ("good1.csv", good, "text/csv")),
        ("files", ("broken.csv", "1,2\n3,nan\n4,5\n", "text/csv")),
        ("files", ("good2.csv", good, "text/csv")),
    ]
    problem = assert_problem(client.post(url, files=files), 422)
    assert "broken.csv" in problem["detail"]
    assert client.get(url).json()["total"] == 0

    batch = {"shapes": [{"name": "ok", "points": circle(10).tolist()}, {"points": [[0, 0]]}]}
    problem = assert_problem(client.post(url, json=batch), 422)
    assert "shapes[1]" in problem["detail"]
    assert client.get(url).json()["total"] == 0


def test_idempotent_posts(client: httpx.Client) -> None:
    headers = {"Idempotency-Key": "coll-1"}
    a = client.post("/v1/collections", json={"name": "idem"}, headers=headers)
    b = client.post("/v1/collections", json={"name": "idem"}, headers=headers)
    assert a.status_code == b.status_code == 201 and a.json()["id"] == b.json()["id"]
    assert_problem(client.post("/v1/collections", json={"name": "other"}, headers=headers), 422)

    url = f"/v1/collections/{a.json()['id']}/shapes"
    body = {"name": "s", "points": circle(20).tolist()}
    s1 = client.post(url, json=body, headers={"Idempotency-Key": "shape-1"})
    s2 = client.post(url, json=body, headers={"Idempotency-Key": "shape-1"})
    assert s1.json()["id"] == s2.json()["id"]
    assert client.get(url).json()["total"] == 1


BAD_SHAPES = [
    pytest.param({"json": {"name": "x", "points": [[0, 0], [1, 1]]}}, 422, id="too-few-points"),
    pytest.param({"json": {"name": "x", "points": [[0, 0, 0]] * 5}}, 422, id="three-columns"),
    pytest.param({"json": {"name": "x", "points": [[0, "a"]] * 5}}, 422, id="string-coord"),
    pytest.param({"json": {"name": "x", "points": "nope"}}, 422, id="points-string"),
    pytest.param({"json": {"name": 5, "points": [[0, 0]] * 5}}, 422, id="name-number"),
    pytest.param({"json": [1, 2, 3]}, 422, id="json-list-of-numbers"),
    pytest.param({"json": {"shapes": []}}, 422, id="empty-batch"),
    pytest.param({"json": {"shapes": "x"}}, 422, id="batch-not-list"),
    pytest.param(
        {
            "content": b'{"points": [[0, 0], [1, NaN], [2, 2]]}',
            "headers": {"content-type": "application/json"},
        },
        422,
        id="nan",
    ),
    pytest.param(
        {
            "content": b"[[0,0],[1e308,1e308],[2,2]]",
            "headers": {"content-type": "application/json"},
        },
        422,
        id="huge-coordinate",
    ),
    pytest.param(
        {"content": b"{not json", "headers": {"content-type": "application/json"}},
        422,
        id="invalid-json",
    ),
    pytest.param({"content": b"", "headers": {"content-type": "text/csv"}}, 422, id="empty-csv"),
    pytest.param(
        {"content": b"a,b\nc,d\n", "headers": {"content-type": "text/csv"}}, 422, id="csv-words"
    ),
    pytest.param(
        {"content": b"\x93NUMPY garbage", "headers": {"content-type": "application/octet-stream"}},
        422,
        id="bad-npy",
    ),
    pytest.param(
        {"content": b"\x89PNG\r\n\x1a\n truncated", "headers": {"content-type": "image/png"}},
        422,
        id="bad-png",
    ),
    pytest.param(
        {
            "content": png_ellipse(),
            "headers": {"content-type": "image/png"},
            "params": {"mode": "outline"},
        },
        422,
        id="bad-mode",
    ),
    pytest.param(
        {
            "content": png_ellipse(),
            "headers": {"content-type": "image/png"},
            "params": {"target_points": 0},
        },
        422,
        id="bad-target-points",
    ),
    pytest.param(
        {"content": b"<x/>", "headers": {"content-type": "application/xml"}}, 415, id="xml"
    ),
    pytest.param({"content": b"1 2\n3 4\n5 6\n"}, 415, id="no-content-type"),
    pytest.param(
        {"files": [("other", ("a.csv", "1,2\n3,4\n5,6\n", "text/csv"))]}, 422, id="no-files-field"
    ),
    pytest.param(
        {"files": [("files", ("a.png", png_ellipse(), "image/png"))], "data": {"mode": "x"}},
        422,
        id="multipart-bad-mode",
    ),
    pytest.param(
        {
            "files": [("files", ("a.csv", "1,2\n3,4\n5,6\n", "text/csv"))],
            "data": {"target_points": "many"},
        },
        422,
        id="multipart-bad-target",
    ),
    pytest.param(
        {
            "content": npy_bytes(np.zeros((30, 2), dtype=object)),
            "headers": {"content-type": "application/octet-stream"},
        },
        422,
        id="pickled-npy",
    ),
]


@pytest.fixture(scope="module")
def bad_collection(service: Service) -> Iterator[int]:
    with service.client() as c:
        yield create_collection(c, "bad-inputs")


@pytest.mark.parametrize(("kwargs", "status"), BAD_SHAPES)
def test_bad_shape_uploads_are_4xx_problems(
    client: httpx.Client, bad_collection: int, kwargs: dict, status: int
) -> None:
    response = client.post(f"/v1/collections/{bad_collection}/shapes", **kwargs)
    problem = assert_problem(response, status)
    assert problem["detail"]
    assert client.get(f"/v1/collections/{bad_collection}/shapes").json()["total"] == 0


@pytest.mark.parametrize(
    ("method", "url", "kwargs", "status"),
    [
        ("GET", "/nowhere", {}, 404),
        ("GET", "/v1/collections/999999", {}, 404),
        ("GET", "/v1/collections/abc", {}, 422),
        ("GET", "/v1/collections?limit=0", {}, 422),
        ("GET", "/v1/collections?limit=100000", {}, 422),
        ("GET", "/v1/collections?offset=-1", {}, 422),
        ("PUT", "/v1/collections", {}, 405),
        ("DELETE", "/v1/jobs", {}, 405),
        ("POST", "/v1/collections", {"json": {}}, 422),
        ("POST", "/v1/collections", {"json": {"name": ""}}, 422),
        ("POST", "/v1/collections", {"json": {"name": "x", "extra": 1}}, 422),
        (
            "POST",
            "/v1/collections",
            {"content": b"[", "headers": {"content-type": "application/json"}},
            422,
        ),
        ("POST", "/v1/collections", {"json": {"name": "x" * 201}}, 422),
        ("GET", "/v1/collections/999999/shapes", {}, 404),
        ("POST", "/v1/collections/999999/shapes", {"json": {"points": TRIANGLE}}, 404),
        ("GET", "/v1/jobs/999999", {}, 404),
        ("GET", "/v1/jobs?status=bogus", {}, 422),
        ("POST", "/v1/jobs/999999/cancel", {}, 404),
        ("GET", "/v1/jobs/999999/result", {}, 404),
        ("GET", "/v1/jobs/999999/result/subjects/1", {}, 404),
        ("POST", "/v1/jobs", {"json": {}}, 422),
        ("POST", "/v1/jobs", {"json": {"collection_id": 999999, "model_shape_id": 1}}, 422),
        (
            "POST",
            "/v1/jobs",
            {"json": {"collection_id": 1, "model_shape_id": 1, "method": "magic"}},
            422,
        ),
        (
            "POST",
            "/v1/jobs",
            {"json": {"collection_id": 1, "model_shape_id": 1, "similarity_threshold": -1}},
            422,
        ),
        (
            "POST",
            "/v1/jobs",
            {"json": {"collection_id": 1, "model_shape_id": 1, "cpd": {"w": 1.5}}},
            422,
        ),
        (
            "POST",
            "/v1/jobs",
            {"json": {"collection_id": 1, "model_shape_id": 1, "cpd": {"beta": 0}}},
            422,
        ),
        (
            "POST",
            "/v1/jobs",
            {"content": b"1e999", "headers": {"content-type": "application/json"}},
            422,
        ),
    ],
)
def test_bad_requests_are_4xx_problems(
    client: httpx.Client, method: str, url: str, kwargs: dict, status: int
) -> None:
    assert_problem(client.request(method, url, **kwargs), status)


def test_body_limit_is_413(service: Service, client: httpx.Client) -> None:
    cid = create_collection(client, "limit")
    url = f"/v1/collections/{cid}/shapes"
    too_big = b"1 2\n" * (4 * 1024 * 1024 // 4 + 10)
    # Declared by Content-Length.
    problem = assert_problem(
        client.post(url, content=too_big, headers={"content-type": "text/plain"}), 413
    )
    assert "limit" in problem["detail"]

    # Streamed without a Content-Length (chunked): counted as it arrives.
    def chunks() -> Iterator[bytes]:
        for start in range(0, len(too_big), 65536):
            yield too_big[start : start + 65536]

    response = client.post(url, content=chunks(), headers={"content-type": "text/plain"})
    assert_problem(response, 413)
    assert client.get(url).json()["total"] == 0


def test_openapi_documents_the_api(client: httpx.Client) -> None:
    schema = client.get("/openapi.json").json()
    paths = schema["paths"]
    for path in (
        "/v1/collections",
        "/v1/collections/{collection_id}",
        "/v1/collections/{collection_id}/shapes",
        "/v1/collections/{collection_id}/shapes/{shape_id}",
        "/v1/jobs",
        "/v1/jobs/{job_id}",
        "/v1/jobs/{job_id}/cancel",
        "/v1/jobs/{job_id}/result",
        "/v1/jobs/{job_id}/result/subjects/{shape_id}",
        "/v1/jobs/{job_id}/result/subjects/{shape_id}/transform",
    ):
        assert path in paths, path
    upload = paths["/v1/collections/{collection_id}/shapes"]["post"]["requestBody"]["content"]
    assert {"application/json", "multipart/form-data", "text/csv", "image/png"} <= set(upload)
    components = schema["components"]["schemas"]
    assert "examples" in components["JobCreate"] and "Problem" in components
    assert "ShapeJSON" in components and "ShapeBatchJSON" in components

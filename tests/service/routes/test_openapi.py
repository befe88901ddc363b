"""``/openapi.json`` walked operation by operation (service/main.py): every operation is
described in Markdown, every id is documented as >= 1 and refused below it, and the status a
malformed body gets is the one the document states, checked by sending one to each operation."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.service.conftest import assert_problem

#: reStructuredText inline markup: a role (:func:`x`, :py:meth:`x`) or a ``literal``.
SPHINX = re.compile(r"``|:[a-z]+(?::[a-z]+)?:`")

#: Bodies that are not JSON: a syntax error, bytes that are not UTF-8, nesting past the
#: parser's depth.
NOT_JSON = [b'{"name": ', b'{"name": "\xff"}', b"[" * 5000]

Operation = tuple[str, str, dict[str, Any]]


@pytest.fixture
def document(client: TestClient) -> dict[str, Any]:
    response = client.get("/openapi.json")
    assert response.status_code == 200
    return dict(response.json())


def operations(document: dict[str, Any]) -> Iterator[Operation]:
    for path, item in document["paths"].items():
        for method, operation in item.items():
            if method in ("get", "post", "put", "patch", "delete"):
                yield method, path, operation


def texts(node: Any, where: str = "") -> Iterator[tuple[str, str]]:
    """Every description and summary in the document, with where it is."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("description", "summary") and isinstance(value, str):
                yield f"{where}/{key}", value
            else:
                yield from texts(value, f"{where}/{key}")
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from texts(value, f"{where}[{i}]")


def integer_schema(schema: dict[str, Any]) -> dict[str, Any]:
    """The integer branch of a parameter's schema (``anyOf`` integer/null when optional)."""
    if "anyOf" in schema:
        (schema,) = [s for s in schema["anyOf"] if s.get("type") == "integer"]
    assert schema.get("type") == "integer", schema
    return schema


def id_parameters(operation: dict[str, Any]) -> list[dict[str, Any]]:
    return [
        p
        for p in operation.get("parameters", [])
        if p["in"] in ("path", "query") and (p["name"] == "id" or p["name"].endswith("_id"))
    ]


def url_of(path: str, **ids: int) -> str:
    """The path with every id 1 unless given."""
    return re.sub(r"\{(\w+)\}", lambda m: str(ids.get(m.group(1), 1)), path)


def test_every_operation_has_a_summary_and_a_description(document: dict[str, Any]) -> None:
    found = list(operations(document))
    assert len(found) >= 25
    undescribed = [
        f"{method.upper()} {path}"
        for method, path, operation in found
        if not operation.get("summary", "").strip()
        or len(operation.get("description", "").strip()) < 20
    ]
    assert undescribed == []


def test_no_sphinx_markup_in_any_description(document: dict[str, Any]) -> None:
    marked = [(where, text[:120]) for where, text in texts(document) if SPHINX.search(text)]
    assert marked == []
    # the models' docstrings were reST: their literals are Markdown code now
    result = document["components"]["schemas"]["ResultDocument"]["description"]
    assert "`shape_id`" in result


def test_ids_are_documented_as_at_least_one(document: dict[str, Any]) -> None:
    checked = 0
    for method, path, operation in operations(document):
        for parameter in id_parameters(operation):
            schema = integer_schema(parameter["schema"])
            assert schema.get("minimum") == 1, (method, path, parameter)
            assert "exclusiveMinimum" not in schema
            checked += 1
    assert checked >= 25
    job = document["components"]["schemas"]["JobCreate"]["properties"]
    assert integer_schema(job["collection_id"])["minimum"] == 1
    assert integer_schema(job["model_shape_id"])["minimum"] == 1  # or null: a grouping


@pytest.mark.parametrize("bad", [0, -1])
def test_ids_below_one_are_refused_with_422(
    client: TestClient, document: dict[str, Any], bad: int
) -> None:
    client.post("/v1/collections", json={"name": "one"})  # id 1 exists
    for method, path, operation in operations(document):
        for parameter in id_parameters(operation):
            name = parameter["name"]
            if parameter["in"] == "path":
                url, params = url_of(path, **{name: bad}), {}
            else:
                url, params = url_of(path), {name: bad}
            body = {"json": {}} if "requestBody" in operation else {}
            response = client.request(method, url, params=params, **body)
            problem = assert_problem(response, 422)
            assert [parameter["in"], name] in [e["loc"] for e in problem["errors"]], (
                method,
                path,
                problem,
            )
            assert "422" in operation["responses"], (method, path)
    for field in ("collection_id", "model_shape_id"):
        job = {"collection_id": 1, "model_shape_id": 1, field: bad}
        problem = assert_problem(client.post("/v1/jobs", json=job), 422)
        assert ["body", field] in [e["loc"] for e in problem["errors"]]


def test_a_malformed_json_body_gets_the_documented_422(
    client: TestClient, document: dict[str, Any]
) -> None:
    client.post("/v1/collections", json={"name": "one"})
    json_operations = [
        (method, path, operation)
        for method, path, operation in operations(document)
        if "application/json" in operation.get("requestBody", {}).get("content", {})
    ]
    assert {path for _, path, _ in json_operations} >= {
        "/v1/collections",
        "/v1/collections/{collection_id}/shapes",
        "/v1/jobs",
        "/v1/jobs/{job_id}/result/subjects/{shape_id}/transform",
        "/v1/jobs/{job_id}/result/subjects/{shape_id}/inverse-transform",
    }
    for method, path, operation in json_operations:
        responses = operation["responses"]
        documented = responses["422"]
        assert "not valid JSON" in documented["description"], (method, path)
        assert "application/problem+json" in documented["content"]
        body_types = operation["requestBody"]["content"]
        assert ("400" in responses) == ("multipart/form-data" in body_types), (method, path)
        for body in NOT_JSON:
            response = client.request(
                method, url_of(path), content=body, headers={"content-type": "application/json"}
            )
            problem = assert_problem(response, 422)
            assert "JSON" in problem["detail"], (method, path, body[:20], problem)
    assert client.get("/v1/collections/1/shapes").json()["total"] == 0  # nothing stored


def test_a_malformed_multipart_body_gets_the_documented_400(
    client: TestClient, document: dict[str, Any]
) -> None:
    client.post("/v1/collections", json={"name": "one"})
    multipart = [
        (method, path, operation)
        for method, path, operation in operations(document)
        if "multipart/form-data" in operation.get("requestBody", {}).get("content", {})
    ]
    assert [path for _, path, _ in multipart] == ["/v1/collections/{collection_id}/shapes"]
    for method, path, operation in multipart:
        assert "multipart" in operation["responses"]["400"]["description"]
        for content_type in ("multipart/form-data", "multipart/form-data; boundary=xx"):
            response = client.request(
                method, url_of(path), content=b"garbage", headers={"content-type": content_type}
            )
            assert_problem(response, 400)

"""Random request bodies never make the server answer 5xx, and every error is a problem."""

from __future__ import annotations

import json

import httpx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.service.conftest import Service, create_collection

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=6)
        | st.dictionaries(
            st.sampled_from(["name", "points", "shapes", "x"]) | st.text(max_size=5),
            children,
            max_size=4,
        )
    ),
    max_leaves=40,
)
point_lists = st.lists(
    st.lists(
        st.floats(allow_nan=True, allow_infinity=True) | st.integers(), min_size=0, max_size=3
    ),
    max_size=12,
)
content_types = st.sampled_from(
    [
        "application/json",
        "text/csv",
        "text/plain",
        "application/octet-stream",
        "image/png",
        "image/jpeg",
        "application/xml",
        "",
    ]
)


@pytest.fixture(scope="module")
def cid(service: Service) -> int:
    with service.client() as client:
        return create_collection(client, "fuzz")


FUZZ = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


def _check(response: httpx.Response) -> None:
    assert response.status_code < 500, response.text
    if response.status_code >= 400:
        assert response.headers["content-type"].startswith("application/problem+json")
        assert response.json()["status"] == response.status_code


@FUZZ
@given(body=json_values)
def test_fuzz_json_shape_bodies(service: Service, cid: int, body: object) -> None:
    with service.client() as client:
        _check(
            client.post(
                f"/v1/collections/{cid}/shapes",
                content=json.dumps(body, allow_nan=True),
                headers={"content-type": "application/json"},
            )
        )


@FUZZ
@given(name=st.text(max_size=5) | st.none(), points=point_lists)
def test_fuzz_points(service: Service, cid: int, name: str | None, points: list) -> None:
    with service.client() as client:
        _check(
            client.post(
                f"/v1/collections/{cid}/shapes",
                content=json.dumps({"name": name, "points": points}, allow_nan=True),
                headers={"content-type": "application/json"},
            )
        )


@FUZZ
@given(
    data=st.binary(max_size=300),
    content_type=content_types,
    mode=st.sampled_from(["contour", "edges", "skeleton", "bogus"]),
)
def test_fuzz_raw_bodies(
    service: Service, cid: int, data: bytes, content_type: str, mode: str
) -> None:
    with service.client() as client:
        headers = {"content-type": content_type} if content_type else {}
        _check(
            client.post(
                f"/v1/collections/{cid}/shapes",
                params={"mode": mode},
                content=data,
                headers=headers,
            )
        )
        _check(client.post("/v1/jobs", content=data, headers={"content-type": "application/json"}))


@FUZZ
@given(body=json_values)
def test_fuzz_job_bodies(service: Service, body: object) -> None:
    with service.client() as client:
        content = json.dumps(body, allow_nan=True)
        headers = {"content-type": "application/json"}
        _check(client.post("/v1/jobs", content=content, headers=headers))
        _check(client.post("/v1/collections", content=content, headers=headers))

"""The service's CPD options (CPDParams) are the library's (CPDOptions): the same defaults,
the same rules, a 422 that says what the library's ValueError says, and an OpenAPI schema
that states the library's ranges. Type errors (a string for a number) stay pydantic's."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from registration import CPDOptions
from service.core.config import Settings
from service.main import create_app
from service.schemas import CPDParams

#: Values that break a rule of the library, one option each (JSON-expressible).
BAD_VALUES: list[tuple[str, Any]] = [
    ("beta", 0),
    ("beta", -1.5),
    ("lmbda", 0.0),
    ("w", -0.1),
    ("w", 1),
    ("w", 1.5),
    ("max_iter", 0),
    ("tol", -1e-3),
    ("dtype", "float16"),
    ("mixture_weights", "even"),
]


def _library_message(name: str, value: Any) -> str:
    # the value as pydantic hands it to the library (1 for a float option becomes 1.0)
    kind = CPDParams.model_fields[name].annotation
    typed = kind(value) if isinstance(kind, type) else value  # str | None: as given
    with pytest.raises(ValueError) as refused:
        CPDOptions.check(name, typed)
    return str(refused.value)


@pytest.fixture(scope="module")
def app_client(tmp_path_factory: pytest.TempPathFactory) -> TestClient:
    path: Path = tmp_path_factory.mktemp("cpdparams") / "db.sqlite"
    return TestClient(create_app(Settings(database_url=f"sqlite:///{path}")))


def test_defaults_are_the_librarys() -> None:
    assert CPDParams().model_dump() == asdict(CPDOptions())


@pytest.mark.parametrize(("name", "value"), BAD_VALUES)
def test_a_bad_value_is_refused_with_the_librarys_message(name: str, value: Any) -> None:
    message = _library_message(name, value)
    with pytest.raises(ValidationError) as refused:
        CPDParams.model_validate({name: value})
    (error,) = refused.value.errors()
    assert error["loc"] == (name,)
    assert error["msg"] == f"Value error, {message}"


@pytest.mark.parametrize(("name", "value"), BAD_VALUES)
def test_a_bad_value_is_a_422_problem_with_the_librarys_message(
    app_client: TestClient, name: str, value: Any
) -> None:
    message = _library_message(name, value)
    response = app_client.post(
        "/v1/jobs", json={"collection_id": 1, "model_shape_id": 1, "cpd": {name: value}}
    )
    assert response.status_code == 422
    assert response.headers["content-type"].startswith("application/problem+json")
    body = response.json()
    assert body["detail"] == f"body.cpd.{name}: Value error, {message}"
    assert body["errors"][0]["loc"] == ["body", "cpd", name]


def test_values_the_library_allows_are_accepted() -> None:
    params = CPDParams(tol=0, w=0, max_iter=1, dtype="float64")
    assert CPDOptions(**params.model_dump()).tol == 0


def test_the_service_adds_only_upper_limits_of_its_own() -> None:
    for name, value in (("beta", 1e4), ("lmbda", 1e7), ("max_iter", 10_001), ("tol", 2.0)):
        CPDOptions.check(name, value)  # the library allows it
        with pytest.raises(ValidationError, match="less than or equal"):
            CPDParams.model_validate({name: value})


def test_the_schema_states_the_librarys_rules(app_client: TestClient) -> None:
    schema = app_client.get("/openapi.json").json()["components"]["schemas"]["CPDParams"]
    props = schema["properties"]
    assert props["beta"]["exclusiveMinimum"] == 0 and "minimum" not in props["beta"]
    assert props["lmbda"]["exclusiveMinimum"] == 0
    assert props["w"]["minimum"] == 0 and props["w"]["exclusiveMaximum"] == 1
    assert props["max_iter"]["minimum"] == 1 and props["max_iter"]["maximum"] == 10_000
    assert props["tol"]["minimum"] == 0 and props["tol"]["maximum"] == 1
    assert props["dtype"]["enum"] == ["float64", "float32"]
    (string,) = [b for b in props["mixture_weights"]["anyOf"] if b.get("type") == "string"]
    assert string["enum"] == ["uniform", "sampling"]

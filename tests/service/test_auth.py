"""The optional API key: every request needs it, except /healthz and the API docs."""

from __future__ import annotations

from collections.abc import Callable

from tests.service.conftest import Service, assert_problem


def test_api_key_required_when_set(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0, env={"REGTREE_API_KEY": "s3cret"}).start()
    with svc.client() as client:
        for method, url in [
            ("GET", "/v1/collections"),
            ("POST", "/v1/collections"),
            ("GET", "/v1/jobs/1"),
            ("GET", "/nowhere"),
        ]:
            problem = assert_problem(client.request(method, url), 401)
            assert "X-API-Key" in problem["detail"]
        assert_problem(client.get("/v1/collections", headers={"X-API-Key": "wrong"}), 401)
        assert_problem(
            client.get("/v1/collections", headers={"Authorization": "Bearer wrong"}), 401
        )
        assert client.get("/v1/collections", headers={"X-API-Key": "s3cret"}).status_code == 200
        ok = client.post(
            "/v1/collections",
            json={"name": "k"},
            headers={"Authorization": "Bearer s3cret"},
        )
        assert ok.status_code == 201
        assert client.get("/healthz").status_code == 200
        schema = client.get("/openapi.json").json()
        assert schema["paths"]["/v1/collections"]["get"]["security"]
        assert "ApiKeyHeader" in schema["components"]["securitySchemes"]


def test_no_api_key_by_default(service: Service) -> None:
    with service.client() as client:
        assert client.get("/v1/collections").status_code == 200

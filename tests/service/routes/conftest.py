"""In-process route tests: ``TestClient(create_app(...))`` on a fresh SQLite file.

One test module per module of ``service/api/routes/``: fast checks of each route's status
codes and problem bodies, beside the end-to-end suites in ``tests/service`` that run the
real ``regtree serve``. A job that needs a result is run in this process by one
:class:`service.worker.Worker` step with the serial executor.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service import migrate
from service.core.config import Settings
from service.db import Database
from service.main import create_app
from service.worker import Worker
from tests.service.conftest import create_collection, family, submit_job, upload_family

KEY = "routes-s3cret"


def make_settings(folder: Path, **overrides: Any) -> Settings:
    """Settings for an app on its own SQLite file, migrated, with a serial executor."""
    settings = Settings(
        _env_file=None,  # type: ignore[call-arg]
        database_url=f"sqlite:///{folder / 'regtree.sqlite'}",
        executor="serial",
        log_level="WARNING",
        **overrides,
    )
    migrate.upgrade(settings)
    return settings


@pytest.fixture
def make_client(tmp_path: Path) -> Iterator[Callable[..., TestClient]]:
    """``make_client(**settings)``: a client of a new app on a new database."""
    clients: list[TestClient] = []

    def make(**overrides: Any) -> TestClient:
        folder = tmp_path / f"app{len(clients)}"
        folder.mkdir()
        client = TestClient(create_app(make_settings(folder, **overrides)))
        client.__enter__()
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.__exit__(None, None, None)


@pytest.fixture
def client(make_client: Callable[..., TestClient]) -> TestClient:
    return make_client()


class Finished:
    """A collection of six shapes with one succeeded job, shared by a test module."""

    def __init__(self, client: TestClient, settings: Settings) -> None:
        self.client = client
        self.collection_id = create_collection(client, "family")
        self.shape_ids = upload_family(
            client,
            self.collection_id,
            family(n_chains=2, chain_length=3, n_points=40),
        )
        self.job_id = int(
            submit_job(client, self.collection_id, self.shape_ids[0])["id"]
        )
        db = Database(settings.database_url)
        try:
            Worker(settings, db).run_once()
        finally:
            db.dispose()
        job = client.get(f"/v1/jobs/{self.job_id}").json()
        assert job["status"] == "succeeded", job
        self.result: dict[str, Any] = client.get(f"/v1/jobs/{self.job_id}/result").json()


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Finished]:
    settings = make_settings(tmp_path_factory.mktemp("finished"))
    with TestClient(create_app(settings)) as client:
        yield Finished(client, settings)

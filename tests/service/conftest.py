"""Fixtures that run the real service: ``regtree serve`` / ``regtree worker`` subprocesses.

Each server gets a free port and its own SQLite file (or the ``database_url`` it is given,
e.g. a scratch PostgreSQL database); settings go through REGTREE_*
environment variables exactly as an operator would set them. Leases are short so that
crash recovery is testable in seconds.
"""

from __future__ import annotations

import io
import os
import random
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]

FAST_ENV = {
    "REGTREE_WORKER_LEASE_SECONDS": "2",
    "REGTREE_WORKER_HEARTBEAT_SECONDS": "0.3",
    "REGTREE_WORKER_POLL_SECONDS": "0.2",
    "REGTREE_RETRY_BACKOFF_SECONDS": "0.2",
    "REGTREE_CALLBACK_POLL_SECONDS": "0.2",
    "REGTREE_PROGRESS_MIN_INTERVAL_SECONDS": "0.1",
    "REGTREE_EXECUTOR": "serial",
    "REGTREE_LOG_LEVEL": "WARNING",
    "REGTREE_MAX_BODY_BYTES": str(4 * 1024 * 1024),
}


_HANDED_OUT: set[int] = set()


#: Ports the servers of the suite listen on: below Linux's ephemeral range (32768-60999),
#: where no client connection of the suite is given one, split evenly between the
#: pytest-xdist workers so that two workers never hand out the same port.
_PORTS = range(20000, 32000)


def _worker_ports() -> range:
    """This pytest-xdist worker's share of :data:`_PORTS` (all of it without xdist)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ...
    count = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1))
    number = int(worker[2:]) % count if worker.startswith("gw") and worker[2:].isdigit() else 0
    span = len(_PORTS) // count
    return range(_PORTS.start + number * span, _PORTS.start + (number + 1) * span)


def free_port() -> int:
    """A port nothing listens on, and not one given before in this session (a server
    launched with it may not be listening yet), from this worker's share of
    :data:`_PORTS`."""
    ports = _worker_ports()
    rng = random.Random()
    while True:
        port = rng.choice(ports)
        if port in _HANDED_OUT:
            continue
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:  # taken
                continue
        _HANDED_OUT.add(port)
        return port


def _stop(process: subprocess.Popen[bytes], timeout: float = 20.0) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)


class Service:
    """A ``regtree serve`` subprocess plus any ``regtree worker`` subprocesses."""

    def __init__(
        self,
        workdir: Path,
        *,
        workers: int = 1,
        env: dict[str, str] | None = None,
        database_url: str | None = None,
    ):
        self.workdir = workdir
        self.db_path = workdir / "regtree.sqlite"
        self.database_url = database_url or f"sqlite:///{self.db_path}"
        self.env = {
            **os.environ,
            **FAST_ENV,
            "REGTREE_DATABASE_URL": self.database_url,
            "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
            **(env or {}),
        }
        self.workers = workers
        self.server: subprocess.Popen[bytes] | None = None
        self.worker_processes: list[subprocess.Popen[bytes]] = []
        self.port = 0
        self._logs: list[Path] = []

    def _spawn(self, *args: str) -> subprocess.Popen[bytes]:
        log = self.workdir / f"log-{len(self._logs)}-{args[0]}.jsonl"
        self._logs.append(log)
        return subprocess.Popen(
            [sys.executable, "-m", "service.cli", *args],
            cwd=self.workdir,
            env=self.env,
            stdout=log.open("wb"),
            stderr=subprocess.STDOUT,
        )

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = 60.0) -> Service:
        return self.launch().wait_healthy(timeout)

    def launch(self) -> Service:
        """Start ``regtree serve`` without waiting for it: several servers a test needs side
        by side then start together (each spends seconds on its imports)."""
        self.port = free_port()
        self.server = self._spawn(
            "serve", "--host", "127.0.0.1", "--port", str(self.port), "--workers", str(self.workers)
        )
        return self

    def wait_healthy(self, timeout: float = 60.0) -> Service:
        assert self.server is not None, "launch() first"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.server.poll() is not None:
                raise RuntimeError(f"server exited with {self.server.returncode}:\n{self.logs()}")
            try:
                if httpx.get(f"{self.base_url}/healthz", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"server did not become healthy:\n{self.logs()}")

    def stop(self) -> None:
        if self.server is not None:
            _stop(self.server)
            self.server = None
        for process in self.worker_processes:
            _stop(process)
        self.worker_processes.clear()

    def start_worker(self) -> subprocess.Popen[bytes]:
        process = self._spawn("worker")
        self.worker_processes.append(process)
        return process

    def client(self, **kwargs: Any) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=30, **kwargs)

    def unhandled_errors(self) -> list[str]:
        """Log lines of requests that ended in an unexpected exception (a 500)."""
        return [
            line
            for p in self._logs
            if p.exists()
            for line in p.read_text(errors="replace").splitlines()
            if '"unhandled error"' in line
        ]

    def logs(self) -> str:
        return "\n".join(p.read_text(errors="replace")[-5000:] for p in self._logs if p.exists())


#: A PostgreSQL database whose role may create databases (``.ci/postgres.sh`` prints one);
#: the PostgreSQL tests are skipped without it.
POSTGRES_URL = os.environ.get("REGTREE_TEST_POSTGRES_URL", "")
POSTGRES_SKIP_REASON = (
    "REGTREE_TEST_POSTGRES_URL is not set (run `bash .ci/postgres.sh` and export the URL it "
    "prints to test the service on PostgreSQL)"
)


@contextmanager
def postgres_scratch_database(base_url: str = POSTGRES_URL) -> Iterator[str]:
    """The URL of a fresh, empty database on the server of ``base_url``, dropped afterwards."""
    pytest.importorskip("psycopg", reason="the psycopg driver is not installed")
    from sqlalchemy import create_engine, make_url, text

    base = make_url(base_url)
    assert base.get_backend_name() == "postgresql", f"not a PostgreSQL URL: {base_url}"
    name = f"regtree_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(base, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as connection:
            connection.execute(text(f'CREATE DATABASE "{name}"'))
        try:
            yield base.set(database=name).render_as_string(hide_password=False)
        finally:
            _drop_database(admin, name)
    finally:
        admin.dispose()


def _drop_database(admin: Any, name: str) -> None:
    """DROP DATABASE ... WITH (FORCE), again for a few seconds while it is refused for want
    of privilege: FORCE may not end an autovacuum worker (a superuser's process) that
    happens to be on the fresh database; it finishes in moments."""
    from sqlalchemy import text
    from sqlalchemy.exc import DBAPIError

    for attempt in range(40):
        try:
            with admin.connect() as connection:
                connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
            return
        except DBAPIError as exc:
            if "pg_signal_backend" not in str(exc) or attempt == 39:
                raise
            time.sleep(0.25)


@pytest.fixture
def make_service(tmp_path: Path) -> Iterator[Callable[..., Service]]:
    services: list[Service] = []

    def make(**kwargs: Any) -> Service:
        workdir = tmp_path / f"svc{len(services)}"
        workdir.mkdir()
        service = Service(workdir, **kwargs)
        services.append(service)
        return service

    yield make
    for service in services:
        service.stop()
    for service in services:
        assert not service.unhandled_errors(), service.unhandled_errors()


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """A server with one embedded worker, shared by a test module."""
    svc = Service(tmp_path_factory.mktemp("service"), workers=1).start()
    yield svc
    svc.stop()
    assert not svc.unhandled_errors(), svc.unhandled_errors()


@pytest.fixture
def client(service: Service) -> Iterator[httpx.Client]:
    with service.client() as c:
        yield c


# --- data --------------------------------------------------------------------------------


def family(
    n_chains: int = 2, chain_length: int = 3, n_points: int = 60, seed: int = 1
) -> list[tuple[str, np.ndarray]]:
    from registration.synthetic import chained_family

    fam = chained_family(n_chains=n_chains, chain_length=chain_length, n_points=n_points, seed=seed)
    return list(zip(fam.names, fam.shapes, strict=True))


def circle(n: int = 60, r: float = 1.0) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[r * np.cos(t), 0.7 * r * np.sin(t)]


def npy_bytes(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points)
    return buffer.getvalue()


def assert_problem(response: httpx.Response, status: int) -> dict[str, Any]:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json"), response.text
    body: dict[str, Any] = response.json()
    assert body["status"] == status
    for key in ("type", "title", "detail", "instance"):
        assert key in body
    return body


def create_collection(client: httpx.Client, name: str = "c") -> int:
    response = client.post("/v1/collections", json={"name": name})
    assert response.status_code == 201, response.text
    return int(response.json()["id"])


def upload_family(
    client: httpx.Client, collection_id: int, shapes: list[tuple[str, np.ndarray]]
) -> list[int]:
    body = {"shapes": [{"name": n, "points": p.tolist()} for n, p in shapes]}
    response = client.post(f"/v1/collections/{collection_id}/shapes", json=body)
    assert response.status_code == 201, response.text
    return [int(item["id"]) for item in response.json()["items"]]


def submit_job(
    client: httpx.Client, collection_id: int, model_id: int, **options: Any
) -> dict[str, Any]:
    response = client.post(
        "/v1/jobs", json={"collection_id": collection_id, "model_shape_id": model_id, **options}
    )
    assert response.status_code == 202, response.text
    assert response.headers["location"] == f"/v1/jobs/{response.json()['id']}"
    job: dict[str, Any] = response.json()
    return job


def second_job_queued_seconds(client: httpx.Client, first_timeout: float = 60.0) -> float:
    """Run a small job, then, once the worker is idle again, a second one; how long the
    second waited between its creation and its start (the tests of waking idle workers:
    with a long poll it would wait most of it)."""
    cid = create_collection(client, "wake")
    ids = upload_family(client, cid, family(n_chains=1, chain_length=3, n_points=40))
    first = wait_job(client, submit_job(client, cid, ids[0])["id"], timeout=first_timeout)
    assert first["status"] == "succeeded", first
    time.sleep(0.5)  # the worker is idle again, in its long wait
    second = wait_job(client, submit_job(client, cid, ids[0])["id"], timeout=60)
    assert second["status"] == "succeeded", second
    started = datetime.fromisoformat(str(second["started_at"]))
    created = datetime.fromisoformat(str(second["created_at"]))
    return (started - created).total_seconds()


def wait_job(
    client: httpx.Client,
    job_id: int,
    *,
    until: Callable[[dict[str, Any]], bool] | None = None,
    timeout: float = 90.0,
) -> dict[str, Any]:
    """Poll a job until ``until(job)`` (default: a final status)."""
    until = until or (lambda j: j["status"] in ("succeeded", "failed", "cancelled"))
    deadline = time.monotonic() + timeout
    while True:
        job: dict[str, Any] = client.get(f"/v1/jobs/{job_id}").json()
        if until(job):
            return job
        if time.monotonic() > deadline:
            raise AssertionError(f"job {job_id} did not get there in {timeout}s: {job}")
        time.sleep(0.1)


def insert_legacy_shape(service: Service, collection_id: int, name: str, points: Any) -> int:
    """Store a shape straight in the service's database, past the upload checks: a shape
    stored before they existed (for example one whose points all coincide). Its id."""
    from service.db import Database
    from service.models import Shape, points_to_npy

    pts = np.asarray(points, dtype=np.float64)
    db = Database(service.database_url)
    try:
        with db.write() as session:
            row = Shape(
                collection_id=collection_id,
                name=name,
                source_format="json",
                n_points=len(pts),
                min_x=float(pts[:, 0].min()),
                min_y=float(pts[:, 1].min()),
                max_x=float(pts[:, 0].max()),
                max_y=float(pts[:, 1].max()),
                points_npy=points_to_npy(pts),
            )
            session.add(row)
            session.flush()
            return int(row.id)
    finally:
        db.dispose()

"""Idle workers wake when a job is queued (service.jobs.wake), not at their poll (on
PostgreSQL: tests/service/test_postgres.py)."""

from __future__ import annotations

import multiprocessing
import threading
import time
from collections.abc import Callable

import pytest

from service.jobs import wake
from tests.service.conftest import Service, second_job_queued_seconds


def test_a_queued_job_starts_at_once_though_the_poll_is_long(
    make_service: Callable[..., Service],
) -> None:
    # with a 30 s poll the worker, idle after the first job, would leave the second
    # queued for 15-30 s
    service = make_service(workers=1, env={"REGTREE_WORKER_POLL_SECONDS": "30"}).start()
    with service.client() as client:
        assert second_job_queued_seconds(client) < 5.0


def test_idle_returns_when_woken_and_clears_the_event() -> None:
    event = multiprocessing.get_context("spawn").Event()
    shutdown = threading.Event()
    threading.Timer(0.2, event.set).start()
    t = time.monotonic()
    wake.idle(wake.EventWaker(event), shutdown, 30.0)
    assert time.monotonic() - t < 5.0
    assert not event.is_set()  # the next job sets it again


def test_idle_returns_on_shutdown_and_at_its_time() -> None:
    event = multiprocessing.get_context("spawn").Event()
    shutdown = threading.Event()
    t = time.monotonic()
    wake.idle(wake.EventWaker(event), shutdown, 0.3)  # nothing queued: the poll's own time
    assert 0.25 < time.monotonic() - t < 5.0
    threading.Timer(0.2, shutdown.set).start()
    t = time.monotonic()
    wake.idle(wake.EventWaker(event), shutdown, 30.0)
    assert time.monotonic() - t < 5.0
    shutdown.clear()
    threading.Timer(0.2, shutdown.set).start()
    t = time.monotonic()
    wake.idle(None, shutdown, 30.0)  # a worker without the event: its shutdown alone
    assert time.monotonic() - t < 5.0


def test_notify_sets_the_installed_event_only() -> None:
    event = multiprocessing.get_context("spawn").Event()
    wake.install(None)
    wake.notify()  # no embedded workers: nothing to wake
    wake.install(event)
    try:
        wake.notify()
        assert event.is_set()
    finally:
        wake.install(None)


def test_a_listener_that_cannot_connect_sleeps_its_time_and_wakes_nobody(
        monkeypatch: pytest.MonkeyPatch) -> None:
    psycopg = pytest.importorskip("psycopg", reason="the psycopg driver is not installed")
    attempts: list[str] = []
    real_connect = psycopg.connect

    def connect(conninfo: str, **kwargs: object) -> object:
        attempts.append(conninfo)
        return real_connect(conninfo, **kwargs)

    monkeypatch.setattr(psycopg, "connect", connect)
    listener = wake.Listener("postgresql+psycopg://nobody:x@127.0.0.1:1/none")
    t = time.monotonic()
    assert listener.wait(0.2) is False  # refused: polling only, no busy loop
    assert 0.15 < time.monotonic() - t < 10.0
    t = time.monotonic()
    assert listener.wait(0.2) is False  # no new attempt before its retry time
    assert 0.15 < time.monotonic() - t < 10.0 and listener._connection is None
    assert len(attempts) == 1 and attempts[0].startswith("postgresql://")
    listener.close()

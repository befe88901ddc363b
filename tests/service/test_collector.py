"""The service's processes collect garbage less often (service/core/collector.py): a full
result document is millions of containers, walked by the collector every 700 allocations
with CPython's default."""

from __future__ import annotations

import gc
import math
import os
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

import service.worker
from service.core.collector import SERVICE_GC_THRESHOLD, tune_collector
from service.core.config import Settings


@pytest.fixture
def thresholds() -> Iterator[None]:
    saved = gc.get_threshold()
    yield
    gc.set_threshold(*saved)


@pytest.mark.usefixtures("thresholds")
def test_the_first_threshold_is_raised_and_the_others_kept() -> None:
    gc.set_threshold(700, 10, 10)
    tune_collector()
    assert gc.get_threshold() == (SERVICE_GC_THRESHOLD, 10, 10)
    gc.set_threshold(5 * SERVICE_GC_THRESHOLD, 3, 4)  # a higher one set by the deployment
    tune_collector()
    assert gc.get_threshold() == (5 * SERVICE_GC_THRESHOLD, 3, 4)


@pytest.mark.usefixtures("thresholds")
def test_a_worker_process_runs_its_jobs_with_the_raised_threshold(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Any) -> None:
    seen: list[tuple[int, int, int]] = []

    class Recorder:
        def __init__(self, settings: Settings, parent_pid: int | None = None,
                     wake_event: Any | None = None) -> None:
            self.db = self

        def install_signal_handlers(self) -> None:
            pass

        def run(self) -> None:
            seen.append(gc.get_threshold())

        def dispose(self) -> None:
            pass

    monkeypatch.setattr(service.worker, "Worker", Recorder)
    monkeypatch.setattr(service.worker, "configure_logging", lambda *args: None)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        # the entry point sets them for its process: undone after this test
        monkeypatch.setenv(var, os.environ.get(var, "1"))
    gc.set_threshold(700, 10, 10)
    service.worker.run_worker_process(
        Settings(database_url=f"sqlite:///{tmp_path / 'db.sqlite'}"))
    assert seen == [(SERVICE_GC_THRESHOLD, 10, 10)]


def test_the_client_parses_with_the_collector_paused_and_left_as_it_was(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A full result is millions of containers: the client parses it with the collector
    off (no collection while parsing, even with a threshold of 1), by orjson when it is
    installed, and by the standard library for what orjson refuses (a NaN written by an
    old server); the collector is left as it was."""
    import orjson

    import service.client._http as http

    parsing = [False]
    collections: list[str] = []

    def flagged(parse: Any) -> Any:
        def run(*args: Any, **kwargs: Any) -> Any:
            parsing[0] = True
            try:
                return parse(*args, **kwargs)
            finally:
                parsing[0] = False
        return run

    class FlaggedOrjson:
        loads = staticmethod(flagged(orjson.loads))
        JSONDecodeError = orjson.JSONDecodeError

    monkeypatch.setattr(http, "_orjson", FlaggedOrjson)
    monkeypatch.setattr(httpx.Response, "json", flagged(httpx.Response.json))

    def seen(phase: str, info: dict[str, int]) -> None:
        if phase == "start" and parsing[0]:
            collections.append("collected while parsing")

    saved = gc.get_threshold()
    was = gc.isenabled()
    body = {"subjects": [{"warped": [[0.5 * k, 1.0]] * 200} for k in range(50)]}
    gc.callbacks.append(seen)
    try:
        gc.set_threshold(1, 1, 1)
        gc.enable()
        got = http._json(httpx.Response(200, json=body))
        assert gc.isenabled()
        nan = http._json(httpx.Response(200, content=b'{"error": NaN}'))
        gc.disable()
        assert http._json(httpx.Response(200, content=b"[1, 2]")) == [1, 2]
        assert not gc.isenabled()
    finally:
        gc.callbacks.remove(seen)
        gc.set_threshold(*saved)
        (gc.enable if was else gc.disable)()
    assert got == body
    assert math.isnan(nan["error"])
    assert collections == []

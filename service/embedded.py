"""One machine, one command: the API server plus worker processes (``regtree serve``)."""

from __future__ import annotations

import gc
import logging
import multiprocessing
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from multiprocessing.process import BaseProcess
from typing import TextIO

import uvicorn

from service import migrate
from service.core.collector import tune_collector
from service.core.config import Settings
from service.jobs import wake
from service.main import create_app
from service.worker import run_worker_process

logger = logging.getLogger("regtree.serve")


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


def start_workers(settings: Settings, count: int) -> list[BaseProcess]:
    """Start ``count`` worker processes (spawned, so they share no state with the server)
    and make the jobs this process queues wake them (:mod:`service.jobs.wake`)."""
    context = multiprocessing.get_context("spawn")
    event = context.Event()
    wake.install(event)
    processes: list[BaseProcess] = []
    for i in range(count):
        process = context.Process(
            target=run_worker_process,
            args=(settings, os.getpid(), event),
            name=f"regtree-worker-{i}",
            daemon=False,  # a worker may start its own process pool
        )
        process.start()
        processes.append(process)
    logger.info("workers started", extra={"pids": [p.pid for p in processes]})
    return processes


def stop_workers(processes: list[BaseProcess], *, timeout: float = 15.0) -> None:
    """SIGTERM (jobs in progress go back to the queue), then SIGKILL after ``timeout``."""
    for process in processes:
        if process.is_alive() and process.pid is not None:
            os.kill(process.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            logger.warning("worker did not stop; killing", extra={"pid": process.pid})
            process.kill()
            process.join(5)


class _Server(uvicorn.Server):
    """uvicorn's server, calling ``on_started`` once it listens."""

    def __init__(self, config: uvicorn.Config, on_started: Callable[[], None] | None) -> None:
        super().__init__(config)
        self.on_started = on_started

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await super().startup(sockets=sockets)
        if self.started and self.on_started is not None:
            self.on_started()


def public_url(host: str, port: int) -> str:
    """The address to open for a server listening on ``host`` (any-address: this machine)."""
    if host in ("", "0.0.0.0", "::", "[::]"):
        host = "127.0.0.1"
    elif ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"http://{host}:{port}"


def announce(settings: Settings, host: str, port: int, out: TextIO | None = None) -> None:
    """Print where the service is: the results page, the API docs and the database."""
    url = public_url(host, port)
    print(
        f"regtree is serving at {url}\n"
        f"  results page  {url}/ui\n"
        f"  API docs      {url}/docs\n"
        f"  database      {settings.database_url}\n"
        "Stop it with Ctrl-C.",
        file=out if out is not None else sys.stdout,
        flush=True,
    )


def make_server(
    settings: Settings, host: str, port: int, *, on_started: Callable[[], None] | None = None
) -> uvicorn.Server:
    config = uvicorn.Config(
        create_app(settings),
        host=host,
        port=port,
        log_config=None,
        access_log=False,
        proxy_headers=True,
        timeout_graceful_shutdown=10,
    )
    return _Server(config, on_started)


@contextmanager
def _sigterm_returns() -> Iterator[None]:
    """Let a SIGTERM that stops uvicorn return from ``Server.run`` instead of ending the
    process.

    uvicorn handles SIGTERM itself and, once shut down, raises it again for the handler that
    was in place before; the default one ends the process on the spot, so the workers were
    never told to stop (they noticed their parent was gone a second later). With this
    handler in place instead, :func:`serve` goes on and stops them (``docker stop``).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, lambda _signum, _frame: None)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def serve(settings: Settings, *, host: str, port: int, workers: int, migrate_db: bool) -> None:
    """Apply migrations, start workers, run the API in this process until a signal; then
    stop the workers (their running jobs go back to the queue)."""
    if migrate_db:
        migrate.upgrade(settings)
    tune_collector()  # a full result read is millions of containers
    processes = start_workers(settings, workers)
    try:
        with _sigterm_returns():
            server = make_server(
                settings, host, port, on_started=lambda: announce(settings, host, port)
            )
            # The imports and the app live as long as the process: out of the collector's
            # way, the exit's collections no longer walk them (about a second per stop).
            gc.freeze()
            server.run()
    finally:
        stop_workers(processes)
    logger.info("stopped")


class BackgroundStack:
    """The same server and workers as :func:`serve`, with the server in a thread (demo)."""

    def __init__(self, settings: Settings, *, workers: int, host: str = "127.0.0.1") -> None:
        self.settings = settings
        self.host = host
        self.port = free_port(host)
        self.workers = workers
        self.server = make_server(settings, host, self.port)
        self.processes: list[BaseProcess] = []
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    @property
    def base_url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def __enter__(self) -> BackgroundStack:
        migrate.upgrade(self.settings)
        tune_collector()
        self.processes = start_workers(self.settings, self.workers)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("the embedded API server did not start")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(15)
        stop_workers(self.processes)

"""The worker loop: claim a job, run it, repeat.

Run it with ``regtree worker`` (any number, on any machine that reaches the database), or let
``regtree serve`` start embedded ones. SIGTERM or SIGINT stops the loop; a job in progress is
given back to the queue at its next progress report (its attempt is not counted). A worker
killed outright (SIGKILL, power loss) stops heartbeating; once its lease expires another
worker claims the job again after a backoff, up to ``max_attempts`` times.

Each worker process also delivers job callbacks, in a thread of its own
(:class:`service.jobs.callbacks.Deliverer`), so that a slow receiver never keeps the loop
from claiming the next job.
"""

from __future__ import annotations

import logging
import os
import random
import signal
import socket
import threading
import uuid
from types import FrameType
from typing import Any

from registration import compiled_kernel, compiled_simd, start_fork_server
from service.core.collector import tune_collector
from service.core.config import Settings
from service.core.logging import configure_logging
from service.db import Database, is_postgresql_url
from service.jobs import wake
from service.jobs.callbacks import Deliverer
from service.jobs.queue import JobQueue, Outcome
from service.jobs.runner import run_claimed

logger = logging.getLogger("regtree.worker")


def make_worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


class Worker:
    """Claims and runs jobs until :attr:`shutdown` is set."""

    def __init__(
        self,
        settings: Settings,
        db: Database | None = None,
        *,
        worker_id: str | None = None,
        parent_pid: int | None = None,
        wake_event: Any | None = None,
    ) -> None:
        self.settings = settings
        self.db = db or Database(
            settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms
        )
        self.worker_id = worker_id or make_worker_id()
        self.queue = JobQueue.from_settings(self.db, settings)
        self.parent_pid = parent_pid
        # what wakes this worker when a job is queued (service.jobs.wake): PostgreSQL's
        # notifications, else the event an embedded worker shares with the API's process;
        # None: the poll alone
        self.waker: wake.Listener | wake.EventWaker | None = (
            wake.Listener(settings.database_url) if is_postgresql_url(settings.database_url)
            else wake.EventWaker(wake_event) if wake_event is not None else None)
        self.shutdown = threading.Event()

    def _parent_gone(self) -> bool:
        return self.parent_pid is not None and os.getppid() != self.parent_pid

    def _watch_parent(self) -> None:
        # An embedded worker must not outlive `regtree serve`, even if that was SIGKILLed.
        while not self.shutdown.wait(1.0):
            if self._parent_gone():
                logger.warning("parent process gone; stopping", extra={"worker": self.worker_id})
                self.shutdown.set()

    def run_once(self) -> Outcome | None:
        """Claim and run one job; its outcome, or None if no job was due."""
        claim = self.queue.claim(self.worker_id)
        if claim is None:
            return None
        return run_claimed(self.queue, self.settings, claim, self.shutdown)

    def _start_deliveries(self) -> threading.Thread:
        deliverer = Deliverer(self.db, self.settings, self.worker_id)
        thread = threading.Thread(
            target=deliverer.run, args=(self.shutdown,), name="callbacks", daemon=True
        )
        thread.start()
        return thread

    def _deliver_due(self) -> None:
        deliverer = Deliverer(self.db, self.settings, self.worker_id)
        try:
            while deliverer.deliver_once() is not None:
                pass
        finally:
            deliverer.close()

    def run(self, *, burst: bool = False) -> None:
        """Loop until shut down; with ``burst``, stop as soon as no job is due (after
        trying the callbacks that are due then, once)."""
        compiled = compiled_kernel()
        logger.info("worker started", extra={"worker": self.worker_id,
                                             "compiled_kernel": compiled,
                                             "simd": compiled_simd()})
        if not compiled:
            logger.warning(
                "CPD's truncated E-step runs numpy's passes: registration._cpd._ckernel is "
                "not built (install with a C compiler present) or REGTREE_NO_CKERNEL=1; "
                "registrations of thousands of points take up to 1.4x longer",
                extra={"worker": self.worker_id})
        if self.settings.executor == "process":
            # a job's pool starts beside threads, from the fork server: started now, the
            # first job does not wait for it to import the library (about 0.75 s)
            start_fork_server()
        if self.parent_pid is not None:
            threading.Thread(target=self._watch_parent, daemon=True).start()
        deliveries = None if burst else self._start_deliveries()
        poll = self.settings.worker_poll_seconds
        while not self.shutdown.is_set():
            try:
                outcome = self.run_once()
            except Exception:
                logger.exception("worker loop error", extra={"worker": self.worker_id})
                outcome = None
            if outcome is None:
                if burst:
                    self._deliver_due()
                    break
                # Jitter so that many idle workers do not poll in lock-step.
                wake.idle(self.waker, self.shutdown, poll * random.uniform(0.5, 1.0))
        if self.waker is not None:
            self.waker.close()
        if deliveries is not None:
            self.shutdown.set()
            deliveries.join(timeout=self.settings.callback_timeout_seconds + 5)
        logger.info("worker stopped", extra={"worker": self.worker_id})

    def install_signal_handlers(self) -> None:
        def handle(signum: int, _frame: FrameType | None) -> None:
            logger.info("signal received; finishing", extra={"signal": signum})
            self.shutdown.set()

        signal.signal(signal.SIGTERM, handle)
        signal.signal(signal.SIGINT, handle)


def run_worker_process(settings: Settings, parent_pid: int | None = None,
                       wake_event: Any | None = None) -> None:
    """Entry point of a worker process (``regtree worker`` and the embedded workers, which
    get the event the API's process sets when it queues a job: `service.jobs.wake`)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    configure_logging(settings.log_level, settings.log_style)
    tune_collector()  # a job's result document is millions of containers
    worker = Worker(settings, parent_pid=parent_pid, wake_event=wake_event)
    worker.install_signal_handlers()
    try:
        worker.run()
    finally:
        worker.db.dispose()

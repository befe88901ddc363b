"""Waking idle workers when a job is queued, instead of leaving it to their poll.

A worker looks for due jobs every ``worker_poll_seconds`` (1 s by default, with jitter), so
a job queued just after a look waited 0.5 s on average before it started. Two ways wake
them sooner:

* On PostgreSQL, queueing a job (or giving one back) sends ``NOTIFY regtree_jobs`` in the
  same transaction (:func:`notify_in`; PostgreSQL delivers it at the commit), and every
  worker, on any machine, waits on a ``LISTEN`` connection of its own (:class:`Listener`).
* On SQLite (one machine), the workers that ``regtree serve`` (and the demo) starts share
  one ``multiprocessing`` event with the API's process: the job route sets it once the job
  is committed (:func:`notify`), and an idle worker waiting on it wakes and clears it
  (:class:`EventWaker`). Workers started on their own (``regtree worker``) have no event
  and keep to their poll.

Either way an idle worker waits in :func:`idle`. The poll is still what makes every due
job run (a retry's backoff, a lost lease, a notification lost with its connection): a wake
only makes the usual case prompt.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Protocol

from sqlalchemy import text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session

from service.db import is_postgresql

logger = logging.getLogger("regtree.worker")

#: The channel of PostgreSQL's notifications of queued jobs.
CHANNEL = "regtree_jobs"

#: The event of the embedded workers, in the process that serves the API (set by
#: :func:`install`; None where the API serves workers it did not start).
_event: Any | None = None

#: Longest single wait on a waker: a worker's shutdown (a threading event it cannot wait
#: on together with the shared event or the connection) is seen within this.
WAKE_SLICE_SECONDS = 0.1


def install(event: Any | None) -> None:
    """Make :func:`notify` set `event` (a ``multiprocessing`` event shared with the
    workers), or nothing when None."""
    global _event
    _event = event


def notify() -> None:
    """A job was queued: wake an idle embedded worker, if there are any."""
    if _event is not None:
        _event.set()


def notify_in(session: Session) -> None:
    """A job is due in `session`'s transaction: on PostgreSQL, notify the listening
    workers when it commits (nothing happens if it rolls back); nothing on SQLite."""
    if is_postgresql(session):
        session.execute(text(f"NOTIFY {CHANNEL}"))


class Waker(Protocol):
    def wait(self, seconds: float) -> bool:
        """Wait at most `seconds`; True when woken (a job was queued)."""


class EventWaker:
    """An embedded worker's side of the shared event (see :func:`install`)."""

    def __init__(self, event: Any) -> None:
        self.event = event

    def wait(self, seconds: float) -> bool:
        if self.event.wait(seconds):
            # cleared before the claim: a job queued after it sets the event again
            self.event.clear()
            return True
        return False

    def close(self) -> None:
        pass


#: After a failed ``LISTEN`` connection, a worker tries again this much later (polling
#: meanwhile), not at every wait.
LISTEN_RETRY_SECONDS = 30.0
#: How long opening that connection may take.
LISTEN_CONNECT_SECONDS = 5


class Listener:
    """A worker's ``LISTEN`` connection to PostgreSQL (psycopg, autocommit), opened at the
    first wait and again :data:`LISTEN_RETRY_SECONDS` after a failure; a connection that
    fails only costs the wake: the waits then sleep their time and the poll goes on."""

    def __init__(self, database_url: str) -> None:
        self.conninfo = make_url(database_url).set(drivername="postgresql").render_as_string(
            hide_password=False)
        self._connection: Any | None = None
        self._retry_at = 0.0
        self._warned = False

    def wait(self, seconds: float) -> bool:
        import psycopg

        if self._connection is None and time.monotonic() < self._retry_at:
            time.sleep(seconds)
            return False
        try:
            if self._connection is None:
                self._connection = psycopg.connect(self.conninfo, autocommit=True,
                                                   connect_timeout=LISTEN_CONNECT_SECONDS)
                self._connection.execute(f"LISTEN {CHANNEL}")
            for _ in self._connection.notifies(timeout=seconds, stop_after=1):
                return True
            return False
        except psycopg.Error as e:
            if not self._warned:
                self._warned = True
                logger.warning("cannot listen for queued jobs; polling only",
                               extra={"error": str(e)})
            self.close()
            self._retry_at = time.monotonic() + LISTEN_RETRY_SECONDS
            time.sleep(seconds)
            return False

    def close(self) -> None:
        connection, self._connection = self._connection, None
        if connection is not None:
            try:
                connection.close()
            except Exception:  # pragma: no cover - closing a broken connection
                pass


def idle(waker: Waker | None, shutdown: threading.Event, seconds: float) -> None:
    """Wait `seconds`, or until `waker` wakes (a job was queued) or `shutdown` is set;
    without a waker, until `shutdown` is set."""
    if waker is None:
        shutdown.wait(seconds)
        return
    deadline = time.monotonic() + seconds
    while not shutdown.is_set():
        left = deadline - time.monotonic()
        if left <= 0:
            return
        if waker.wait(min(left, WAKE_SLICE_SECONDS)):
            return

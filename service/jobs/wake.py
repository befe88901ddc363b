"""Waking idle embedded workers when a job is queued, instead of leaving it to their poll.

A worker looks for due jobs every ``worker_poll_seconds`` (1 s by default, with jitter), so
a job queued just after a look waited 0.5 s on average before it started. The workers that
``regtree serve`` (and the demo) starts share one ``multiprocessing`` event with the API's
process: the job route sets it once the job is committed (:func:`notify`), and an idle
worker waiting on it (:func:`idle`) wakes, clears it and looks at once. Workers started on
their own (``regtree worker``, other machines) have no event and keep to their poll, as do
jobs that become due later (a retry's backoff, a lost lease): the poll is still what makes
every due job run; the event only makes the usual case prompt.
"""

from __future__ import annotations

import threading
import time
from typing import Any

#: The event of the embedded workers, in the process that serves the API (set by
#: :func:`install`; None where the API serves workers it did not start).
_event: Any | None = None

#: Longest single wait on the event: a worker's shutdown (a threading event it cannot wait
#: on together with the process-shared one) is seen within this.
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


def idle(event: Any | None, shutdown: threading.Event, seconds: float) -> None:
    """Wait `seconds`, or until `event` is set (a job was queued: the event is cleared for
    the next one) or `shutdown` is; without an event, until `shutdown` is set."""
    if event is None:
        shutdown.wait(seconds)
        return
    deadline = time.monotonic() + seconds
    while not shutdown.is_set():
        left = deadline - time.monotonic()
        if left <= 0:
            return
        if event.wait(min(left, WAKE_SLICE_SECONDS)):
            # cleared before the claim: a job queued after it sets the event again
            event.clear()
            return

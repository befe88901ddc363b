"""The job's heartbeat thread (``service.jobs.runner.JobControl``) and the end of a run."""

from __future__ import annotations

import logging
import threading

import pytest

from service.core.config import Settings
from service.jobs.queue import Claim, Outcome
from service.jobs.runner import JobControl, LeaseLost


class _Queue:
    """A queue whose lease is gone once the job's outcome is written: each poll waits
    until `release` is set, then reports the lease lost, as the database does after
    ``complete`` marks the job succeeded."""

    def __init__(self) -> None:
        self.polling = threading.Event()
        self.release = threading.Event()

    def peek(self, claim: Claim) -> Outcome:
        self.polling.set()
        self.release.wait(5)
        return Outcome.lost

    def heartbeat(self, claim: Claim, **kw: object) -> Outcome:
        return self.peek(claim)


def test_a_finished_run_does_not_report_its_lease_lost(caplog: pytest.LogCaptureFixture
                                                       ) -> None:
    """A poll in flight when the run ends sees the job no longer running (its outcome
    written): that is the lease ending, not lost. Before, the warning "lease lost" was
    logged whenever a poll fell between the outcome and the pool's closing (seen in the
    demo's stderr)."""
    queue = _Queue()
    settings = Settings(cancel_poll_seconds=0.01, worker_heartbeat_seconds=5.0)
    caplog.set_level(logging.WARNING, logger="regtree.runner")
    with JobControl(queue, Claim(job_id=1, owner="w", attempt=1), settings) as control:  # type: ignore[arg-type]
        assert queue.polling.wait(5)
        control.done()  # the run is over: its outcome is being written
        queue.release.set()  # ... and the poll in flight sees the job finished
    assert not control.lost.is_set() and control.reason() is None
    assert "lease lost" not in caplog.text


def test_a_lease_lost_while_running_still_stops_the_run(caplog: pytest.LogCaptureFixture
                                                        ) -> None:
    queue = _Queue()
    queue.release.set()
    settings = Settings(cancel_poll_seconds=0.01, worker_heartbeat_seconds=5.0)
    caplog.set_level(logging.WARNING, logger="regtree.runner")
    with JobControl(queue, Claim(job_id=2, owner="w", attempt=1), settings) as control:  # type: ignore[arg-type]
        assert control.lost.wait(5)
        with pytest.raises(LeaseLost, match="lease lost"):
            control.check()
    assert "lease lost" in caplog.text

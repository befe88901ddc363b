"""Retry timing shared by the job queue and the callback deliveries: a wait that doubles
with each failed attempt, up to a cap (the settings ``retry_backoff_*`` and
``callback_backoff_*``, :attr:`~service.core.config.Settings.retry_backoff`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Backoff:
    """Exponential backoff: ``base`` seconds after the first failed attempt, doubling with
    each further one, never more than ``cap``. Deterministic (no jitter): workers claim
    retries through the database, one at a time, so they do not stampede."""

    base: float
    cap: float

    def delay(self, failed_attempts: int) -> float:
        """Seconds to wait after ``failed_attempts`` (1 or more) attempts failed."""
        if failed_attempts < 1:
            return 0.0
        return float(min(self.cap, self.base * 2.0 ** min(failed_attempts - 1, 60)))


#: The defaults of the settings retry_backoff_* and callback_backoff_*.
JOB_BACKOFF = Backoff(5.0, 300.0)
CALLBACK_BACKOFF = Backoff(10.0, 600.0)

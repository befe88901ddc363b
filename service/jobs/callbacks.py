"""Job callbacks: a webhook called when a job with a ``callback_url`` ends.

When a job ends (succeeded, failed, cancelled while queued, aborted while running), the
transaction that ends it stores a pending delivery (:func:`schedule`): one row per job
holding the exact JSON body, so a delivery survives a restart. A :class:`Deliverer` (a
thread in every worker process, apart from the loop that claims jobs) POSTs it::

    POST <callback_url>
    Content-Type: application/json
    X-Regtree-Timestamp: 1767268800                  (Unix seconds, when this try was sent)
    X-Regtree-Signature: sha256=<hex HMAC-SHA256 of "<timestamp>.<body>" with the secret>
    X-Regtree-Delivery: <job id>                     (the same on every try: deduplicate)
    X-Regtree-Attempt: <1, 2, ...>

    {"error":null,"finished_at":"...","job_id":3,"job_url":".../v1/jobs/3",
     "result_url":".../v1/jobs/3/result","state":"succeeded","status":"succeeded"}

``state`` is the job's outcome: succeeded, failed, cancelled or aborted; ``result_url`` is
null unless it succeeded. The receiver checks the signature (:func:`verify`) and refuses a
timestamp older than a few minutes, so a captured request cannot be replayed later. Any
2xx answer is a delivery; anything else (another status, a redirect, a connection error or
a timeout) is tried again after an exponential backoff, up to ``callback_max_attempts``
tries. Every try is recorded (``GET /v1/jobs/{id}/deliveries``).

A ``callback_url`` must be http(s) on a host of the setting ``callback_allowed_hosts``, and
the server must have ``callback_secret``; otherwise the job is refused (:func:`check_url`).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any
from urllib.parse import urlsplit

import httpx
from sqlalchemy import and_, or_, select, update
from sqlalchemy.orm import Session

from service.core.backoff import CALLBACK_BACKOFF, Backoff
from service.core.config import Settings
from service.db import Database, lock_first
from service.models import (
    CallbackAttempt,
    CallbackDelivery,
    DeliveryState,
    Job,
    JobOutcome,
    utcnow,
)

logger = logging.getLogger("regtree.callbacks")

SIGNATURE_HEADER = "X-Regtree-Signature"
TIMESTAMP_HEADER = "X-Regtree-Timestamp"
DELIVERY_HEADER = "X-Regtree-Delivery"
ATTEMPT_HEADER = "X-Regtree-Attempt"


# --- signing -----------------------------------------------------------------------------


def sign(secret: str, timestamp: int, body: bytes) -> str:
    """The ``X-Regtree-Signature`` value: ``sha256=`` and the hex HMAC-SHA256 of
    ``b"<timestamp>." + body`` keyed with the shared secret."""
    mac = hmac.new(secret.encode(), f"{int(timestamp)}.".encode() + body, hashlib.sha256)
    return f"sha256={mac.hexdigest()}"


def verify(
    secret: str,
    body: bytes,
    *,
    timestamp: str | None,
    signature: str | None,
    tolerance_seconds: float = 300.0,
    now: float | None = None,
) -> bool:
    """Whether a callback is authentic and fresh: what a receiver checks, given the raw
    body and the two headers. A timestamp further than ``tolerance_seconds`` from ``now``
    is refused (a replay)."""
    if not timestamp or not signature:
        return False
    try:
        sent = int(timestamp)
    except ValueError:
        return False
    if abs((time.time() if now is None else now) - sent) > tolerance_seconds:
        return False
    return hmac.compare_digest(sign(secret, sent, body), signature)


# --- where a callback may go -----------------------------------------------------------------


def allowed_hosts(settings: Settings) -> list[str]:
    return [h.strip().lower() for h in settings.callback_allowed_hosts.split(",") if h.strip()]


def _split(pattern: str) -> tuple[str, int | None]:
    """``host``, ``host:port``, ``[v6]`` or ``[v6]:port`` -> (host, port or None)."""
    if pattern.startswith("["):
        host, _, rest = pattern[1:].partition("]")
        return host, int(rest[1:]) if rest[1:].isdigit() else None
    name, sep, port = pattern.rpartition(":")
    if sep and port.isdigit() and ":" not in name:
        return name, int(port)
    return pattern, None


def _host_allowed(host: str, port: int, patterns: list[str]) -> bool:
    for pattern in patterns:
        name, allowed_port = _split(pattern)
        if allowed_port is not None and allowed_port != port:
            continue
        if name == host or (name.startswith("*.") and host.endswith(name[1:])):
            return True
    return False


def check_url(url: str, settings: Settings) -> str:
    """The callback URL if this server may call it; a ``ValueError`` saying why not."""
    if settings.callback_secret is None or not settings.callback_secret.get_secret_value():
        raise ValueError(
            "callbacks are not enabled on this server: it has no callback_secret (setting "
            "REGTREE_CALLBACK_SECRET) to sign them with"
        )
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"callback_url must be an http or https URL with a host; got {url!r}")
    if parts.username is not None or parts.password is not None:
        raise ValueError("callback_url must not carry a user name or password")
    try:
        port = parts.port
    except ValueError as e:
        raise ValueError(f"callback_url has an invalid port: {e}") from None
    patterns = allowed_hosts(settings)
    effective = port if port is not None else (443 if parts.scheme == "https" else 80)
    if not _host_allowed(parts.hostname.lower(), effective, patterns):
        allowed = ", ".join(patterns) or "none"
        raise ValueError(
            f"callback_url host {parts.hostname!r} is not allowed (setting "
            f"callback_allowed_hosts: {allowed})"
        )
    return url


# --- scheduling ----------------------------------------------------------------------------


@dataclass(frozen=True)
class CallbackPolicy:
    max_attempts: int = 5
    backoff: Backoff = CALLBACK_BACKOFF
    public_url: str | None = None

    @classmethod
    def from_settings(cls, settings: Settings) -> CallbackPolicy:
        return cls(
            max_attempts=settings.callback_max_attempts,
            backoff=settings.callback_backoff,
            public_url=settings.public_url,
        )


def callback_body(job: Job, public_url: str | None) -> str:
    """The JSON a job's callback sends (compact, keys sorted: the exact bytes signed)."""
    job_url = f"{(public_url or '').rstrip('/')}/v1/jobs/{job.id}"
    body = {
        "job_id": job.id,
        "state": job.outcome,
        "status": job.status,
        "error": (job.error or "")[:1000] or None,
        "job_url": job_url,
        "result_url": f"{job_url}/result" if job.outcome == JobOutcome.succeeded else None,
        "finished_at": job.finished_at.isoformat() if job.finished_at else None,
    }
    return json.dumps(body, separators=(",", ":"), sort_keys=True)


def schedule(session: Session, job_id: int, now: datetime, policy: CallbackPolicy) -> None:
    """Store the callback of a job that just ended (in the transaction that ended it)."""
    job = session.get(Job, job_id, populate_existing=True)
    if job is None or not job.callback_url:
        return
    session.add(
        CallbackDelivery(
            job_id=job_id,
            url=job.callback_url,
            body=callback_body(job, policy.public_url),
            state=DeliveryState.pending.value,
            attempts=0,
            max_attempts=policy.max_attempts,
            next_attempt_at=now,
            created_at=now,
        )
    )


# --- delivering ----------------------------------------------------------------------------


@dataclass(frozen=True)
class _Due:
    job_id: int
    url: str
    body: str
    attempt: int


class Deliverer:
    """Delivers due callbacks, one at a time, with a lease so that two workers never send
    the same try; a worker that dies mid-try leaves it to be tried again once the lease
    expires. No database transaction is open while a request is in flight."""

    def __init__(
        self,
        db: Database,
        settings: Settings,
        owner: str,
        *,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.db = db
        self.owner = owner
        self.policy = CallbackPolicy.from_settings(settings)
        secret = settings.callback_secret
        self.secret = secret.get_secret_value() if secret is not None else ""
        self.timeout = settings.callback_timeout_seconds
        self.poll = settings.callback_poll_seconds
        self._client = httpx.Client(
            timeout=self.timeout, follow_redirects=False, transport=transport
        )

    def close(self) -> None:
        self._client.close()

    def _claim(self) -> _Due | None:
        now = utcnow()
        with self.db.write() as session:
            free = or_(
                CallbackDelivery.lease_owner.is_(None), CallbackDelivery.lease_expires_at < now
            )
            due = and_(
                CallbackDelivery.state == DeliveryState.pending.value,
                CallbackDelivery.next_attempt_at <= now,
                free,
            )
            order = (CallbackDelivery.next_attempt_at, CallbackDelivery.job_id)
            row = lock_first(session, select(CallbackDelivery).where(due).order_by(*order))
            if row is None:
                return None
            if row.attempts >= row.max_attempts:  # its last try was cut short (a crash)
                row.state, row.finished_at, row.lease_owner = DeliveryState.failed.value, now, None
                return None
            row.attempts += 1
            row.lease_owner = self.owner
            row.lease_expires_at = now + timedelta(seconds=self.timeout + 30)
            return _Due(row.job_id, row.url, row.body, row.attempts)

    def _send(self, due: _Due) -> tuple[int | None, str | None]:
        body = due.body.encode()
        timestamp = int(time.time())
        headers = {
            "Content-Type": "application/json",
            TIMESTAMP_HEADER: str(timestamp),
            SIGNATURE_HEADER: sign(self.secret, timestamp, body),
            DELIVERY_HEADER: str(due.job_id),
            ATTEMPT_HEADER: str(due.attempt),
            "User-Agent": "regtree-callback/1",
        }
        try:
            response = self._client.post(due.url, content=body, headers=headers)
        except httpx.HTTPError as e:
            return None, f"{type(e).__name__}: {e}"[:1000]
        if 200 <= response.status_code < 300:
            return response.status_code, None
        return response.status_code, f"HTTP {response.status_code}"

    def _record(
        self, due: _Due, started: datetime, seconds: float, code: int | None, error: str | None
    ) -> str:
        now = utcnow()
        with self.db.write() as session:
            max_attempts = session.scalar(
                select(CallbackDelivery.max_attempts).where(CallbackDelivery.job_id == due.job_id)
            )
            if error is None:
                values: dict[str, Any] = {"state": DeliveryState.delivered.value}
            elif max_attempts is None or due.attempt >= max_attempts:
                values = {"state": DeliveryState.failed.value}
            else:
                delay = self.policy.backoff.delay(due.attempt)
                values = {"next_attempt_at": now + timedelta(seconds=delay)}
            if "state" in values:
                values["finished_at"] = now
            result = session.execute(
                update(CallbackDelivery)
                .where(
                    CallbackDelivery.job_id == due.job_id,
                    CallbackDelivery.lease_owner == self.owner,
                    CallbackDelivery.attempts == due.attempt,
                )
                .values(lease_owner=None, lease_expires_at=None, **values)
                .execution_options(synchronize_session=False)
            )
            if getattr(result, "rowcount", 0) != 1:
                return "lost"  # our lease expired and another worker took the delivery
            session.add(
                CallbackAttempt(
                    job_id=due.job_id,
                    attempt=due.attempt,
                    started_at=started,
                    duration_ms=int(seconds * 1000),
                    status_code=code,
                    error=error,
                )
            )
            return str(values.get("state", DeliveryState.pending.value))

    def deliver_once(self) -> str | None:
        """Try one due callback; its delivery state afterwards, or None if none was due."""
        due = self._claim()
        if due is None:
            return None
        started, clock = utcnow(), time.monotonic()
        code, error = self._send(due)
        state = self._record(due, started, time.monotonic() - clock, code, error)
        log = {"job_id": due.job_id, "attempt": due.attempt, "state": state, "error": error}
        logger.log(logging.INFO if error is None else logging.WARNING, "callback tried", extra=log)
        return state

    def run(self, stop: threading.Event) -> None:
        """Deliver due callbacks until ``stop`` is set, polling every ``callback_poll_seconds``."""
        while not stop.is_set():
            try:
                while not stop.is_set() and self.deliver_once() is not None:
                    pass
            except Exception:
                logger.exception("callback delivery loop error")
            stop.wait(self.poll)
        self.close()

"""``Idempotency-Key`` support for POST requests.

Each key is scoped to the request path. The first request with a key stores a hash of its body
and the ids of what it created, in the same write transaction as the resource itself (on
SQLite the transaction is ``BEGIN IMMEDIATE``, so two concurrent requests with one key are
serialised and the second sees the first's row). A repeat with the same body is answered
with the current state of that resource; a repeat with a different body is a 422 problem.

On PostgreSQL (READ COMMITTED) two concurrent first requests would both find no row, both
create their resource, and the second would fail on the unique constraint at commit (a 500).
So :func:`lookup` first takes a transaction-level advisory lock named by the scope and key:
the second request waits until the first commits or rolls back, and its lookup, a new
statement with a new snapshot, then finds the first's row and returns the same resource.
The unique constraint stays as the backstop.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.api.problems import ProblemError
from service.contract.names import ProblemType
from service.db import is_postgresql
from service.models import IdempotencyKey


def hash_json(value: Any) -> str:
    canonical = json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()


def hash_bytes(*parts: bytes) -> str:
    digest = hashlib.sha256()
    for part in parts:
        digest.update(len(part).to_bytes(8, "big"))
        digest.update(part)
    return digest.hexdigest()


def advisory_lock_id(scope: str, key: str) -> int:
    """A signed 64-bit number naming ``(scope, key)`` for ``pg_advisory_xact_lock``.

    Two keys that share a number only wait for each other; they never share a resource.
    """
    digest = hashlib.sha256(f"regtree-idempotency\n{scope}\n{key}".encode()).digest()
    return int.from_bytes(digest[:8], "big", signed=True)


def lookup(
    session: Session, scope: str, key: str | None, request_hash: str
) -> IdempotencyKey | None:
    """The stored entry for ``key`` in ``scope``, or None; 422 if the body differs.

    Call it in the write transaction that will create the resource and :func:`remember` it.
    """
    if key is None:
        return None
    if is_postgresql(session):
        # Held until the transaction ends: concurrent requests with this key take turns.
        session.execute(select(func.pg_advisory_xact_lock(advisory_lock_id(scope, key))))
    entry = session.scalars(
        select(IdempotencyKey).where(IdempotencyKey.scope == scope, IdempotencyKey.key == key)
    ).one_or_none()
    if entry is not None and entry.request_hash != request_hash:
        raise ProblemError(
            422,
            "Idempotency-Key was already used with a different request body",
            type_=ProblemType.IDEMPOTENCY_KEY_REUSED,
        )
    return entry


def remember(
    session: Session,
    scope: str,
    key: str | None,
    request_hash: str,
    *,
    status_code: int,
    resource_type: str,
    resource_ids: list[int],
) -> None:
    if key is None:
        return
    session.add(
        IdempotencyKey(
            scope=scope,
            key=key,
            request_hash=request_hash,
            status_code=status_code,
            resource_type=resource_type,
            resource_ids=resource_ids,
        )
    )

"""SQLAlchemy ORM models: collections, shapes, jobs, results, idempotency keys.

Times are stored as naive UTC and read back as aware UTC (:class:`UTCDateTime`), so that the
same SQL works on SQLite and on a server database. Integer ids use SQLite AUTOINCREMENT so an
id is never reused after a delete (results keep referring to shape ids).
"""

from __future__ import annotations

import enum
import io
from datetime import UTC, datetime
from typing import Any

import numpy as np
from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Dialect,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

# Ids are 64-bit everywhere (the API accepts any id up to 2**63 - 1): BIGINT on a server
# database, plain INTEGER on SQLite (already 64-bit, and required for AUTOINCREMENT).
Id = BigInteger().with_variant(Integer(), "sqlite")


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Store naive UTC, return aware UTC."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value
        return value.astimezone(UTC).replace(tzinfo=None)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    pass


def _never_reused_ids(*table_args: Any) -> tuple[Any, ...]:
    """``__table_args__`` for a table whose ids are never handed out again: SQLite's
    AUTOINCREMENT (a deleted job's id never names a new job); other databases' sequences
    already behave so."""
    return (*table_args, {"sqlite_autoincrement": True})


class JobStatus(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


TERMINAL_STATUSES = (JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled)


class JobOutcome(enum.StrEnum):
    """How a job ended (``Job.outcome``; None until it ends).

    ``status`` keeps the five states every client knows; the outcome tells the two ways of
    ending ``cancelled`` apart: ``cancelled`` (while queued: it never ran, or waited for a
    retry) and ``aborted`` (while running: its worker stopped the registrations in progress).
    """

    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"
    aborted = "aborted"


class Collection(Base):
    __tablename__ = "collections"
    __table_args__ = _never_reused_ids()

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)

    shapes: Mapped[list[Shape]] = relationship(
        back_populates="collection", cascade="all, delete-orphan", passive_deletes=True
    )


class Shape(Base):
    __tablename__ = "shapes"
    __table_args__ = _never_reused_ids(Index("ix_shapes_collection_id_id", "collection_id", "id"))

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    collection_id: Mapped[int] = mapped_column(
        Id, ForeignKey("collections.id", ondelete="CASCADE"), index=False
    )
    name: Mapped[str] = mapped_column(String(300))
    source_format: Mapped[str] = mapped_column(String(40))
    n_points: Mapped[int] = mapped_column(Integer)
    min_x: Mapped[float] = mapped_column(Float)
    min_y: Mapped[float] = mapped_column(Float)
    max_x: Mapped[float] = mapped_column(Float)
    max_y: Mapped[float] = mapped_column(Float)
    points_npy: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

    collection: Mapped[Collection] = relationship(back_populates="shapes")

    @property
    def points(self) -> np.ndarray:
        """The (n, 2) float64 points, decoded from the stored ``.npy`` bytes."""
        return points_from_npy(self.points_npy)


def points_to_npy(points: np.ndarray) -> bytes:
    """``.npy`` bytes of a float64 array (points, or any other array)."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(points, dtype=np.float64), allow_pickle=False)
    return buffer.getvalue()


def points_from_npy(data: bytes) -> np.ndarray:
    array = np.load(io.BytesIO(data), allow_pickle=False)
    return np.asarray(array, dtype=np.float64).reshape(-1, 2)


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = _never_reused_ids(
        Index("ix_jobs_status_created", "status", "created_at"),
        Index("ix_jobs_collection_id", "collection_id"),
    )

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    collection_id: Mapped[int] = mapped_column(
        Id, ForeignKey("collections.id", ondelete="CASCADE")
    )
    # A plain id, not a foreign key: a finished job keeps naming its model after a delete.
    # Null for a grouping, which has no model (migration 0006).
    model_shape_id: Mapped[int | None] = mapped_column(Id, nullable=True)
    # The shapes of the collection when the job was submitted, in input order.
    shape_ids: Mapped[list[int]] = mapped_column(JSON)
    method: Mapped[str] = mapped_column(String(40))
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(20), default=JobStatus.queued.value)
    progress_stage: Mapped[str | None] = mapped_column(String(100), nullable=True)
    progress_done: Mapped[int] = mapped_column(Integer, default=0)
    progress_total: Mapped[int] = mapped_column(Integer, default=0)
    # The worker's estimate of the share of the whole job done (service.progress).
    progress_fraction: Mapped[float | None] = mapped_column(Float, nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    lease_owner: Mapped[str | None] = mapped_column(String(200), nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    # How it ended (JobOutcome); when a queued retry may be claimed (None: at once).
    outcome: Mapped[str | None] = mapped_column(String(20), nullable=True)
    next_attempt_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    callback_url: Mapped[str | None] = mapped_column(Text, nullable=True)


class DeliveryState(enum.StrEnum):
    pending = "pending"
    delivered = "delivered"
    failed = "failed"


class CallbackDelivery(Base):
    """The callback of a job that ended: one row per job, written in the transaction that
    ended it, so a pending delivery survives a restart (:mod:`service.jobs.callbacks`)."""

    __tablename__ = "callback_deliveries"
    __table_args__ = (Index("ix_callback_deliveries_state_next", "state", "next_attempt_at"),)

    job_id: Mapped[int] = mapped_column(
        Id, ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True
    )
    url: Mapped[str] = mapped_column(Text)
    body: Mapped[str] = mapped_column(Text)  # the exact JSON sent (and signed) each time
    state: Mapped[str] = mapped_column(String(20), default=DeliveryState.pending.value)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer)
    next_attempt_at: Mapped[datetime] = mapped_column(UTCDateTime)
    lease_owner: Mapped[str | None] = mapped_column(String(200), nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)


class CallbackAttempt(Base):
    """One try at delivering a job's callback: when, and what the receiver answered."""

    __tablename__ = "callback_attempts"
    __table_args__ = _never_reused_ids(Index("ix_callback_attempts_job_id", "job_id", "attempt"))

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    job_id: Mapped[int] = mapped_column(
        Id, ForeignKey("callback_deliveries.job_id", ondelete="CASCADE")
    )
    attempt: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime)
    duration_ms: Mapped[int] = mapped_column(Integer)
    status_code: Mapped[int | None] = mapped_column(Integer, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)


class Result(Base):
    """The result document of a succeeded job, with heavy per-subject arrays left out."""

    __tablename__ = "results"

    job_id: Mapped[int] = mapped_column(
        Id, ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True
    )
    document: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    #: The similarity D the job computed, (n, n) float64 ``.npy`` bytes in the order of the
    #: job's ``shape_ids`` (NaN: not computed); None for results from before it was kept.
    #: Deferred: read only by ``GET /v1/jobs/{id}/similarity`` and the export.
    similarity_npy: Mapped[bytes | None] = mapped_column(
        LargeBinary, nullable=True, deferred=True
    )

    @property
    def similarity(self) -> np.ndarray | None:
        if self.similarity_npy is None:
            return None
        array = np.load(io.BytesIO(self.similarity_npy), allow_pickle=False)
        return np.asarray(array, dtype=np.float64)


class ResultSubject(Base):
    """One subject of a result: its place in the tree, error, transform and correspondences."""

    __tablename__ = "result_subjects"

    job_id: Mapped[int] = mapped_column(
        Id, ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True
    )
    shape_id: Mapped[int] = mapped_column(Id, primary_key=True)
    position: Mapped[int] = mapped_column(Integer)
    parent_shape_id: Mapped[int | None] = mapped_column(Id, nullable=True)
    layer: Mapped[int | None] = mapped_column(Integer, nullable=True)
    error: Mapped[float | None] = mapped_column(Float, nullable=True)
    document: Mapped[dict[str, Any]] = mapped_column(JSON)


class IdempotencyKey(Base):
    """A POST seen with an ``Idempotency-Key`` header: what was asked and what it created."""

    __tablename__ = "idempotency_keys"
    __table_args__ = (UniqueConstraint("scope", "key", name="uq_idempotency_scope_key"),)

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    scope: Mapped[str] = mapped_column(String(300))
    key: Mapped[str] = mapped_column(String(300))
    request_hash: Mapped[str] = mapped_column(String(64))
    status_code: Mapped[int] = mapped_column(Integer)
    resource_type: Mapped[str] = mapped_column(String(40))
    resource_ids: Mapped[list[int]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

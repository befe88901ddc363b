"""Storing and deleting shapes: idempotency, the collection lock, name policy, quota, insert.

The routes in :mod:`service.api.routes.shapes` speak HTTP and decode uploads; everything that
reads or writes the database for an upload or a delete is here, in one write transaction
each, so a refused upload changes nothing (on SQLite the transaction starts with ``BEGIN
IMMEDIATE``; on PostgreSQL the collection row is locked ``FOR UPDATE``, so two uploads to one
collection take turns and cannot both pass the name check or the size limit).

Refusals are the exceptions below; the route turns them into problem documents.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session, defer

from service.api import idempotency
from service.api.routes.collections import get_collection_or_404
from service.contract.names import OnConflict
from service.db import Database
from service.models import TERMINAL_STATUSES, Job, Shape, points_to_npy


@dataclass
class NewShape:
    """A decoded upload, ready to store. ``label`` names it in messages (file name or index)."""

    name: str
    source_format: str
    points: np.ndarray
    label: str = ""


@dataclass
class Stored:
    """The rows an upload stored (in upload order) and the ids of the shapes it replaced."""

    shapes: list[Shape]
    replaced_ids: list[int] = field(default_factory=list)


class NameConflict(Exception):
    """``on_conflict=refuse`` and the collection already holds shapes of these names."""

    def __init__(self, collection_id: int, existing: list[tuple[int, str]]) -> None:
        self.collection_id = collection_id
        self.existing = existing
        shown = ", ".join(f"{name!r} (id {sid})" for sid, name in existing[:5])
        more = f" and {len(existing) - 5} more" if len(existing) > 5 else ""
        super().__init__(
            f"collection {collection_id} already has shape(s) named {shown}{more}; nothing was "
            "stored. Pass on_conflict=replace to replace them or on_conflict=keep to keep "
            "both, or upload under other names"
        )


class DuplicateNames(Exception):
    """One upload names two shapes alike (allowed only with ``on_conflict=keep``)."""

    def __init__(self, name: str, labels: list[str]) -> None:
        self.name = name
        self.labels = labels
        super().__init__(
            f"this upload has {len(labels)} shapes named {name!r} ({', '.join(labels)}); "
            "nothing was stored. Give them distinct names, or pass on_conflict=keep to store "
            "them all"
        )


class CollectionFull(Exception):
    def __init__(self, collection_id: int, existing: int, adding: int, limit: int) -> None:
        super().__init__(
            f"collection {collection_id} has {existing} shapes; adding {adding} would pass the "
            f"limit of {limit} (setting max_shapes_per_collection)"
        )


class ShapesInUse(Exception):
    """Shapes that unfinished jobs use cannot be deleted or replaced."""

    def __init__(self, using: dict[int, list[int]], *, replacing: bool = False) -> None:
        self.using = using
        shown = "; ".join(
            f"shape {sid} is used by unfinished job(s) {jobs}" for sid, jobs in using.items()
        )
        why = " (on_conflict=replace deletes the old shapes); nothing was stored"
        if not replacing:
            why = ""
        super().__init__(f"{shown}; cancel them or wait{why}")


def content_name(points: np.ndarray) -> str:
    """The name of a shape uploaded without one: ``shape-`` and 12 hex digits of the SHA-256
    of its points (little-endian float64, row by row), so the same points get the same name
    whatever the file format, and uploading them twice is seen as a name conflict."""
    data = np.ascontiguousarray(points, dtype="<f8").tobytes()
    return "shape-" + hashlib.sha256(data).hexdigest()[:12]


def shapes_in_use(
    session: Session, collection_id: int, shape_ids: Iterable[int]
) -> dict[int, list[int]]:
    """For each of ``shape_ids`` that an unfinished job of the collection uses, those jobs."""
    wanted = set(shape_ids)
    jobs = session.scalars(
        select(Job).where(
            Job.collection_id == collection_id,
            Job.status.not_in([s.value for s in TERMINAL_STATUSES]),
        )
    ).all()
    using: dict[int, list[int]] = {}
    for job in jobs:
        for sid in sorted(wanted & ({job.model_shape_id} | set(job.shape_ids))):
            using.setdefault(sid, []).append(job.id)
    return using


def _check_names_within(items: Sequence[NewShape]) -> None:
    seen: dict[str, list[str]] = {}
    for k, item in enumerate(items):
        seen.setdefault(item.name, []).append(item.label or f"shapes[{k}]")
    for name, labels in seen.items():
        if len(labels) > 1:
            raise DuplicateNames(name, labels)


def _row(collection_id: int, item: NewShape) -> Shape:
    pts = item.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return Shape(
        collection_id=collection_id,
        name=item.name,
        source_format=item.source_format,
        n_points=int(pts.shape[0]),
        min_x=float(lo[0]),
        min_y=float(lo[1]),
        max_x=float(hi[0]),
        max_y=float(hi[1]),
        points_npy=points_to_npy(pts),
    )


def add_shapes(
    db: Database,
    collection_id: int,
    items: Sequence[NewShape],
    *,
    on_conflict: OnConflict,
    max_shapes: int,
    scope: str,
    key: str | None,
    request_hash: str,
) -> Stored:
    """Store an upload, all or nothing, under the name policy ``on_conflict``.

    * ``refuse``: if the collection holds a shape of any uploaded name, raise
      :class:`NameConflict` naming them;
    * ``replace``: delete the shapes of those names (refused with :class:`ShapesInUse` if an
      unfinished job uses one), then store the new ones (new ids);
    * ``keep``: store the new shapes beside the old ones, names repeated.

    Two uploaded shapes of one name raise :class:`DuplicateNames` unless ``keep``. A repeat
    of an ``Idempotency-Key`` returns what the first request stored.
    """
    with db.write() as session:
        entry = idempotency.lookup(session, scope, key, request_hash)
        if entry is not None:
            again = [session.get(Shape, sid) for sid in entry.resource_ids]
            return Stored([s for s in again if s is not None])
        get_collection_or_404(session, collection_id, for_update=True)
        if on_conflict != "keep":
            _check_names_within(items)
        names = {item.name for item in items}
        held = session.execute(
            select(Shape.id, Shape.name)
            .where(Shape.collection_id == collection_id)
            .order_by(Shape.id)
        ).all()
        clashes = [(int(sid), str(name)) for sid, name in held if name in names]
        replaced: list[int] = []
        if clashes and on_conflict == "refuse":
            raise NameConflict(collection_id, clashes)
        if clashes and on_conflict == "replace":
            replaced = [sid for sid, _ in clashes]
            using = shapes_in_use(session, collection_id, replaced)
            if using:
                raise ShapesInUse(using, replacing=True)
            for sid in replaced:
                session.delete(session.get(Shape, sid))
        remaining = len(held) - len(replaced)
        if remaining + len(items) > max_shapes:
            raise CollectionFull(collection_id, remaining, len(items), max_shapes)
        rows = [_row(collection_id, item) for item in items]
        session.add_all(rows)
        session.flush()
        idempotency.remember(
            session,
            scope,
            key,
            request_hash,
            status_code=201,
            resource_type="shapes",
            resource_ids=[r.id for r in rows],
        )
        return Stored(rows, replaced)


def count_shapes(session: Session, collection_id: int) -> int:
    return int(
        session.scalar(select(func.count(Shape.id)).where(Shape.collection_id == collection_id))
        or 0
    )


def list_shapes(session: Session, collection_id: int, limit: int, offset: int) -> list[Shape]:
    """A page of a collection's shapes in upload order, points not loaded."""
    return list(
        session.scalars(
            select(Shape)
            .options(defer(Shape.points_npy))
            .where(Shape.collection_id == collection_id)
            .order_by(Shape.id)
            .limit(limit)
            .offset(offset)
        ).all()
    )


def get_shape(session: Session, collection_id: int, shape_id: int) -> Shape | None:
    shape = session.get(Shape, shape_id)
    return shape if shape is not None and shape.collection_id == collection_id else None


def delete_shape(db: Database, collection_id: int, shape_id: int) -> bool:
    """Delete a shape; False if there is none. :class:`ShapesInUse` if a job needs it."""
    with db.write() as session:
        shape = get_shape(session, collection_id, shape_id)
        if shape is None:
            return False
        using = shapes_in_use(session, collection_id, [shape_id])
        if using:
            raise ShapesInUse(using)
        session.delete(shape)
    return True

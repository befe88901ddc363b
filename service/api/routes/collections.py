"""``/v1/collections``: create, list, read and delete shape collections."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.api import idempotency
from service.api.deps import DbDep, IdempotencyKeyDep, PaginationDep
from service.api.problems import not_found, operation
from service.models import Collection, Shape
from service.schemas import CollectionCreate, CollectionOut, DbId, Page

router = APIRouter(prefix="/collections", tags=["collections"])


def _shape_counts(session: Session, ids: list[int]) -> dict[int, int]:
    if not ids:
        return {}
    rows = session.execute(
        select(Shape.collection_id, func.count(Shape.id))
        .where(Shape.collection_id.in_(ids))
        .group_by(Shape.collection_id)
    ).all()
    return {cid: count for cid, count in rows}


def collection_out(collection: Collection, n_shapes: int) -> CollectionOut:
    return CollectionOut(
        id=collection.id,
        name=collection.name,
        description=collection.description,
        n_shapes=n_shapes,
        created_at=collection.created_at,
        updated_at=collection.updated_at,
    )


def get_collection_or_404(
    session: Session, collection_id: int, *, for_update: bool = False
) -> Collection:
    collection = session.get(Collection, collection_id, with_for_update=for_update)
    if collection is None:
        raise not_found("collection", collection_id)
    return collection


@operation(
    router.post, "", "Create a collection", (401, 413, 422),
    status_code=status.HTTP_201_CREATED, response_model=CollectionOut,
)
def create_collection(
    body: CollectionCreate,
    request: Request,
    response: Response,
    db: DbDep,
    idempotency_key: IdempotencyKeyDep = None,
) -> CollectionOut:
    """Creates an empty collection and answers 201 with it and its `Location`; upload shapes
    to `/v1/collections/{id}/shapes` next. Names need not be unique. With an
    `Idempotency-Key`, the same request sent again answers the collection it created the first
    time; the same key with another body is a 422."""
    scope = f"POST {request.url.path}"
    request_hash = idempotency.hash_json(body.model_dump())
    with db.write() as session:
        entry = idempotency.lookup(session, scope, idempotency_key, request_hash)
        if entry is not None:
            collection = get_collection_or_404(session, entry.resource_ids[0])
        else:
            collection = Collection(name=body.name, description=body.description)
            session.add(collection)
            session.flush()
            idempotency.remember(
                session,
                scope,
                idempotency_key,
                request_hash,
                status_code=201,
                resource_type="collection",
                resource_ids=[collection.id],
            )
        n_shapes = _shape_counts(session, [collection.id]).get(collection.id, 0)
    response.headers["Location"] = f"/v1/collections/{collection.id}"
    return collection_out(collection, n_shapes)


@router.get("", response_model=Page[CollectionOut], summary="List collections")
def list_collections(db: DbDep, page: PaginationDep) -> Page[CollectionOut]:
    """Every collection, oldest first, one page at a time (`limit`, `offset`; `total` counts
    them all), each with its number of shapes."""
    with db.read() as session:
        total = session.scalar(select(func.count(Collection.id))) or 0
        collections = session.scalars(
            select(Collection).order_by(Collection.id).limit(page.limit).offset(page.offset)
        ).all()
        counts = _shape_counts(session, [c.id for c in collections])
        items = [collection_out(c, counts.get(c.id, 0)) for c in collections]
    return Page[CollectionOut](items=items, total=total, limit=page.limit, offset=page.offset)


@operation(
    router.get, "/{collection_id}", "Read a collection", (404,),
    response_model=CollectionOut,
)
def get_collection(collection_id: DbId, db: DbDep) -> CollectionOut:
    """The collection's name, description, number of shapes and times."""
    with db.read() as session:
        collection = get_collection_or_404(session, collection_id)
        n_shapes = _shape_counts(session, [collection_id]).get(collection_id, 0)
        return collection_out(collection, n_shapes)


@operation(
    router.delete, "/{collection_id}", "Delete a collection, its shapes, jobs and results", (404,),
    status_code=status.HTTP_204_NO_CONTENT,
)
def delete_collection(collection_id: DbId, db: DbDep) -> Response:
    """Deletes the collection with everything in it: its shapes, and its jobs with their
    results. 204 with no body."""
    with db.write() as session:
        collection = get_collection_or_404(session, collection_id)
        session.delete(collection)
    return Response(status_code=status.HTTP_204_NO_CONTENT)

"""``/v1/collections/{id}/shapes``: upload, list, read and delete shapes.

The upload's forms, names and conflict policy are described for users in ``_UPLOAD_DOC``
(the operation's OpenAPI description). Decoding and validation are :mod:`service.ingest`'s;
storing is :mod:`service.api.shape_store`'s.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response, status
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import FormData, UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from service import ingest
from service.api import idempotency, shape_store
from service.api.deps import DbDep, IdempotencyKeyDep, PaginationDep, SettingsDep
from service.api.problems import ProblemError, not_found, operation
from service.api.routes.collections import get_collection_or_404
from service.api.shape_store import NewShape, OnConflict, content_name
from service.contract.names import ProblemType
from service.core.config import Settings
from service.core.limits import bounds, example
from service.models import Shape
from service.schemas import (
    NO_NUL,
    DbId,
    ImageMode,
    Page,
    ShapeBatchOut,
    ShapeDetail,
    ShapeOut,
)

router = APIRouter(prefix="/collections/{collection_id}/shapes", tags=["shapes"])

#: The upload operation's description (Markdown, as /docs renders it).
_UPLOAD_DOC = """One upload endpoint takes every supported form:

* `application/json`: `{"name": ..., "points": [[x, y], ...]}`, or a batch
  `{"shapes": [{"name": ..., "points": ...}, ...]}`;
* `multipart/form-data`: one or many files in the `files` field, with optional form fields
  `mode` (contour|edges|skeleton, for images) and `target_points`;
* a raw body typed `text/csv`, `text/plain`, `application/octet-stream` (`.npy`),
  `image/png` or `image/jpeg`, named with `?name=`.

Names: a file's name without its extension (multipart), `?name=` (raw body) or the
`"name"` of a JSON shape; a shape uploaded without one is named `shape-` and 12 hex
digits of the SHA-256 of its points (the same points get the same name in every format).

Existing names: `?on_conflict=` says what happens when the collection already holds a shape
of an uploaded name. `refuse` (the default: uploading a folder twice must not double the
collection) answers 409 naming the existing shapes; `replace` deletes them and stores the
new ones under new ids (409 if an unfinished job uses one); `keep` stores the new ones
beside them, the name repeated. One upload naming two shapes alike is a 422 unless `keep`.

Shapes whose points all coincide, or nearly, are refused. An upload is all-or-nothing: a
bad file answers 422 and nothing is stored; a refused upload leaves the collection as it
was. The problem document lists every invalid file of the batch (or shape of a JSON batch)
in `invalid`, each with its `file` (or `shape`), `index` and `detail`; its `detail` names
the first and counts the others, and `file` (or `shape`) and `index` repeat the first.
"""

#: The limits, as the operation's description states them (placeholders: service.core.limits).
_LIMITS_DOC = """
Limits of this server: a request body of at most {max_body_bytes} bytes (else 413);
{min_points} to {max_points_per_shape} points per shape, each coordinate within
±{max_coordinate:g}; images of at most {max_image_pixels} pixels; at most {max_batch_files}
files (multipart) or shapes (JSON batch) in one upload; at most {max_shapes_per_collection}
shapes in the collection (else 422, nothing stored).
"""

_TARGET_POINTS_DOC = (
    "Upper bound on the points taken from an image: {min_points} to {max_points_per_shape} "
    "(settings min_points and max_points_per_shape)."
)
_TARGET_POINTS_BOUNDS = bounds(minimum="min_points", maximum="max_points_per_shape")

RAW_TYPES = {
    "text/csv": "csv",
    "text/plain": "txt",
    "application/octet-stream": "npy",
    "application/x-npy": "npy",
    "image/png": "png",
    "image/jpeg": "jpeg",
}

_UPLOAD_OPENAPI: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {
                "schema": {
                    "oneOf": [
                        {"$ref": "#/components/schemas/ShapeJSON"},
                        {"$ref": "#/components/schemas/ShapeBatchJSON"},
                    ]
                },
                "examples": {
                    "single": {
                        "summary": "One shape",
                        "value": {"name": "polygon", "points": example("points")},
                    },
                    "batch": {
                        "summary": "Several shapes, all or nothing",
                        "value": {"shapes": example("batch")},
                    },
                },
            },
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["files"],
                    "properties": {
                        "files": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                            **bounds(maxItems="max_batch_files"),
                            "description": "JSON, CSV/TXT, NPY, PNG or JPEG files, 1 to "
                            "{max_batch_files} (setting max_batch_files); the file name "
                            "(without extension) becomes the shape name.",
                        },
                        "mode": {
                            "type": "string",
                            "enum": ["contour", "edges", "skeleton"],
                            "default": "contour",
                        },
                        "target_points": {
                            "type": "integer",
                            **_TARGET_POINTS_BOUNDS,
                            "description": _TARGET_POINTS_DOC,
                        },
                    },
                }
            },
            "text/csv": {"schema": {"type": "string"}, "example": example("csv")},
            "text/plain": {"schema": {"type": "string"}, "example": example("text")},
            "application/octet-stream": {
                "schema": {"type": "string", "format": "binary"},
                "description": "A `.npy` file holding an (n, 2) numeric array.",
            },
            "image/png": {
                "schema": {"type": "string", "format": "binary"},
                "description": "At most {max_image_pixels} pixels (setting max_image_pixels).",
            },
            "image/jpeg": {
                "schema": {"type": "string", "format": "binary"},
                "description": "At most {max_image_pixels} pixels (setting max_image_pixels).",
            },
        },
    }
}


def _limits(settings: Settings) -> ingest.Limits:
    return ingest.Limits(
        min_points=settings.min_points,
        max_points=settings.max_points_per_shape,
        max_coordinate=settings.max_coordinate,
        max_image_pixels=settings.max_image_pixels,
    )


def _invalid(detail: str, *, extra: dict[str, Any] | None = None) -> ProblemError:
    return ProblemError(
        422, detail, type_="/problems/invalid-shape", title="Invalid shape", extra=extra
    )


def _stem(filename: str | None) -> str | None:
    """A file's name without folders and extension (None if nothing is left)."""
    if not filename:
        return None
    base = filename.replace("\x00", "").replace("\\", "/").rsplit("/", 1)[-1]
    stem = base.rsplit(".", 1)[0] if "." in base else base
    return stem[:300] or None


def _parse_target_points(raw: str | None) -> int | None:
    if raw is None or raw == "":
        return None
    try:
        return int(raw)
    except ValueError as e:
        raise _invalid(f"target_points must be an integer; got {raw[:40]!r}") from e


def _check_target_points(target: int | None, limits: ingest.Limits) -> int | None:
    """The configured bounds, for every upload form (the schema states them too)."""
    if target is not None and not limits.min_points <= target <= limits.max_points:
        raise _invalid(
            f"target_points must be an integer between {limits.min_points} and "
            f"{limits.max_points} (settings min_points and max_points_per_shape); got {target}"
        )
    return target


def _parse_mode(raw: str | None) -> ImageMode:
    mode = raw or "contour"
    if mode not in ("contour", "edges", "skeleton"):
        raise _invalid(f"mode must be one of contour, edges, skeleton; got {mode[:40]!r}")
    return mode  # type: ignore[return-value]


def _too_many_files(count: str, max_batch_files: int, what: str = "files") -> ProblemError:
    return _invalid(
        f"{count} {what} in one upload; at most {max_batch_files} are allowed "
        "(setting max_batch_files)"
    )


def _decode_json_body(
    body: bytes, limits: ingest.Limits, max_batch_files: int
) -> tuple[list[NewShape], bool]:
    """Shapes from a JSON body, and whether it was a batch."""
    try:
        obj = json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
        raise _invalid(f"invalid JSON body: {e}") from e
    if isinstance(obj, dict) and "shapes" in obj:
        items = obj["shapes"]
        if not isinstance(items, list) or not items:
            raise _invalid('"shapes" must be a non-empty array of {"name", "points"} objects')
        if len(items) > max_batch_files:
            raise _too_many_files(str(len(items)), max_batch_files, "shapes")
        batch = True
    else:
        items = [obj]
        batch = False
    decoded: list[NewShape] = []
    invalid: list[dict[str, Any]] = []
    for i, item in enumerate(items):
        label = f"shapes[{i}]" if batch else "body"
        try:
            decoded.append(_json_shape(item, label, limits))
        except ingest.IngestError as e:
            invalid.append({"shape": label, "index": i, "detail": str(e)})
    if invalid and not batch:
        raise _invalid(f"body: {invalid[0]['detail']}")
    if invalid:
        raise _invalid_batch(invalid, len(items), "shape")
    return decoded, batch


def _json_shape(item: Any, label: str, limits: ingest.Limits) -> NewShape:
    """One shape of a JSON body (`label`: where it is, for its name when it has none)."""
    if not isinstance(item, dict):
        raise ingest.IngestError('expected an object {"name": ..., "points": [[x, y], ...]}')
    name = item.get("name")
    if name is not None and (not isinstance(name, str) or not 0 < len(name) <= 300):
        raise ingest.IngestError("name must be a string of 1 to 300 characters")
    if name is not None and "\x00" in name:
        raise ingest.IngestError("name must not contain NUL characters")
    points = ingest.points_from_json(item, limits=limits)
    return NewShape(name or content_name(points), "json", points, label)


def _invalid_batch(invalid: list[dict[str, Any]], total: int, what: str) -> ProblemError:
    """The 422 for a batch some of whose `what`s (``file`` or ``shape``) are invalid: the
    detail names the first and counts the others; ``invalid`` lists every one (its
    ``what``, ``index`` and ``detail``), so that a folder is fixed in one go. The first's
    ``what`` and ``index`` are also top-level members, as for a batch with one invalid."""
    first = invalid[0]
    detail = f"{first[what]}: {first['detail']}"
    if len(invalid) > 1:
        detail += f"; {len(invalid) - 1} more of the {total} {what}s are invalid too"
    return _invalid(detail, extra={what: first[what], "index": first["index"],
                                   "invalid": invalid})


def _decode_files(
    files: list[tuple[str | None, str | None, bytes]],
    mode: ImageMode,
    target_points: int | None,
    limits: ingest.Limits,
) -> list[NewShape]:
    decoded: list[NewShape] = []
    invalid: list[dict[str, Any]] = []
    for i, (filename, content_type, data) in enumerate(files):
        label = filename or f"file {i}"
        try:
            upload = ingest.decode_upload(
                data,
                filename=filename,
                content_type=content_type,
                mode=mode,
                target_points=target_points,
                limits=limits,
            )
        except ingest.IngestError as e:
            invalid.append({"file": label, "index": i, "detail": str(e)})
            continue
        name = _stem(filename) or content_name(upload.points)
        decoded.append(NewShape(name, upload.source_format, upload.points, label))
    if invalid:
        raise _invalid_batch(invalid, len(files), "file")
    return decoded


def shape_out(shape: Shape) -> ShapeOut:
    return ShapeOut.model_validate(
        {
            "id": shape.id,
            "collection_id": shape.collection_id,
            "name": shape.name,
            "source_format": shape.source_format,
            "n_points": shape.n_points,
            "bbox": {
                "min_x": shape.min_x,
                "min_y": shape.min_y,
                "max_x": shape.max_x,
                "max_y": shape.max_y,
            },
            "created_at": shape.created_at,
        }
    )


def _refused(e: Exception) -> ProblemError:
    """The problem document for an upload or delete that :mod:`shape_store` refused."""
    if isinstance(e, shape_store.NameConflict):
        existing = [{"id": sid, "name": name} for sid, name in e.existing]
        return ProblemError(
            409, str(e), type_=ProblemType.NAME_CONFLICT, extra={"existing": existing}
        )
    if isinstance(e, shape_store.DuplicateNames):
        return ProblemError(
            422,
            str(e),
            type_=ProblemType.DUPLICATE_NAMES,
            extra={"name": e.name, "files": e.labels},
        )
    if isinstance(e, shape_store.ShapesInUse):
        return ProblemError(
            409, str(e), type_="/problems/shape-in-use", extra={"shape_ids": list(e.using)}
        )
    return ProblemError(422, str(e), type_="/problems/collection-full")


@asynccontextmanager
async def _form(request: Request, max_batch_files: int) -> AsyncIterator[FormData]:
    """The multipart form, with at most ``max_batch_files`` files.

    The parser stops at the first file past the limit; Starlette would answer that with a
    400 naming its own count, so it is the same 422 as any other upload past the limit.
    """
    try:
        form = await request.form(max_files=max_batch_files, max_fields=100)
    except StarletteHTTPException as e:
        if e.status_code == 400 and str(e.detail).startswith("Too many files"):
            raise _too_many_files(f"more than {max_batch_files}", max_batch_files) from e
        raise
    try:
        yield form
    finally:
        await form.close()


@operation(
    router.post, "", "Upload one shape or a batch", (401, 404, 409, 413, 415, 422),
    status_code=status.HTTP_201_CREATED, response_model=ShapeOut | ShapeBatchOut,
    openapi_extra=_UPLOAD_OPENAPI,
    description=_UPLOAD_DOC + _LIMITS_DOC,
)
async def upload_shapes(
    collection_id: DbId,
    request: Request,
    response: Response,
    db: DbDep,
    settings: SettingsDep,
    idempotency_key: IdempotencyKeyDep = None,
    name: Annotated[
        str | None,
        Query(
            max_length=300,
            pattern=NO_NUL,
            description="Name of a raw upload (default: shape- and 12 hex digits of the "
            "SHA-256 of its points).",
        ),
    ] = None,
    mode: Annotated[ImageMode | None, Query(description="Image mode of a raw upload.")] = None,
    target_points: Annotated[
        int | None,
        Query(
            description=_TARGET_POINTS_DOC,
            json_schema_extra=_TARGET_POINTS_BOUNDS,
        ),
    ] = None,
    on_conflict: Annotated[
        OnConflict,
        Query(
            description="When the collection already holds a shape of an uploaded name: "
            "refuse (409 naming it, nothing stored), replace (delete it, store the new "
            "shape under a new id) or keep (store both, the name repeated)."
        ),
    ] = "refuse",
) -> ShapeOut | ShapeBatchOut:
    content_type = request.headers.get("content-type", "")
    media_type = content_type.split(";", 1)[0].strip().lower()
    limits = _limits(settings)
    target_points = _check_target_points(target_points, limits)
    scope = f"POST {request.url.path}"
    batch: bool

    if media_type == "application/json" or media_type.endswith("+json"):
        body = await request.body()
        request_hash = idempotency.hash_bytes(b"json", on_conflict.encode(), body)
        decoded, batch = await run_in_threadpool(
            _decode_json_body, body, limits, settings.max_batch_files
        )
    elif media_type == "multipart/form-data":
        async with _form(request, settings.max_batch_files) as form:
            uploads = [
                f
                for key in ("files", "file")
                for f in form.getlist(key)
                if isinstance(f, UploadFile)
            ]
            if not uploads:
                raise _invalid('multipart upload has no file in the "files" field')
            if len(uploads) > settings.max_batch_files:
                raise _too_many_files(str(len(uploads)), settings.max_batch_files)
            form_mode = form.get("mode")
            form_target = form.get("target_points")
            files = [(u.filename, u.content_type, await u.read()) for u in uploads]
        image_mode = _parse_mode(form_mode if isinstance(form_mode, str) else mode)
        target = _parse_target_points(form_target if isinstance(form_target, str) else None)
        target = _check_target_points(target, limits) if target is not None else target_points
        request_hash = idempotency.hash_bytes(
            b"multipart",
            on_conflict.encode(),
            image_mode.encode(),
            str(target).encode(),
            *[part for f in files for part in ((f[0] or "").encode(), f[2])],
        )
        decoded = await run_in_threadpool(_decode_files, files, image_mode, target, limits)
        batch = True
    elif media_type in RAW_TYPES:
        body = await request.body()
        image_mode = mode or "contour"
        ext = RAW_TYPES[media_type]
        filename = f"{name or 'shape'}.{ext}"
        request_hash = idempotency.hash_bytes(
            b"raw",
            on_conflict.encode(),
            media_type.encode(),
            (name or "").encode(),
            image_mode.encode(),
            str(target_points).encode(),
            body,
        )
        decoded = await run_in_threadpool(
            _decode_files, [(filename, media_type, body)], image_mode, target_points, limits
        )
        decoded[0].name = name or content_name(decoded[0].points)
        batch = False
    else:
        raise ProblemError(
            415,
            f"unsupported content type {media_type or '(none)'!r}; send application/json, "
            "multipart/form-data, text/csv, text/plain, application/octet-stream (.npy), "
            "image/png or image/jpeg",
            type_="/problems/unsupported-media-type",
        )

    try:
        rows = await run_in_threadpool(
            lambda: (
                shape_store.add_shapes(
                    db,
                    collection_id,
                    decoded,
                    on_conflict=on_conflict,
                    max_shapes=settings.max_shapes_per_collection,
                    scope=scope,
                    key=idempotency_key,
                    request_hash=request_hash,
                ).shapes
            )
        )
    except (
        shape_store.NameConflict,
        shape_store.DuplicateNames,
        shape_store.ShapesInUse,
        shape_store.CollectionFull,
    ) as e:
        raise _refused(e) from e
    stored = [shape_out(r) for r in rows]
    if batch:
        return ShapeBatchOut(items=stored, count=len(stored))
    response.headers["Location"] = f"/v1/collections/{collection_id}/shapes/{stored[0].id}"
    return stored[0]


@operation(
    router.get, "", "List a collection's shapes (metadata only)", (404,),
    response_model=Page[ShapeOut],
)
def list_shapes(collection_id: DbId, db: DbDep, page: PaginationDep) -> Page[ShapeOut]:
    """The collection's shapes in upload order, one page at a time: id, name, source
    format, number of points and bounding box, without the points (read a shape for those)."""
    with db.read() as session:
        get_collection_or_404(session, collection_id)
        total = shape_store.count_shapes(session, collection_id)
        shapes = shape_store.list_shapes(session, collection_id, page.limit, page.offset)
        items = [shape_out(s) for s in shapes]
    return Page[ShapeOut](items=items, total=total, limit=page.limit, offset=page.offset)


@operation(
    router.get, "/{shape_id}", "Read a shape with its points", (404,),
    response_model=ShapeDetail,
)
def get_shape(collection_id: DbId, shape_id: DbId, db: DbDep) -> ShapeDetail:
    """The shape's metadata and its points as stored: (x, y) pairs in the units they were
    uploaded in (an image's pixels, y down)."""
    with db.read() as session:
        shape = shape_store.get_shape(session, collection_id, shape_id)
        if shape is None:
            raise not_found(f"shape {shape_id} in collection", collection_id)
        out = shape_out(shape)
        return ShapeDetail(**out.model_dump(), points=[tuple(p) for p in shape.points.tolist()])


@operation(
    router.delete, "/{shape_id}", "Delete a shape", (404, 409),
    status_code=status.HTTP_204_NO_CONTENT,
)
def delete_shape(collection_id: DbId, shape_id: DbId, db: DbDep) -> Response:
    """Deletes the shape: 204 with no body. A shape that a queued or running job uses is
    kept (409 naming the jobs); finished jobs keep their results."""
    try:
        deleted = shape_store.delete_shape(db, collection_id, shape_id)
    except shape_store.ShapesInUse as e:
        raise _refused(e) from e
    if not deleted:
        raise not_found(f"shape {shape_id} in collection", collection_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)

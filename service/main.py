"""The FastAPI application factory."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import APIRouter, FastAPI
from fastapi.openapi.utils import get_openapi
from sqlalchemy import text

from service import __version__
from service.api.middleware import (
    PUBLIC_PATHS,
    ApiKeyMiddleware,
    BodyLimitMiddleware,
    RequestLogMiddleware,
)
from service.api.problems import Problem, ProblemError, install_problem_handlers
from service.api.problems import operation as documented
from service.api.routes import (
    collections,
    deliveries,
    exports,
    grouping,
    jobs,
    pages,
    pictures,
    results,
    shapes,
)
from service.api.routes.docs import install_docs
from service.contract.names import ProblemType
from service.core.config import Settings, get_settings
from service.core.limits import limits_description, resolve_limits
from service.db import Database
from service.schemas import ShapeBatchJSON, ShapeJSON

DESCRIPTION = """
Register a model shape onto every shape of a collection, across large shape differences, by
chaining registrations through similar shapes (Du et al. 2016, dynamic tree).

1. `POST /v1/collections`, then upload shapes to `/v1/collections/{id}/shapes` (JSON,
   CSV/TXT, NPY, PNG/JPEG; one or many files).
2. `POST /v1/jobs` with the model shape: 202 and a `Location` to poll.
3. When the job has `succeeded`, read `/v1/jobs/{id}/result` and, per shape,
   `/v1/jobs/{id}/result/subjects/{shape_id}`.
4. Look at it: the results page at `/ui`, or the pictures `/v1/jobs/{id}/result/tree.svg`,
   `summary.png` and `subjects/{shape_id}/overlay.png`.

Every error is an RFC 9457 `application/problem+json` document. When the service has an API
key, send it as `X-API-Key` or `Authorization: Bearer`; `/healthz` and the API docs are open.
"""

TAGS = [
    {"name": "collections", "description": "Named sets of shapes."},
    {"name": "shapes", "description": "Upload and read shapes (point sets)."},
    {"name": "jobs", "description": "Registration jobs, their progress and results."},
    {"name": "pictures", "description": "PNG/SVG pictures of a result: tree, summary, overlays."},
    {"name": "health", "description": "Liveness."},
]


def create_app(settings: Settings | None = None, *, db: Database | None = None) -> FastAPI:
    """Build the app. The database schema must exist (``regtree migrate``)."""
    settings = settings or get_settings()
    database = db or Database(
        settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        if db is None:
            database.dispose()

    app = FastAPI(
        title="regtree",
        version=__version__,
        description=DESCRIPTION + limits_description(),
        openapi_tags=TAGS,
        lifespan=lifespan,
        docs_url=None,  # served from the package by install_docs, not from a CDN
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.db = database

    install_problem_handlers(app)
    # Added innermost first: the request log wraps everything, then the key check, then
    # the body limit.
    app.add_middleware(BodyLimitMiddleware, max_body_bytes=settings.max_body_bytes)
    if settings.api_key is not None and settings.api_key.get_secret_value():
        app.add_middleware(ApiKeyMiddleware, api_key=settings.api_key.get_secret_value())
    app.add_middleware(RequestLogMiddleware)

    v1 = APIRouter(prefix="/v1")
    v1.include_router(collections.router)
    v1.include_router(shapes.router)
    v1.include_router(jobs.router)
    v1.include_router(results.router)
    v1.include_router(exports.router)
    v1.include_router(deliveries.router)
    v1.include_router(pictures.router)
    v1.include_router(grouping.router)
    app.include_router(v1)
    app.include_router(pages.router)  # the results page at /ui
    install_docs(app)  # /docs and /redoc

    @documented(app.get, "/healthz", "Liveness and database check", (503,), tags=["health"])
    def healthz() -> dict[str, str]:
        """`{"status": "ok"}` when the service runs and its database answers; 503 otherwise.
        Open without an API key."""
        try:
            with database.read() as session:
                session.execute(text("SELECT 1"))
        except Exception as e:
            raise ProblemError(503, "database unavailable", type_=ProblemType.UNAVAILABLE) from e
        return {"status": "ok"}

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(
            title=app.title,
            version=app.version,
            description=app.description,
            routes=app.routes,
            tags=app.openapi_tags,
        )
        components = schema.setdefault("components", {})
        schemas = components.setdefault("schemas", {})
        for model in (Problem, ShapeJSON, ShapeBatchJSON):
            model_schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
            for name, sub in model_schema.pop("$defs", {}).items():
                schemas.setdefault(name, sub)
            schemas.setdefault(model.__name__, model_schema)
        _document_errors_as_problems(schema)
        _markdown_descriptions(schema)
        # The limits the document states are this app's settings, as enforced.
        schema = resolve_limits(schema, settings)
        components = schema["components"]
        components["securitySchemes"] = {
            "ApiKeyHeader": {"type": "apiKey", "in": "header", "name": "X-API-Key"},
            "Bearer": {"type": "http", "scheme": "bearer"},
        }
        if settings.api_key is not None:
            for path, item in schema.get("paths", {}).items():
                if path in PUBLIC_PATHS:
                    continue
                for operation in item.values():
                    if isinstance(operation, dict):
                        operation["security"] = [{"ApiKeyHeader": []}, {"Bearer": []}]
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app


_PROBLEM_CONTENT = {
    "application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}
}


#: The 422 of an operation that takes JSON: what it covers, as the service answers it.
MALFORMED_JSON_422 = (
    "Unprocessable Content: a parameter or the body is invalid, and so is a body that is not "
    "valid JSON (a syntax error, bytes that are not UTF-8, nesting too deep)."
)
#: The 400 of an operation that takes multipart/form-data (Starlette's parser refuses it).
MALFORMED_MULTIPART_400 = (
    "Bad Request: the multipart/form-data body cannot be parsed (no boundary, or malformed)."
)


#: reStructuredText inline markup of docstrings: a role (``:func:`x```, ``:class:`~a.b```,
#: ``:ref:`text <target>```) or a double-backquoted literal.
_RST_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:`~?(?:([^`<]*?)\s*<[^`>]*>|([^`]*))`")
_RST_LITERAL = re.compile(r"``(.+?)``", re.DOTALL)


def rst_to_markdown(text: str) -> str:
    """Docstring markup as /docs and ReDoc render it (Markdown): roles and ``x`` become `x`."""

    def role(match: re.Match[str]) -> str:
        shown = match.group(1) or match.group(2)
        if match.group(0).split("`", 1)[1].startswith("~"):
            shown = shown.rsplit(".", 1)[-1]
        return f"`{shown}`"

    return _RST_LITERAL.sub(r"`\1`", _RST_ROLE.sub(role, text))


def _markdown_descriptions(node: Any) -> None:
    """Every description in the document in Markdown: docstrings (routes, models) are reST."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "description" and isinstance(value, str):
                node[key] = rst_to_markdown(value)
            else:
                _markdown_descriptions(value)
    elif isinstance(node, list):
        for value in node:
            _markdown_descriptions(value)


def _document_errors_as_problems(schema: dict[str, Any]) -> None:
    """Make the schema say what the service sends: every error is a problem document.

    FastAPI documents its automatic 422 as ``application/json`` ``HTTPValidationError``,
    while the validation handler answers ``application/problem+json``. A JSON body that
    cannot be read is a 422 (``service.api.problems``), a multipart body that cannot be
    parsed a 400; each operation documents the one its body types can get.
    """
    for item in schema.get("paths", {}).values():
        for operation in item.values():
            if not isinstance(operation, dict):
                continue
            responses = operation.setdefault("responses", {})
            if "422" in responses:
                responses["422"]["content"] = dict(_PROBLEM_CONTENT)
            body_types = set(operation.get("requestBody", {}).get("content", {}))
            if "application/json" in body_types:
                responses["422"] = {
                    "description": MALFORMED_JSON_422,
                    "content": dict(_PROBLEM_CONTENT),
                }
            if "multipart/form-data" in body_types:
                responses["400"] = {
                    "description": MALFORMED_MULTIPART_400,
                    "content": dict(_PROBLEM_CONTENT),
                }
            if "requestBody" in operation:
                # BodyLimitMiddleware refuses any body past the limit, on every operation.
                responses["413"] = {
                    "description": "The request body is larger than {max_body_bytes} bytes "
                    "(setting max_body_bytes).",
                    "content": dict(_PROBLEM_CONTENT),
                }
    component_schemas = schema.get("components", {}).get("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):
        component_schemas.pop(name, None)

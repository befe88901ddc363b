"""FastAPI dependencies, as ``Annotated`` aliases for route signatures."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Header, Query, Request
from fastapi.exceptions import RequestValidationError

from service.core.config import Settings
from service.core.limits import DEFAULT_PAGE_SIZE, bounds, default_page_size
from service.db import Database
from service.schemas import INT64_MAX


def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def get_db(request: Request) -> Database:
    db: Database = request.app.state.db
    return db


SettingsDep = Annotated[Settings, Depends(get_settings)]
DbDep = Annotated[Database, Depends(get_db)]


@dataclass(frozen=True)
class Pagination:
    limit: int
    offset: int


def get_pagination(
    request: Request,
    settings: SettingsDep,
    limit: Annotated[
        int,
        Query(
            ge=1,
            description="Page size: 1 to {max_page_size} (setting max_page_size); "
            "{default_page_size} when not given.",
            json_schema_extra=bounds(maximum="max_page_size", default="default_page_size"),
        ),
    ] = DEFAULT_PAGE_SIZE,
    offset: Annotated[int, Query(ge=0, le=INT64_MAX, description="Items to skip.")] = 0,
) -> Pagination:
    """The page a list asks for; ``limit`` is bounded by the setting ``max_page_size``."""
    if "limit" not in request.query_params:
        limit = default_page_size(settings)
    elif limit > settings.max_page_size:
        # The same 422 as a bound in the signature would give (that bound is the setting's,
        # so it is checked here, and the schema states it: service.core.limits).
        raise RequestValidationError(
            [
                {
                    "type": "less_than_equal",
                    "loc": ("query", "limit"),
                    "msg": f"Input should be less than or equal to {settings.max_page_size} "
                    "(setting max_page_size)",
                    "input": limit,
                    "ctx": {"le": settings.max_page_size},
                }
            ]
        )
    return Pagination(limit=limit, offset=offset)


PaginationDep = Annotated[Pagination, Depends(get_pagination)]

IdempotencyKeyDep = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        min_length=1,
        max_length=255,
        description="Repeat a POST safely: the same key with the same body returns the "
        "resource the first request created; with a different body, 422.",
    ),
]

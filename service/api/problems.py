"""RFC 9457 problem details (``application/problem+json``) for every error the API returns.

Handlers are installed for :class:`ProblemError` (raised by our own code), Starlette's
``HTTPException`` (404 for unknown paths, 405, 400 for a multipart body that cannot be parsed),
request validation errors (422, a JSON body that cannot be read included) and any unexpected
exception (500, without internals in the body).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.types import DecoratedCallable
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.contract.names import ProblemType

PROBLEM_MEDIA_TYPE = "application/problem+json"

logger = logging.getLogger("regtree.api")


class Problem(BaseModel):
    """An RFC 9457 problem details document."""

    type: str = Field(default="about:blank", examples=["/problems/validation-error"])
    title: str = Field(examples=["Unprocessable Content"])
    status: int = Field(examples=[422])
    detail: str | None = Field(default=None, examples=["points must have shape (n, 2)"])
    instance: str | None = Field(default=None, examples=["/v1/collections/1/shapes"])
    errors: list[dict[str, Any]] | None = Field(
        default=None, description="Field-level validation errors, when there are any."
    )


def _title(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


class ProblemError(Exception):
    """Raise to answer with a problem document."""

    def __init__(
        self,
        status: int,
        detail: str | None = None,
        *,
        type_: str = "about:blank",
        title: str | None = None,
        headers: dict[str, str] | None = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(detail or _title(status))
        self.status = status
        self.detail = detail
        self.type = type_
        self.title = title or _title(status)
        self.headers = headers
        self.extra = extra or {}

    def response(self, request: Request | None) -> JSONResponse:
        """The problem document answering ``request``."""
        body: dict[str, Any] = {
            "type": self.type,
            "title": self.title,
            "status": self.status,
            "detail": self.detail,
            "instance": request.url.path if request is not None else None,
            **self.extra,
        }
        return JSONResponse(
            jsonable_encoder(body),
            status_code=self.status,
            headers=self.headers,
            media_type=PROBLEM_MEDIA_TYPE,
        )


class BodyTooLarge(StarletteHTTPException):
    """Raised while a request body is read once it passes the configured limit.

    A subclass of ``HTTPException`` so that FastAPI's body parsing passes it through
    unchanged instead of turning it into a generic 400.
    """

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body larger than the limit of {limit} bytes")
        self.limit = limit


async def _problem_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ProblemError)
    return exc.response(request)


def _unreadable_json(exc: StarletteHTTPException) -> str | None:
    """Why a JSON body could not be read, when FastAPI's bare 400 hides that it is JSON's fault.

    FastAPI answers a body that ``json.loads`` refuses with a ``JSONDecodeError`` as a 422
    (``json_invalid``), but bytes that are not UTF-8 (``UnicodeDecodeError``) or nesting past
    the parser's depth (``RecursionError``) as "400 There was an error parsing the body".
    Both are the same mistake, so both get the same 422.
    """
    cause = exc.__cause__
    if exc.status_code != 400:
        return None
    if isinstance(cause, UnicodeDecodeError):
        return f"not UTF-8 text ({cause.reason} at byte {cause.start})"
    if isinstance(cause, RecursionError):
        return "nested too deeply"
    return None


async def _http_exception_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    reason = _unreadable_json(exc)
    if reason is not None:
        error = {"loc": ["body"], "msg": "JSON decode error", "type": "json_invalid"}
        return _validation_problem(request, [{**error, "ctx": {"error": reason}}])
    detail = exc.detail if isinstance(exc.detail, str) else None
    type_ = ProblemType.BODY_TOO_LARGE if exc.status_code == 413 else "about:blank"
    if exc.status_code == 404 and detail == "Not Found":
        detail = f"no route for {request.method} {request.url.path}"
    if exc.status_code == 405:
        detail = f"method {request.method} not allowed on {request.url.path}"
    headers = getattr(exc, "headers", None)
    return ProblemError(exc.status_code, detail, type_=type_, headers=headers).response(request)


def _clean_error(error: dict[str, Any]) -> dict[str, Any]:
    cleaned = {
        "loc": list(error.get("loc", ())),
        "msg": error.get("msg"),
        "type": error.get("type"),
    }
    ctx = error.get("ctx")
    if ctx:
        cleaned["ctx"] = {k: str(v) for k, v in ctx.items()}
    return cleaned


async def _validation_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return _validation_problem(request, [_clean_error(e) for e in exc.errors()])


def _validation_problem(request: Request, errors: list[dict[str, Any]]) -> JSONResponse:
    """The 422 of request validation; its detail is the first error's."""
    first = errors[0] if errors else None
    detail = "request validation failed"
    if first is not None and first["type"] == "json_invalid":
        loc = first["loc"]
        at = f" at character {loc[1]}" if len(loc) > 1 else ""
        detail = f"the request body is not valid JSON: {first.get('ctx', {}).get('error')}{at}"
    elif first is not None:
        where = ".".join(str(part) for part in first["loc"])
        detail = f"{where}: {first['msg']}" if where else str(first["msg"])
    return ProblemError(
        422,
        detail,
        type_=ProblemType.VALIDATION_ERROR,
        title="Request validation failed",
        extra={"errors": errors},
    ).response(request)


async def _unexpected_handler(request: Request, exc: Exception) -> JSONResponse:
    logger.error(
        "unhandled error",
        exc_info=exc,
        extra={"method": request.method, "path": request.url.path},
    )
    return ProblemError(
        500, "internal error; the server log has the details", type_=ProblemType.INTERNAL
    ).response(request)


def install_problem_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ProblemError, _problem_error_handler)
    app.add_exception_handler(StarletteHTTPException, _http_exception_handler)
    app.add_exception_handler(RequestValidationError, _validation_handler)
    app.add_exception_handler(Exception, _unexpected_handler)


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries documenting problem documents for the given statuses."""
    return {
        status: {
            "model": Problem,
            "description": _title(status),
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
        for status in statuses
    }


def operation(
    verb: Callable[..., Callable[[DecoratedCallable], DecoratedCallable]],
    path: str,
    summary: str,
    problems: tuple[int, ...],
    description: str | None = None,
    **options: Any,
) -> Callable[[DecoratedCallable], DecoratedCallable]:
    """``verb(path, ...)`` (``router.get``, ``router.post``, ...) with its summary, Markdown
    description and the problem documents it may answer (:func:`problem_responses`, after the
    operation's own ``responses``, if any); the other ``options`` (``response_model``,
    ``status_code``, ...) go to FastAPI as they are."""
    responses = {**options.pop("responses", {}), **problem_responses(*problems)}
    return verb(path, summary=summary, description=description, responses=responses, **options)


def not_found(what: str, ident: object) -> ProblemError:
    return ProblemError(404, f"{what} {ident} not found", type_=ProblemType.NOT_FOUND)

"""Pure-ASGI middleware: request ids and logs, API-key check, request body size limit."""

from __future__ import annotations

import hmac
import logging
import time
import uuid

from starlette.datastructures import Headers
from starlette.requests import Request
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.problems import BodyTooLarge, ProblemError
from service.api.routes.docs import DOCS_PATHS
from service.api.routes.pages import PAGE_PATHS
from service.contract.names import ProblemType

logger = logging.getLogger("regtree.access")

#: Paths answered without an API key: liveness probes, the API documentation and its pages'
#: files (the schema describes the service, it holds no data) and the results page's files
#: (the page asks for the key and sends it with every API call).
PUBLIC_PATHS = frozenset({"/healthz", "/openapi.json", *DOCS_PATHS, *PAGE_PATHS})


#: The order methods are listed in an ``Allow`` header.
_METHOD_ORDER = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(app: object, scope: Scope) -> list[str]:
    """Every method that some route of ``app`` answers on the request's path.

    Starlette answers a 405 from the first route whose path matched, so its ``Allow`` header
    names that route's methods only, though FastAPI gives each method of a path a route of
    its own (``POST /v1/collections`` and ``GET /v1/collections``). Each method is asked of
    the app's routes as if the request had used it (``BaseRoute.matches``), which also sees
    the routes of included routers.
    """
    routes = getattr(app, "routes", ())
    return [
        method
        for method in _METHOD_ORDER
        if any(route.matches({**scope, "method": method})[0] is Match.FULL for route in routes)
    ]


class RequestLogMiddleware:
    """Give every request an ``X-Request-ID`` and log one JSON line when it ends.

    As the outermost layer it also completes a 405's ``Allow`` header with every method of
    the path (see :func:`allowed_methods`).
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = Headers(scope=scope).get("x-request-id") or uuid.uuid4().hex
        request_id = request_id[:100]
        scope.setdefault("state", {})["request_id"] = request_id
        started = time.perf_counter()
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                headers = list(message.get("headers", []))
                headers.append((b"x-request-id", request_id.encode("latin-1")))
                if status == 405:
                    allow = allowed_methods(scope.get("app"), scope)
                    if allow:
                        headers = [(k, v) for k, v in headers if k.lower() != b"allow"]
                        headers.append((b"allow", ", ".join(allow).encode("latin-1")))
                message = {**message, "headers": headers}
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            logger.info(
                "request",
                extra={
                    "method": scope.get("method"),
                    "path": scope.get("path"),
                    "status": status,
                    "duration_ms": round((time.perf_counter() - started) * 1000, 2),
                    "request_id": request_id,
                },
            )


class ApiKeyMiddleware:
    """Answer 401 unless the request carries the key (``X-API-Key`` or ``Bearer``)."""

    def __init__(self, app: ASGIApp, api_key: str) -> None:
        self.app = app
        self.api_key = api_key.encode()

    def _authorised(self, headers: Headers) -> bool:
        candidates = []
        if "x-api-key" in headers:
            candidates.append(headers["x-api-key"])
        authorization = headers.get("authorization", "")
        scheme, _, token = authorization.partition(" ")
        if scheme.lower() == "bearer" and token:
            candidates.append(token.strip())
        return any(hmac.compare_digest(c.encode(), self.api_key) for c in candidates)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("path") in PUBLIC_PATHS:
            await self.app(scope, receive, send)
            return
        if not self._authorised(Headers(scope=scope)):
            response = ProblemError(
                401,
                "missing or wrong API key: send it as `X-API-Key: <key>` or "
                "`Authorization: Bearer <key>`",
                type_=ProblemType.UNAUTHORIZED,
                headers={"WWW-Authenticate": 'Bearer realm="regtree"'},
            ).response(Request(scope))
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)


class BodyLimitMiddleware:
    """Refuse request bodies over ``max_body_bytes`` with 413.

    A declared ``Content-Length`` over the limit is refused before reading anything; a body
    without one (chunked) is counted while it streams in, and reading it raises
    :class:`BodyTooLarge` as soon as it passes the limit.
    """

    def __init__(self, app: ASGIApp, max_body_bytes: int) -> None:
        self.app = app
        self.limit = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None:
            try:
                too_large = int(declared) > self.limit
            except ValueError:
                too_large = False
            if too_large:
                response = ProblemError(
                    413,
                    f"request body of {declared} bytes is larger than the limit of "
                    f"{self.limit} bytes",
                    type_=ProblemType.BODY_TOO_LARGE,
                    headers={"Connection": "close"},
                ).response(Request(scope))
                await response(scope, receive, send)
                return

        received = 0

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise BodyTooLarge(self.limit)
            return message

        await self.app(scope, counting_receive, send)

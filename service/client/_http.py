"""The client's HTTP plumbing: one ``httpx.Client``, retries, errors, paging."""

from __future__ import annotations

import time
from collections.abc import Iterator
from types import TracebackType
from typing import Any, Self

import httpx

from service.client.errors import (
    RegtreeConnectionError,
    RegtreeError,
    RegtreeTimeout,
    ValidationError,
    _page_size_limit,
)
from service.core.collector import paused

try:  # the server's JSON library, when installed (several times the standard library's speed)
    import orjson as _orjson
except ImportError:  # pragma: no cover - the client extra alone
    _orjson = None  # type: ignore[assignment]

_RETRY_STATUSES = frozenset({502, 503, 504})


class HttpClient:
    """Synchronous client for one regtree service.

    Parameters
    ----------
    base_url : str
        E.g. ``"http://127.0.0.1:8000"`` (without ``/v1``).
    api_key : str, optional
        Sent as ``X-API-Key`` when the service requires a key.
    timeout : float
        Seconds per HTTP request (uploads of large batches may need more).
    retries : int
        How often to retry a request that could not connect, or a GET / idempotent POST
        answered 502/503/504 or cut off; 0 disables retries.
    transport : httpx.BaseTransport, optional
        For tests (e.g. ``httpx.MockTransport``).
    """

    def __init__(
        self,
        base_url: str,
        *,
        api_key: str | None = None,
        timeout: float = 60.0,
        retries: int = 2,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        headers = {"Accept": "application/json", "User-Agent": "regtree-client/0.1"}
        if api_key:
            headers["X-API-Key"] = api_key
        self.base_url = base_url.rstrip("/")
        self.retries = max(0, retries)
        self._http = httpx.Client(
            base_url=self.base_url, headers=headers, timeout=timeout, transport=transport
        )

    @classmethod
    def from_env(cls, base_url: str | None = None, **kwargs: Any) -> Self:
        """A client for ``base_url``, else ``$REGTREE_URL`` (default
        ``http://127.0.0.1:8000``), with the key in ``$REGTREE_API_KEY`` if set (the variable
        the server reads its key from)."""
        import os

        url = base_url or os.environ.get("REGTREE_URL") or "http://127.0.0.1:8000"
        kwargs.setdefault("api_key", os.environ.get("REGTREE_API_KEY") or None)
        return cls(url, **kwargs)

    # --- plumbing ----------------------------------------------------------------------

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _request(
        self,
        method: str,
        path: str,
        *,
        retry: bool,
        idempotency_key: str | None = None,
        **kwargs: Any,
    ) -> httpx.Response:
        """Send a request; raise the matching :class:`RegtreeError` unless it is 2xx.

        ``retry``: whether the request may be repeated after a reply was possibly processed
        (read errors, 502/503/504). Connection failures are always retried: the request
        never reached the server.
        """
        headers = dict(kwargs.pop("headers", None) or {})
        if idempotency_key is not None:
            headers["Idempotency-Key"] = idempotency_key
        attempt = 0
        while True:
            try:
                response = self._http.request(method, path, headers=headers, **kwargs)
            except httpx.TransportError as e:
                failure, may_retry = self._transport_failure(method, path, e, retry)
                if not (may_retry and attempt < self.retries):
                    raise failure from e
            else:
                if response.is_success:
                    return response
                may_retry = retry and response.status_code in _RETRY_STATUSES
                if not (may_retry and attempt < self.retries):
                    raise RegtreeError.from_response(response)
            attempt += 1
            time.sleep(0.25 * 2**attempt)

    def _transport_failure(
        self, method: str, path: str, e: httpx.TransportError, retry: bool
    ) -> tuple[RegtreeError, bool]:
        """The error a transport failure raises, and whether the request may be sent again:
        always when it never reached the server (connect failures), with ``retry`` when a
        reply may have been processed (a broken connection); never after a read timeout."""
        if isinstance(e, httpx.TimeoutException):
            return RegtreeTimeout(
                f"{method} {path}: no answer within the timeout "
                f"({type(e).__name__}; raise RegtreeClient(timeout=...) for big uploads)"
            ), isinstance(e, httpx.ConnectTimeout)
        if isinstance(e, httpx.ConnectError):
            message = f"cannot reach the regtree service at {self.base_url}: {e}"
            return RegtreeConnectionError(message), True
        if isinstance(e, httpx.RemoteProtocolError | httpx.ReadError):
            message = f"{method} {path}: the connection to {self.base_url} broke: {e}"
            return RegtreeConnectionError(message), retry
        raise e

    def _get(self, path: str, **kwargs: Any) -> Any:
        return _json(self._request("GET", path, retry=True, **kwargs))

    def _paged(self, path: str, page_size: int = 500, **params: Any) -> Iterator[dict[str, Any]]:
        offset = 0
        while True:
            try:
                page = self._get(path, params={**params, "limit": page_size, "offset": offset})
            except ValidationError as e:
                smaller = _page_size_limit(e)
                if smaller is None or smaller >= page_size:
                    raise
                page_size = smaller  # the server's max_page_size is lower: ask for that
                continue
            items = page.get("items") or []
            yield from items
            offset += len(items)
            if not items or offset >= int(page.get("total", 0)):
                return


def _json(response: httpx.Response) -> Any:
    """A response's JSON, parsed with the collector paused (a full result is millions of
    lists and floats: 57 MB for the 73 full-resolution 永 glyphs), by orjson when it is
    installed, else by the standard library (also for what orjson refuses)."""
    with paused():
        if _orjson is not None:
            try:
                return _orjson.loads(response.content)
            except _orjson.JSONDecodeError:
                pass
        return response.json()

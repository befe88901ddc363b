"""The client's exceptions: the server's problem documents as typed errors."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

import httpx

if TYPE_CHECKING:
    from service.client.models import JobStatus, Shape



def _page_size_limit(error: RegtreeError) -> int | None:
    """The largest page size a 422 on ``?limit=`` allows (the server's ``max_page_size``)."""
    for item in error.errors or []:
        if not isinstance(item, dict) or list(item.get("loc") or []) != ["query", "limit"]:
            continue
        le = str((item.get("ctx") or {}).get("le", ""))
        return int(le) if le.isdigit() and int(le) >= 1 else None
    return None


class RegtreeError(Exception):
    """An error answer from the service, with its RFC 9457 problem document.

    Attributes
    ----------
    status : int or None
        HTTP status (None when no answer came: timeouts, connection failures).
    title, detail, type, instance : str or None
        The problem document's fields (``detail`` is the server's explanation).
    errors : list of dict or None
        Field-level validation errors, when the server sent them.
    problem : dict
        The whole problem document (``{}`` if the body was not JSON).
    """

    def __init__(
        self,
        message: str,
        *,
        status: int | None = None,
        title: str | None = None,
        detail: str | None = None,
        type: str | None = None,
        instance: str | None = None,
        errors: list[dict[str, Any]] | None = None,
        problem: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.title = title
        self.detail = detail
        self.type = type
        self.instance = instance
        self.errors = errors
        self.problem = problem or {}
        #: Shapes stored by earlier batches when an upload batch was refused.
        self.stored: list[Shape] = []

    @classmethod
    def from_response(cls, response: httpx.Response) -> RegtreeError:
        """The exception for an error response, of the subclass its status calls for."""
        problem: dict[str, Any] = {}
        try:
            body = response.json()
            if isinstance(body, dict):
                problem = body
        except (json.JSONDecodeError, UnicodeDecodeError, ValueError):
            pass
        status = response.status_code
        title = problem.get("title") or response.reason_phrase or "Error"
        detail = problem.get("detail")
        if detail is None and not problem:
            text = response.text.strip()
            detail = text[:500] if text else None
        request = response.request
        message = f"{status} {title}"
        if detail:
            message += f": {detail}"
        message += f" ({request.method} {request.url.path})"
        kind = _class_for_status(status)
        return kind(
            message,
            status=status,
            title=title,
            detail=detail,
            type=problem.get("type"),
            instance=problem.get("instance"),
            errors=problem.get("errors"),
            problem=problem,
        )


class NotFound(RegtreeError):
    """404: the collection, shape, job or subject does not exist."""


class Unauthorized(RegtreeError):
    """401: the API key is missing or wrong."""


class Conflict(RegtreeError):
    """409: e.g. the job is not finished (no result yet) or already finished (cancel)."""


class ValidationError(RegtreeError):
    """Any other 4xx: the request was refused as invalid (422, 413, 415, 400...)."""


class ServerError(RegtreeError):
    """5xx: the service failed; its log has the details."""


class RegtreeTimeout(RegtreeError, TimeoutError):
    """A request, or :meth:`RegtreeClient.wait`, ran out of time.

    ``last_status`` holds the job's last known :class:`JobStatus` when ``wait`` timed out.
    """

    def __init__(self, message: str, *, last_status: JobStatus | None = None) -> None:
        super().__init__(message)
        self.last_status = last_status


class RegtreeConnectionError(RegtreeError, ConnectionError):
    """The service could not be reached."""


class JobFailed(RegtreeError):
    """:meth:`RegtreeClient.wait` saw the job end ``failed`` or ``cancelled``."""

    def __init__(self, message: str, *, job: JobStatus) -> None:
        super().__init__(message, detail=job.error)
        self.job = job


def _class_for_status(status: int) -> type[RegtreeError]:
    if status == 404:
        return NotFound
    if status == 401:
        return Unauthorized
    if status == 409:
        return Conflict
    if 400 <= status < 500:
        return ValidationError
    if status >= 500:
        return ServerError
    return RegtreeError

"""A synchronous Python client for the regtree HTTP API (``/v1``).

::

    from service.client import RegtreeClient

    with RegtreeClient("http://127.0.0.1:8000", api_key=None) as rt:
        coll = rt.create_collection("yong", "永 from 73 fonts")
        shapes = rt.upload_folder(coll.id, "glyphs/", pattern="*.png", target_points=300)
        job = rt.start_job(coll.id, shapes[0].id, compare_direct=True)
        rt.wait(job.id, on_progress=lambda s: print(s.stage, s.done, s.total))
        result = rt.result(job.id, full=True)
        mapped = rt.apply_transform(job.id, shapes[5].id, [[0.0, 0.0], [1.0, 1.0]])

Every method returns typed, frozen dataclasses (:class:`Collection`, :class:`Shape`,
:class:`JobStatus`, :class:`JobResult`, :class:`Subject`); each keeps the server's JSON in
``raw`` so nothing the server sends is lost. Failures raise :class:`RegtreeError` carrying the
server's problem+json document (``status``, ``title``, ``detail``, ``type``), as one of
:class:`NotFound` (404), :class:`Unauthorized` (401), :class:`Conflict` (409),
:class:`ValidationError` (any other 4xx) or :class:`ServerError` (5xx); a request or a
:meth:`RegtreeClient.wait` that runs out of time raises :class:`RegtreeTimeout`, and a server
that cannot be reached :class:`RegtreeConnectionError`.

POSTs that create something (collections, shape batches, jobs) send an ``Idempotency-Key``
(generated unless given), so the client retries them safely after a connection failure or a
502/503/504; cancelling is never retried.
"""

from __future__ import annotations

import fnmatch
import json
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import httpx
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "POINT_SUFFIXES",
    "SUBJECT_SORTS",
    "UPLOAD_SUFFIXES",
    "Collection",
    "Conflict",
    "JobFailed",
    "JobResult",
    "JobStatus",
    "NotFound",
    "RegtreeClient",
    "RegtreeConnectionError",
    "RegtreeError",
    "RegtreeTimeout",
    "ServerError",
    "Shape",
    "Subject",
    "SubjectSort",
    "Unauthorized",
    "ValidationError",
]

FloatArray = NDArray[np.float64]
ImageMode = Literal["contour", "edges", "skeleton"]
Method = Literal["dynamic_tree", "static_tree", "direct"]
#: How the affine pre-alignment may pose a shape: see :meth:`RegtreeClient.start_job`.
Pose = Literal["as_given", "upright", "rotation", "affine"]
#: Orders of a result's subjects (``sort`` of :meth:`RegtreeClient.result`).
SubjectSort = Literal["position", "confidence", "-confidence", "error", "-error"]
SUBJECT_SORTS: tuple[str, ...] = ("position", "confidence", "-confidence", "error", "-error")

#: Point files, and images, that :meth:`RegtreeClient.upload_folder` sends (by suffix).
POINT_SUFFIXES: dict[str, str] = {
    ".txt": "text/plain",
    ".csv": "text/csv",
    ".json": "application/json",
    ".npy": "application/octet-stream",
}
UPLOAD_SUFFIXES: dict[str, str] = {
    **POINT_SUFFIXES,
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
}

TERMINAL = frozenset({"succeeded", "failed", "cancelled"})
_RETRY_STATUSES = frozenset({502, 503, 504})


# --- errors ----------------------------------------------------------------------------------


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


# --- typed results ---------------------------------------------------------------------------


def _dt(value: Any) -> datetime | None:
    if value is None:
        return None
    return datetime.fromisoformat(str(value))


def _array(value: Any, *, dtype: Any = np.float64) -> NDArray[Any] | None:
    if value is None:
        return None
    return np.asarray(value, dtype=dtype)


@dataclass(frozen=True)
class Collection:
    id: int
    name: str
    description: str
    n_shapes: int
    created_at: datetime | None
    updated_at: datetime | None
    raw: dict[str, Any] = field(repr=False, compare=False)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Collection:
        return cls(
            id=int(d["id"]),
            name=str(d["name"]),
            description=str(d.get("description") or ""),
            n_shapes=int(d.get("n_shapes", 0)),
            created_at=_dt(d.get("created_at")),
            updated_at=_dt(d.get("updated_at")),
            raw=dict(d),
        )


@dataclass(frozen=True)
class Shape:
    """A stored shape; ``points`` only when read one by one (:meth:`RegtreeClient.get_shape`)."""

    id: int
    collection_id: int
    name: str
    source_format: str
    n_points: int
    bbox: tuple[float, float, float, float]  # min_x, min_y, max_x, max_y
    created_at: datetime | None
    points: FloatArray | None = field(default=None, repr=False, compare=False)
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Shape:
        box = d.get("bbox") or {}
        points = d.get("points")
        return cls(
            id=int(d["id"]),
            collection_id=int(d["collection_id"]),
            name=str(d["name"]),
            source_format=str(d.get("source_format", "")),
            n_points=int(d.get("n_points", 0)),
            bbox=(
                float(box.get("min_x", np.nan)),
                float(box.get("min_y", np.nan)),
                float(box.get("max_x", np.nan)),
                float(box.get("max_y", np.nan)),
            ),
            created_at=_dt(d.get("created_at")),
            points=None if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 2),
            raw={k: v for k, v in d.items() if k != "points"},
        )


@dataclass(frozen=True)
class JobStatus:
    """A job's state: ``status`` and its progress (``stage``, ``done`` of ``total``)."""

    id: int
    collection_id: int
    model_shape_id: int
    method: str
    status: str
    stage: str | None
    done: int
    total: int
    n_shapes: int
    attempts: int
    cancel_requested: bool
    error: str | None
    params: dict[str, Any]
    created_at: datetime | None
    started_at: datetime | None
    finished_at: datetime | None
    raw: dict[str, Any] = field(repr=False, compare=False)

    @property
    def finished(self) -> bool:
        """True once the job is succeeded, failed or cancelled."""
        return self.status in TERMINAL

    @property
    def fraction(self) -> float | None:
        """``done / total`` of the current stage, or None before the stage is known."""
        return self.done / self.total if self.total else None

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> JobStatus:
        progress = d.get("progress") or {}
        return cls(
            id=int(d["id"]),
            collection_id=int(d["collection_id"]),
            model_shape_id=int(d["model_shape_id"]),
            method=str(d.get("method", "")),
            status=str(d["status"]),
            stage=progress.get("stage"),
            done=int(progress.get("done") or 0),
            total=int(progress.get("total") or 0),
            n_shapes=int(d.get("n_shapes", 0)),
            attempts=int(d.get("attempts", 0)),
            cancel_requested=bool(d.get("cancel_requested", False)),
            error=d.get("error"),
            params=dict(d.get("params") or {}),
            created_at=_dt(d.get("created_at")),
            started_at=_dt(d.get("started_at")),
            finished_at=_dt(d.get("finished_at")),
            raw=dict(d),
        )


@dataclass(frozen=True)
class Subject:
    """One subject of a result: its place in the tree, its error e and, when read with points,
    the model warped onto it (``warped``, in the subject's coordinates), ``correspondence``
    (for each model point, the index of its subject point) and the transform.

    ``confidence`` is the estimated probability (0 to 1) that its correspondences are right
    (None when unattached, or in a result from before confidences existed); ``leaf`` is true
    for a low-confidence leaf (the tree could not accept it; it got its best registration
    anyway, never as a parent; ``reason`` says why); ``quality`` holds the checks of its
    last registration.

    ``direct`` is the direct-CPD registration of the same subject when the job compared it.
    """

    shape_id: int
    name: str
    attached: bool
    layer: int | None
    parent_shape_id: int | None
    path_shape_ids: list[int]
    similarity: float | None
    error: float | None
    direct_error: float | None
    reason: str
    confidence: float | None = None
    leaf: bool = False
    quality: dict[str, Any] | None = field(default=None, repr=False, compare=False)
    warped: FloatArray | None = field(default=None, repr=False, compare=False)
    correspondence: NDArray[np.intp] | None = field(default=None, repr=False, compare=False)
    probability: FloatArray | None = field(default=None, repr=False, compare=False)
    transform: dict[str, Any] | None = field(default=None, repr=False, compare=False)
    direct: Subject | None = field(default=None, repr=False, compare=False)
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Subject:
        direct = d.get("direct")
        correspondence = _array(d.get("correspondence"), dtype=np.intp)
        warped = _array(d.get("warped"))
        return cls(
            shape_id=int(d["shape_id"]),
            name=str(d.get("name", d["shape_id"])),
            attached=bool(d.get("attached", d.get("layer") is not None)),
            layer=None if d.get("layer") is None else int(d["layer"]),
            parent_shape_id=(
                None if d.get("parent_shape_id") is None else int(d["parent_shape_id"])
            ),
            path_shape_ids=[int(i) for i in d.get("path_shape_ids") or []],
            similarity=d.get("similarity"),
            error=d.get("error"),
            direct_error=d.get("direct_error"),
            reason=str(d.get("reason") or ""),
            confidence=(
                float(d["confidence"])
                if isinstance(d.get("confidence"), int | float)
                and not isinstance(d.get("confidence"), bool)
                else None
            ),
            leaf=bool(d.get("leaf", False)),
            quality=dict(d["quality"]) if isinstance(d.get("quality"), Mapping) else None,
            warped=None if warped is None else warped.reshape(-1, 2),
            correspondence=correspondence,
            probability=_array(d.get("probability")),
            transform=d.get("transform"),
            direct=cls.from_json(direct) if isinstance(direct, Mapping) else None,
            raw=dict(d),
        )


@dataclass(frozen=True)
class JobResult:
    """A job's result document (``GET /v1/jobs/{id}/result``).

    ``document`` is the JSON exactly as served: pass it to :mod:`service.plots`.
    """

    job_id: int
    method: str
    root_shape_id: int
    subjects: list[Subject]
    summary: dict[str, Any]
    thresholds: dict[str, Any]
    document: dict[str, Any] = field(repr=False, compare=False)

    @property
    def attached(self) -> list[Subject]:
        return [s for s in self.subjects if s.attached]

    @property
    def unattached(self) -> list[Subject]:
        return [s for s in self.subjects if not s.attached]

    @property
    def leaves(self) -> list[Subject]:
        """The low-confidence leaves (attached too: they have a parent and a registration)."""
        return [s for s in self.subjects if s.leaf]

    def subject(self, shape_id: int) -> Subject:
        for s in self.subjects:
            if s.shape_id == shape_id:
                return s
        raise KeyError(f"shape {shape_id} is not a subject of job {self.job_id}")

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> JobResult:
        return cls(
            job_id=int(d["job_id"]),
            method=str(d.get("method", "")),
            root_shape_id=int(d["root_shape_id"]),
            subjects=[Subject.from_json(s) for s in d.get("subjects") or []],
            summary=dict(d.get("summary") or {}),
            thresholds=dict(d.get("thresholds") or {}),
            document=dict(d),
        )


# --- the client ------------------------------------------------------------------------------


def _result_params(
    full: bool, min_confidence: float | None, sort: str | None, leaf: bool | None
) -> dict[str, str] | None:
    """The query of ``GET /v1/jobs/{id}/result``: only what was given."""
    params: dict[str, str] = {}
    if full:
        params["full"] = "true"
    if min_confidence is not None:
        params["min_confidence"] = repr(float(min_confidence))
    if sort is not None:
        params["sort"] = str(sort)
    if leaf is not None:
        params["leaf"] = "true" if leaf else "false"
    return params or None


def _points_list(points: ArrayLike) -> list[list[float]]:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"points must have shape (n, 2); got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("points must be finite")
    out: list[list[float]] = arr.tolist()
    return out


def find_shape_files(
    folder: str | Path, *, pattern: str = "*", recursive: bool = False
) -> list[Path]:
    """The point files and images in ``folder`` whose name matches ``pattern``, sorted by
    their path relative to the folder; other files are skipped.

    Raises
    ------
    FileNotFoundError
        If ``folder`` is not a folder or holds no matching shape file.
    """
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder")
    candidates = root.rglob("*") if recursive else root.iterdir()
    files = sorted(
        (
            p
            for p in candidates
            if p.is_file()
            and p.suffix.lower() in UPLOAD_SUFFIXES
            and fnmatch.fnmatch(p.name, pattern)
        ),
        key=lambda p: str(p.relative_to(root)),
    )
    if not files:
        raise FileNotFoundError(
            f"no shape files matching {pattern!r} in {root} "
            f"(looked for {', '.join(sorted(UPLOAD_SUFFIXES))})"
        )
    return files


class RegtreeClient:
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
    def from_env(cls, base_url: str | None = None, **kwargs: Any) -> RegtreeClient:
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

    def __enter__(self) -> RegtreeClient:
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
            except httpx.TimeoutException as e:
                if isinstance(e, httpx.ConnectTimeout) and attempt < self.retries:
                    attempt += 1
                    time.sleep(0.25 * 2**attempt)
                    continue
                raise RegtreeTimeout(
                    f"{method} {path}: no answer within the timeout "
                    f"({type(e).__name__}; raise RegtreeClient(timeout=...) for big uploads)"
                ) from e
            except httpx.ConnectError as e:
                if attempt < self.retries:
                    attempt += 1
                    time.sleep(0.25 * 2**attempt)
                    continue
                raise RegtreeConnectionError(
                    f"cannot reach the regtree service at {self.base_url}: {e}"
                ) from e
            except (httpx.RemoteProtocolError, httpx.ReadError) as e:
                if retry and attempt < self.retries:
                    attempt += 1
                    time.sleep(0.25 * 2**attempt)
                    continue
                raise RegtreeConnectionError(
                    f"{method} {path}: the connection to {self.base_url} broke: {e}"
                ) from e
            if response.status_code in _RETRY_STATUSES and retry and attempt < self.retries:
                attempt += 1
                time.sleep(0.25 * 2**attempt)
                continue
            if response.is_success:
                return response
            raise RegtreeError.from_response(response)

    def _get(self, path: str, **kwargs: Any) -> Any:
        return self._request("GET", path, retry=True, **kwargs).json()

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

    # --- collections -------------------------------------------------------------------

    def create_collection(
        self, name: str, description: str = "", *, idempotency_key: str | None = None
    ) -> Collection:
        response = self._request(
            "POST",
            "/v1/collections",
            retry=True,
            idempotency_key=idempotency_key or uuid.uuid4().hex,
            json={"name": name, "description": description},
        )
        return Collection.from_json(response.json())

    def list_collections(self) -> list[Collection]:
        """Every collection (all pages), oldest first."""
        return [Collection.from_json(c) for c in self._paged("/v1/collections")]

    def get_collection(self, collection_id: int) -> Collection:
        return Collection.from_json(self._get(f"/v1/collections/{collection_id}"))

    def delete_collection(self, collection_id: int) -> None:
        """Delete a collection with its shapes, jobs and results."""
        self._request("DELETE", f"/v1/collections/{collection_id}", retry=False)

    # --- shapes ------------------------------------------------------------------------

    def upload_points(
        self,
        collection_id: int,
        name: str,
        points: ArrayLike,
        *,
        idempotency_key: str | None = None,
    ) -> Shape:
        """Upload one shape given as an (n, 2) array of (x, y) points."""
        response = self._request(
            "POST",
            f"/v1/collections/{collection_id}/shapes",
            retry=True,
            idempotency_key=idempotency_key or uuid.uuid4().hex,
            json={"name": name, "points": _points_list(points)},
        )
        return Shape.from_json(response.json())

    def upload_files(
        self,
        collection_id: int,
        files: Sequence[str | Path],
        *,
        mode: ImageMode = "contour",
        target_points: int | None = None,
        batch_size: int = 100,
        max_batch_bytes: int = 16 * 1024 * 1024,
        on_batch: Callable[[int, int], None] | None = None,
    ) -> list[Shape]:
        """Upload files (point files or images) in multipart batches, in the given order.

        Each batch is stored all-or-nothing by the service; batches end at ``batch_size``
        files or ``max_batch_bytes`` (keep it under the service's body limit). If a batch is
        refused, the exception says which batch and carries the shapes stored by the earlier
        batches in ``exc.stored``. ``on_batch(done_files, total_files)`` is called after each.
        The shape name is the file name without its extension.
        """
        if batch_size < 1:
            raise ValueError("batch_size must be >= 1")
        paths = [Path(f) for f in files]
        stored: list[Shape] = []
        batches: list[list[Path]] = []
        current: list[Path] = []
        current_bytes = 0
        for p in paths:
            size = p.stat().st_size
            if current and (len(current) >= batch_size or current_bytes + size > max_batch_bytes):
                batches.append(current)
                current, current_bytes = [], 0
            current.append(p)
            current_bytes += size
        if current:
            batches.append(current)
        data: dict[str, str] = {"mode": mode}
        if target_points is not None:
            data["target_points"] = str(int(target_points))
        done = 0
        for number, batch in enumerate(batches, start=1):
            parts = [
                (
                    "files",
                    (
                        p.name,
                        p.read_bytes(),
                        UPLOAD_SUFFIXES.get(p.suffix.lower(), "application/octet-stream"),
                    ),
                )
                for p in batch
            ]
            try:
                response = self._request(
                    "POST",
                    f"/v1/collections/{collection_id}/shapes",
                    retry=True,
                    idempotency_key=uuid.uuid4().hex,
                    files=parts,
                    data=data,
                )
            except RegtreeError as e:
                e.stored = list(stored)
                e.add_note(
                    f"upload batch {number} of {len(batches)} ({batch[0].name} .. "
                    f"{batch[-1].name}) was refused; {len(stored)} shape(s) from earlier "
                    "batches are stored (exc.stored)"
                )
                raise
            stored.extend(Shape.from_json(s) for s in response.json()["items"])
            done += len(batch)
            if on_batch is not None:
                on_batch(done, len(paths))
        return stored

    def upload_folder(
        self,
        collection_id: int,
        folder: str | Path,
        *,
        pattern: str = "*",
        mode: ImageMode = "contour",
        target_points: int | None = None,
        batch_size: int = 100,
        recursive: bool = False,
        on_batch: Callable[[int, int], None] | None = None,
    ) -> list[Shape]:
        """Upload every point file (.txt .csv .json .npy) and image (.png .jpg .jpeg) in
        ``folder`` whose name matches ``pattern``, sorted by name (other files are skipped).

        Images are turned into points by the service with ``mode`` (contour, edges or
        skeleton) and at most ``target_points`` points. Returns the stored shapes in upload
        order. See :meth:`upload_files` for batching and partial failures.
        """
        files = find_shape_files(folder, pattern=pattern, recursive=recursive)
        return self.upload_files(
            collection_id,
            files,
            mode=mode,
            target_points=target_points,
            batch_size=batch_size,
            on_batch=on_batch,
        )

    def list_shapes(self, collection_id: int) -> list[Shape]:
        """Every shape of a collection (metadata only), in upload order."""
        return [Shape.from_json(s) for s in self._paged(f"/v1/collections/{collection_id}/shapes")]

    def get_shape(self, collection_id: int, shape_id: int) -> Shape:
        """One shape with its points."""
        return Shape.from_json(self._get(f"/v1/collections/{collection_id}/shapes/{shape_id}"))

    def shape_points(self, collection_id: int, shape_ids: Sequence[int]) -> dict[int, FloatArray]:
        """Points of several shapes, by id (e.g. for :mod:`service.plots`)."""
        out: dict[int, FloatArray] = {}
        for sid in shape_ids:
            points = self.get_shape(collection_id, sid).points
            assert points is not None
            out[sid] = points
        return out

    def delete_shape(self, collection_id: int, shape_id: int) -> None:
        self._request("DELETE", f"/v1/collections/{collection_id}/shapes/{shape_id}", retry=False)

    # --- jobs --------------------------------------------------------------------------

    def start_job(
        self,
        collection_id: int,
        model_shape_id: int,
        *,
        method: Method = "dynamic_tree",
        similarity_threshold: float | None = None,
        error_threshold: float | None = None,
        compare_direct: bool = True,
        cpd: Mapping[str, Any] | None = None,
        pose: Pose | None = None,
        max_rotation: float | None = None,
        idempotency_key: str | None = None,
        callback_url: str | None = None,
    ) -> JobStatus:
        """Queue a job registering ``model_shape_id`` onto every shape of the collection.

        Thresholds left None are chosen automatically by the service. ``cpd`` may set
        ``beta``, ``lmbda``, ``w``, ``max_iter``, ``tol``.

        ``pose`` is which poses the affine pre-alignment may give a shape:

        * ``"as_given"``: only the shapes as uploaded (no rotation search);
        * ``"upright"``: rotations within +-``max_rotation`` degrees (30 unless given) of
          the shapes as uploaded, no mirror images: glyph scans, aligned outlines;
        * ``"rotation"``: any rotation, no mirror images;
        * ``"affine"``: any affine map, mirror images included (the paper's).

        Left None (and ``max_rotation`` too), the service decides, as for any HTTP client:
        ``"upright"`` when every shape of the collection was uploaded as an image, else
        ``"rotation"``; ``max_rotation`` alone means ``"upright"``. The job's ``params``
        record the pose used and ``pose_source``. ``max_rotation`` with another pose is
        refused (:class:`ValidationError`).

        Give ``idempotency_key`` to make a resubmission (e.g. after a crash of your script)
        return the same job.

        ``callback_url`` is POSTed a signed JSON body when the job ends (see
        :meth:`deliveries`); the server must allow its host (else :class:`ValidationError`).
        """
        body: dict[str, Any] = {
            "collection_id": collection_id,
            "model_shape_id": model_shape_id,
            "method": method,
            "similarity_threshold": similarity_threshold,
            "error_threshold": error_threshold,
            "compare_direct": compare_direct,
        }
        if pose is not None:
            body["pose"] = pose
        if max_rotation is not None:
            body["max_rotation"] = max_rotation
        if cpd is not None:
            body["cpd"] = dict(cpd)
        if callback_url is not None:
            body["callback_url"] = callback_url
        response = self._request(
            "POST",
            "/v1/jobs",
            retry=True,
            idempotency_key=idempotency_key or uuid.uuid4().hex,
            json=body,
        )
        return JobStatus.from_json(response.json())

    def get_job(self, job_id: int) -> JobStatus:
        return JobStatus.from_json(self._get(f"/v1/jobs/{job_id}"))

    def deliveries(self, job_id: int) -> dict[str, Any]:
        """The job's callback: ``state`` (none, waiting, pending, delivered, failed) and
        ``items``, every try (``status_code``, ``error``)."""
        return self._get(f"/v1/jobs/{job_id}/deliveries")

    def list_jobs(
        self, *, collection_id: int | None = None, status: str | None = None
    ) -> list[JobStatus]:
        """Jobs, newest first, optionally of one collection and/or in one status."""
        params: dict[str, Any] = {}
        if collection_id is not None:
            params["collection_id"] = collection_id
        if status is not None:
            params["status"] = status
        return [JobStatus.from_json(j) for j in self._paged("/v1/jobs", **params)]

    def wait(
        self,
        job_id: int,
        *,
        poll: float = 0.5,
        timeout: float | None = None,
        on_progress: Callable[[JobStatus], None] | None = None,
        raise_on_failure: bool = True,
    ) -> JobStatus:
        """Poll a job until it is succeeded, failed or cancelled; return its final status.

        ``on_progress`` is called with the first status seen and then whenever the status,
        stage or ``done`` / ``total`` change (including the final one). ``timeout`` (seconds,
        None = forever) raises :class:`RegtreeTimeout`; the job keeps running. A job that ends
        failed or cancelled raises :class:`JobFailed` unless ``raise_on_failure=False``.
        """
        if poll <= 0:
            raise ValueError("poll must be > 0")
        deadline = None if timeout is None else time.monotonic() + timeout
        last_key: tuple[Any, ...] | None = None
        while True:
            state = self.get_job(job_id)
            key = (state.status, state.stage, state.done, state.total)
            if key != last_key:
                last_key = key
                if on_progress is not None:
                    on_progress(state)
            if state.finished:
                if raise_on_failure and state.status != "succeeded":
                    detail = f": {state.error}" if state.error else ""
                    raise JobFailed(f"job {job_id} ended {state.status}{detail}", job=state)
                return state
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                raise RegtreeTimeout(
                    f"job {job_id} still {state.status} ({state.stage or 'no stage'} "
                    f"{state.done}/{state.total}) after {timeout:g} s; it keeps running",
                    last_status=state,
                )
            sleep = poll if deadline is None else max(0.0, min(poll, deadline - now))
            time.sleep(sleep)

    def cancel(self, job_id: int) -> JobStatus:
        """Cancel a job: queued jobs at once, running ones at their next progress report.

        Raises :class:`Conflict` if the job had already finished.
        """
        return JobStatus.from_json(
            self._request("POST", f"/v1/jobs/{job_id}/cancel", retry=False).json()
        )

    # --- results -----------------------------------------------------------------------

    def result(
        self,
        job_id: int,
        *,
        full: bool = False,
        min_confidence: float | None = None,
        sort: SubjectSort | None = None,
        leaf: bool | None = None,
    ) -> JobResult:
        """The job's result. ``full=True`` includes every subject's warped model,
        correspondences and transform (heavy for big collections; :meth:`subject` reads one).

        ``min_confidence`` (0 to 1) lists only subjects at least that confident (those
        without a confidence, unattached ones, are left out); ``leaf`` only low-confidence
        leaves (True) or only the others (False); ``sort`` orders the subjects: "position"
        (the server's default: the job's shape order), "confidence", "-confidence", "error"
        or "-error" (a leading "-" is descending; subjects without the value come last).
        The server checks them: a bad value raises :class:`ValidationError` (422). The
        ``summary`` always counts every subject.

        Raises :class:`Conflict` while the job has not succeeded.
        """
        params = _result_params(full, min_confidence, sort, leaf)
        return JobResult.from_json(self._get(f"/v1/jobs/{job_id}/result", params=params))

    def result_document(
        self,
        job_id: int,
        *,
        full: bool = False,
        min_confidence: float | None = None,
        sort: SubjectSort | None = None,
        leaf: bool | None = None,
    ) -> dict[str, Any]:
        """The result JSON as served (what :mod:`service.plots` takes); the options are
        :meth:`result`'s."""
        params = _result_params(full, min_confidence, sort, leaf)
        document: dict[str, Any] = self._get(f"/v1/jobs/{job_id}/result", params=params)
        return document

    def subject(self, job_id: int, shape_id: int) -> Subject:
        """One subject of a result, with its warped model, correspondences and transform."""
        return Subject.from_json(self._get(f"/v1/jobs/{job_id}/result/subjects/{shape_id}"))

    def apply_transform(self, job_id: int, shape_id: int, points: ArrayLike) -> FloatArray:
        """Map (n, 2) points from the model's coordinates onto a subject, with the transform
        the job found (the chain of registrations along its tree path)."""
        response = self._request(
            "POST",
            f"/v1/jobs/{job_id}/result/subjects/{shape_id}/transform",
            retry=True,
            json={"points": _points_list(points)},
        )
        return np.asarray(response.json()["points"], dtype=np.float64).reshape(-1, 2)

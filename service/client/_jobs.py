"""Jobs and their results: :class:`RegtreeClient`'s methods for them."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypedDict, Unpack

import numpy as np
from numpy.typing import ArrayLike

from service.client._http import HttpClient
from service.client.errors import JobFailed, RegtreeTimeout
from service.client.files import _points_list
from service.client.models import FloatArray, JobResult, JobStatus, Similarity, Subject
from service.contract.names import (
    DEFAULT_COMPARE_DIRECT,
    DEFAULT_METHOD,
    DEFAULT_WORKING_POINTS,
    Method,
    PoseName,
    SubjectSort,
)


class SubjectQuery(TypedDict, total=False):
    """Which subjects a result lists, in which order: the keywords of
    :meth:`~RegtreeClient.result_csv` (described at :meth:`~RegtreeClient.result`)."""

    min_confidence: float | None
    sort: SubjectSort | None
    leaf: bool | None


class ResultQuery(SubjectQuery, total=False):
    """A :class:`SubjectQuery` and ``full``: the keywords of :meth:`~RegtreeClient.result`
    and :meth:`~RegtreeClient.result_document`."""

    full: bool


def _result_params(
    method: str, query: Mapping[str, Any], accepted: frozenset[str]
) -> dict[str, str] | None:
    """The query of ``GET /v1/jobs/{id}/result`` (or ``result.csv``): only what was given;
    a keyword `method` does not take is a TypeError, as Python raises it."""
    for name in query:
        if name not in accepted:
            raise TypeError(f"{method}() got an unexpected keyword argument {name!r}")
    params: dict[str, str] = {}
    if query.get("full"):
        params["full"] = "true"
    if (min_confidence := query.get("min_confidence")) is not None:
        params["min_confidence"] = repr(float(min_confidence))
    if (sort := query.get("sort")) is not None:
        params["sort"] = str(sort)
    if (leaf := query.get("leaf")) is not None:
        params["leaf"] = "true" if leaf else "false"
    return params or None


#: How the affine pre-alignment may pose a shape: see :meth:`RegtreeClient.start_job`.
Pose = PoseName


class JobsAndResults(HttpClient):
    # --- jobs --------------------------------------------------------------------------

    def start_job(
        self,
        collection_id: int,
        model_shape_id: int,
        *,
        method: Method = DEFAULT_METHOD,
        similarity_threshold: float | None = None,
        error_threshold: float | None = None,
        compare_direct: bool = DEFAULT_COMPARE_DIRECT,
        cpd: Mapping[str, Any] | None = None,
        pose: Pose | None = None,
        max_rotation: float | None = None,
        working_points: int | None = DEFAULT_WORKING_POINTS,
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

        ``working_points``: the tree is decided with every shape subsampled to at most this
        many points, then each edge is registered once at the stored resolution (the result
        is at the stored resolution); None or 0 decides at the stored resolution.

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
        if working_points != DEFAULT_WORKING_POINTS:  # the default: what older servers run
            body["working_points"] = working_points
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

    def result(self, job_id: int, **query: Unpack[ResultQuery]) -> JobResult:
        """The job's result; ``document`` is the JSON as served. The keywords
        (:class:`ResultQuery`, all optional): ``full=True`` includes every subject's warped
        model, correspondences and transform (heavy for big collections; :meth:`subject`
        reads one).

        ``min_confidence`` (0 to 1) lists only subjects at least that confident (those
        without a confidence, unattached ones, are left out); ``leaf`` only low-confidence
        leaves (True) or only the others (False); ``sort`` orders the subjects: "position"
        (the server's default: the job's shape order), "confidence", "-confidence", "error"
        or "-error" (a leading "-" is descending; subjects without the value come last).
        The server checks them: a bad value raises :class:`ValidationError` (422). The
        ``summary`` always counts every subject.

        Raises :class:`Conflict` while the job has not succeeded.
        """
        return JobResult.from_json(self._result_json(job_id, "result", query))

    def result_document(self, job_id: int, **query: Unpack[ResultQuery]) -> dict[str, Any]:
        """The result JSON as served (what :mod:`service.plots` takes); the keywords
        (:class:`ResultQuery`) are :meth:`result`'s."""
        return self._result_json(job_id, "result_document", query)

    def _result_json(self, job_id: int, method: str, query: ResultQuery) -> dict[str, Any]:
        """``GET /v1/jobs/{id}/result`` with `query` (what `method` was called with)."""
        params = _result_params(method, query, ResultQuery.__optional_keys__)
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

    def inverse_transform(self, job_id: int, shape_id: int, points: ArrayLike) -> FloatArray:
        """Map (n, 2) points from a subject's coordinates back onto the model's: the inverse
        of :meth:`apply_transform` (solved numerically by the server; a point without a
        preimage, e.g. far outside the shape, comes back as NaN)."""
        response = self._request(
            "POST",
            f"/v1/jobs/{job_id}/result/subjects/{shape_id}/inverse-transform",
            retry=True,
            json={"points": _points_list(points)},
        )
        return np.array(
            [[np.nan, np.nan] if p is None else p for p in response.json()["points"]],
            dtype=np.float64,
        ).reshape(-1, 2)

    def similarity(self, job_id: int, *, k: int = 5, matrix: bool = True) -> Similarity:
        """The similarity D the job computed and each shape's ``k`` nearest shapes.

        Raises :class:`Conflict` for a result stored before the similarity was kept."""
        params = {"k": str(int(k)), "matrix": "true" if matrix else "false"}
        return Similarity.from_json(self._get(f"/v1/jobs/{job_id}/similarity", params=params))

    def result_csv(self, job_id: int, **query: Unpack[SubjectQuery]) -> str:
        """The per-subject results as CSV text (one row per subject); the keywords
        (:class:`SubjectQuery`) are :meth:`result`'s but ``full``."""
        params = _result_params("result_csv", query, SubjectQuery.__optional_keys__)
        return self._request(
            "GET", f"/v1/jobs/{job_id}/result.csv", retry=True, params=params
        ).text

    def export_zip(
        self, job_id: int, path: str | Path | None = None, *, subject_pictures: bool = False
    ) -> bytes:
        """The whole job as one ZIP (result JSON and CSV, similarity, pictures; with
        ``subject_pictures`` every subject's overlay too); written to ``path`` if given."""
        params = {"subject_pictures": "true"} if subject_pictures else None
        data = self._request(
            "GET", f"/v1/jobs/{job_id}/export.zip", retry=True, params=params
        ).content
        if path is not None:
            Path(path).write_bytes(data)
        return data

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

The client is a package by section: errors, typed results (models), shape files, HTTP
plumbing, and the methods for collections and shapes, and for jobs and results.
"""

from __future__ import annotations

from service.client._grouping import Grouping, GroupPicture
from service.client._http import HttpClient
from service.client._jobs import JobsAndResults, Pose, ResultQuery, SubjectQuery
from service.client._shapes import CollectionsAndShapes
from service.client.errors import (
    Conflict,
    JobFailed,
    NotFound,
    RegtreeConnectionError,
    RegtreeError,
    RegtreeTimeout,
    ServerError,
    Unauthorized,
    ValidationError,
)
from service.client.files import POINT_SUFFIXES, UPLOAD_SUFFIXES, find_shape_files
from service.client.models import (
    TERMINAL,
    Collection,
    JobResult,
    JobStatus,
    Shape,
    Similarity,
    Subject,
)
from service.contract.names import SUBJECT_SORTS, ImageMode, Method, OnConflict, SubjectSort

__all__ = [
    "POINT_SUFFIXES",
    "SUBJECT_SORTS",
    "TERMINAL",
    "UPLOAD_SUFFIXES",
    "Collection",
    "Conflict",
    "GroupPicture",
    "ImageMode",
    "JobFailed",
    "JobResult",
    "JobStatus",
    "Method",
    "NotFound",
    "OnConflict",
    "Pose",
    "RegtreeClient",
    "RegtreeConnectionError",
    "RegtreeError",
    "RegtreeTimeout",
    "ResultQuery",
    "ServerError",
    "Shape",
    "Similarity",
    "Subject",
    "SubjectQuery",
    "SubjectSort",
    "Unauthorized",
    "ValidationError",
    "find_shape_files",
]


class RegtreeClient(JobsAndResults, Grouping, CollectionsAndShapes, HttpClient):
    __doc__ = HttpClient.__doc__

"""Grouping jobs (issue 11): :class:`RegtreeClient`'s methods for them."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Literal

from service.client._http import HttpClient
from service.client.models import JobStatus
from service.contract.names import GROUPING_METHOD
from service.contract.result import GroupingDocument

#: The pictures of a grouping: ``GET /v1/jobs/{id}/groups/<name>.png``.
GroupPicture = Literal["gallery", "dendrogram"]


class Grouping(HttpClient):
    def start_grouping(
        self,
        collection_id: int,
        *,
        threshold: float | None = None,
        max_rotation: float | None = None,
        idempotency_key: str | None = None,
    ) -> JobStatus:
        """Queue a job grouping the collection's shapes by the mould that printed them.

        ``threshold`` (units: the shapes' RMS radius) cuts the average-linkage tree; None
        lets the service choose (2x the median nearest-instance distance).
        ``max_rotation`` (degrees) when the scans may be rotated by more than a few degrees.
        Follow it with :meth:`wait`, then read :meth:`groups`.
        """
        body: dict[str, object] = {"collection_id": collection_id, "method": GROUPING_METHOD}
        if threshold is not None:
            body["group_threshold"] = threshold
        if max_rotation is not None:
            body["max_rotation"] = max_rotation
        response = self._request("POST", "/v1/jobs", retry=True,
                                 idempotency_key=idempotency_key or uuid.uuid4().hex, json=body)
        return JobStatus.from_json(response.json())

    def groups(self, job_id: int) -> GroupingDocument:
        """A succeeded grouping's document: ``labels`` by shape id, ``groups`` with their
        ``representative_shape_id``, ``instances`` with ``confidence``, ``distances``.

        Raises :class:`Conflict` while the job has not succeeded, or for a registration."""
        return GroupingDocument.model_validate(self._get(f"/v1/jobs/{job_id}/groups"))

    def group_picture(
        self,
        job_id: int,
        picture: GroupPicture | int = "gallery",
        path: str | Path | None = None,
    ) -> bytes:
        """A grouping's picture as PNG bytes (also written to ``path`` when given):
        ``"gallery"``, ``"dendrogram"``, or a shape id for that instance beside its
        group's representative."""
        name = f"instances/{picture}" if isinstance(picture, int) else picture
        data = self._request("GET", f"/v1/jobs/{job_id}/groups/{name}.png", retry=True).content
        if path is not None:
            Path(path).write_bytes(data)
        return data

"""Collections and shapes: :class:`RegtreeClient`'s methods for them."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Sequence
from pathlib import Path

from numpy.typing import ArrayLike

from service.client._http import HttpClient
from service.client.errors import RegtreeError
from service.client.files import UPLOAD_SUFFIXES, _points_list, find_shape_files
from service.client.models import Collection, FloatArray, Shape
from service.contract.names import (
    DEFAULT_IMAGE_MODE,
    DEFAULT_ON_CONFLICT,
    ImageMode,
    OnConflict,
)


class CollectionsAndShapes(HttpClient):
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
        on_conflict: OnConflict = DEFAULT_ON_CONFLICT,
        idempotency_key: str | None = None,
    ) -> Shape:
        """Upload one shape given as an (n, 2) array of (x, y) points.

        ``on_conflict``: if the collection holds a shape of this name, ``refuse`` (an error,
        nothing stored), ``replace`` it (the new shape gets a new id) or ``keep`` both.
        """
        response = self._request(
            "POST",
            f"/v1/collections/{collection_id}/shapes",
            retry=True,
            idempotency_key=idempotency_key or uuid.uuid4().hex,
            params={"on_conflict": on_conflict},
            json={"name": name, "points": _points_list(points)},
        )
        return Shape.from_json(response.json())

    def upload_files(
        self,
        collection_id: int,
        files: Sequence[str | Path],
        *,
        mode: ImageMode = DEFAULT_IMAGE_MODE,
        target_points: int | None = None,
        on_conflict: OnConflict = DEFAULT_ON_CONFLICT,
        batch_size: int = 100,
        max_batch_bytes: int = 16 * 1024 * 1024,
        on_batch: Callable[[int, int], None] | None = None,
    ) -> list[Shape]:
        """Upload files (point files or images) in multipart batches, in the given order.

        Each batch is stored all-or-nothing by the service; batches end at ``batch_size``
        files or ``max_batch_bytes`` (keep it under the service's body limit). If a batch is
        refused, the exception says which batch and carries the shapes stored by the earlier
        batches in ``exc.stored``; for invalid files, ``exc.problem["invalid"]`` lists every
        one of that batch (``file``, ``index``, ``detail``).
        ``on_batch(done_files, total_files)`` is called after each.
        The shape name is the file name without its extension; ``on_conflict`` says what
        happens to names the collection holds already (see :meth:`upload_points`).
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
                    params={"on_conflict": on_conflict},
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
        mode: ImageMode = DEFAULT_IMAGE_MODE,
        target_points: int | None = None,
        on_conflict: OnConflict = DEFAULT_ON_CONFLICT,
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
            on_conflict=on_conflict,
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

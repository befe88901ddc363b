"""The client's typed results, read through the contract's models
(:mod:`service.contract.result`); each keeps the server's JSON in ``raw``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.contract.names import (
    TERMINAL_STATUSES,
    SubjectStatus,
)
from service.contract.result import ResultDocument, SimilarityDocument, SubjectDetail

FloatArray = NDArray[np.float64]
TERMINAL = TERMINAL_STATUSES



def _dt(value: Any) -> datetime | None:
    if value is None:
        return None
    return datetime.fromisoformat(str(value))


def _array(
    value: Any, *, dtype: Any = np.float64, shape: tuple[int, ...] | None = None
) -> NDArray[Any] | None:
    if value is None:
        return None
    array = np.asarray(value, dtype=dtype)
    return array if shape is None else array.reshape(shape)


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
    model_shape_id: int | None  # None: a job without a model (a grouping)
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
            model_shape_id=None if d.get("model_shape_id") is None else int(d["model_shape_id"]),
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
    #: How far apart two registrations that err differently put the model's points, in the
    #: subject's RMS radius: a second sign beside ``confidence`` (None where no symmetric
    #: finish ran, or in a result from before it was reported).
    disagreement: float | None = None
    #: "tree" (a member), "leaf" (a low-confidence leaf) or "unattached".
    status: SubjectStatus = "unattached"
    quality: dict[str, Any] | None = field(default=None, repr=False, compare=False)
    warped: FloatArray | None = field(default=None, repr=False, compare=False)
    correspondence: NDArray[np.intp] | None = field(default=None, repr=False, compare=False)
    probability: FloatArray | None = field(default=None, repr=False, compare=False)
    transform: dict[str, Any] | None = field(default=None, repr=False, compare=False)
    direct: Subject | None = field(default=None, repr=False, compare=False)
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Subject:
        """A subject from the server's JSON, read through :class:`SubjectDetail`."""
        return cls.from_model(SubjectDetail.model_validate(dict(d)), d)

    @classmethod
    def from_model(cls, m: SubjectDetail, raw: Mapping[str, Any]) -> Subject:
        """A subject from its validated model; ``raw`` is the JSON it was read from."""
        direct = raw.get("direct")
        return cls(
            shape_id=m.shape_id,
            name=m.name or str(m.shape_id),
            attached=m.attached,
            layer=m.layer,
            parent_shape_id=m.parent_shape_id,
            path_shape_ids=[int(i) for i in m.path_shape_ids if i is not None],
            similarity=m.similarity,
            error=m.error,
            direct_error=m.direct_error,
            reason=m.reason,
            confidence=m.confidence,
            disagreement=m.disagreement,
            leaf=m.leaf,
            status=m.status,
            quality=None if m.quality is None else m.quality.model_dump(exclude_unset=True),
            warped=_array(m.warped, shape=(-1, 2)),
            correspondence=_array(m.correspondence, dtype=np.intp),
            probability=_array(m.probability),
            transform=raw.get("transform"),
            direct=(
                cls.from_model(m.direct, direct)
                if m.direct is not None and isinstance(direct, Mapping)
                else None
            ),
            raw=dict(raw),
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
    #: The document as validated by the contract's model (typed summary, subjects...).
    model: ResultDocument | None = field(default=None, repr=False, compare=False)

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
        """A result from the server's JSON, read through :class:`ResultDocument`."""
        m = ResultDocument.model_validate(dict(d))
        raw_subjects = [s for s in d.get("subjects") or [] if isinstance(s, Mapping)]
        return cls(
            job_id=m.job_id,
            method=m.method,
            root_shape_id=m.root_shape_id,
            subjects=[
                Subject.from_model(s, raw) for s, raw in zip(m.subjects, raw_subjects, strict=True)
            ],
            summary=dict(d.get("summary") or {}),
            thresholds=dict(m.thresholds),
            document=dict(d),
            model=m,
        )


@dataclass(frozen=True)
class Similarity:
    """The similarity D a job computed (``GET /v1/jobs/{id}/similarity``).

    ``D[i, j]`` is D (eq. 9) from shape ``shape_ids[i]`` onto ``shape_ids[j]`` (the direction
    the tree uses, member onto subject), NaN where the job did not compute it (or when read
    with ``matrix=False``); ``nearest[shape_id]`` lists ``(other_shape_id, D)`` with the
    smallest D onto that shape first.
    """

    job_id: int
    shape_ids: list[int]
    names: list[str]
    D: FloatArray = field(repr=False, compare=False)
    nearest: dict[int, list[tuple[int, float]]] = field(repr=False, compare=False)
    computed_pairs: int = 0
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Similarity:
        m = SimilarityDocument.model_validate(dict(d))
        n = len(m.shape_ids)
        D = np.full((n, n), np.nan)
        if m.D is not None:
            D = np.array(
                [[np.nan if v is None else v for v in row] for row in m.D], dtype=np.float64
            ).reshape(n, n)
        return cls(
            job_id=m.job_id,
            shape_ids=list(m.shape_ids),
            names=list(m.names),
            D=D,
            nearest={s.shape_id: [(x.shape_id, x.D) for x in s.nearest] for s in m.nearest},
            computed_pairs=m.computed_pairs,
            raw=dict(d),
        )

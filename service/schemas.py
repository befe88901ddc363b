"""Pydantic request and response models of the HTTP API (the OpenAPI document's schemas)."""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Generic, Literal, TypeVar

from annotated_types import Interval
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from service.contract.names import (
    DEFAULT_COMPARE_DIRECT,
    DEFAULT_METHOD,
    DEFAULT_WORKING_POINTS,
    GROUPING_METHOD,
    JobOutcomeName,
    JobStatusName,
    Method,
    PoseName,
)
from service.contract.names import ImageMode as ImageMode  # re-exported for routes/shapes.py
from service.contract.result import ResultDocument
from service.core.limits import bounds, example, examples

T = TypeVar("T")


#: Text without NUL characters: PostgreSQL cannot store them in a text column, so every
#: name and description refuses them, on every database alike.
NO_NUL = r"^[^\x00]*$"

# The upload limits are settings: the schema states them with placeholders that each app
# fills in from its own settings (service.core.limits). These models document the JSON
# upload; the server enforces the limits with the same settings (service.ingest).

#: Largest value of SQLite's INTEGER (a signed 64-bit integer).
INT64_MAX = 2**63 - 1
#: A database id (of a collection, shape or job): 1 or more, and at most SQLite's largest
#: INTEGER, which is also the most a Python int bound into SQL may be (beyond it, an
#: OverflowError and a 500). Anything else is refused up front with 422 like any other
#: invalid parameter, and the schema says so (``minimum: 1``).
DbId = Annotated[int, Interval(ge=1, le=INT64_MAX)]

# The vocabulary (methods, image modes, poses, statuses) is service.contract.names's.

POSE_DESCRIPTION = (
    "Which poses the affine pre-alignment (before the non-rigid registration) may give a "
    "shape. "
    "as_given: only the shapes as uploaded (no rotation search; matched on position and size). "
    "upright: rotations within +-max_rotation degrees of the shapes as uploaded (30 unless "
    "max_rotation says otherwise), never a mirror image; for upright collections such as "
    "glyph scans and aligned outlines. "
    "rotation: any rotation, never a mirror image. "
    "affine: any affine map, mirror images included (the paper's method). "
    "In every mode the pose as uploaded is tried too, and a rotated pose is only kept when "
    "the registration from it is clearly better. "
    "Default (null): upright (30 degrees) when every shape of the collection was uploaded as "
    "a PNG or JPEG image, rotation otherwise; max_rotation alone means upright. The job's "
    "params record the pose used (pose, max_rotation) and why (pose_source)."
)


class Page(BaseModel, Generic[T]):
    """One page of a list."""

    items: list[T]
    total: int = Field(description="Number of items over all pages.")
    limit: int
    offset: int


# --- collections -----------------------------------------------------------------------------


class CollectionCreate(BaseModel):
    model_config = examples(
        {"name": "yong-glyphs", "description": "永 from 73 font designs"}, extra="forbid"
    )

    name: str = Field(min_length=1, max_length=200, pattern=NO_NUL)
    description: str = Field(default="", max_length=5000, pattern=NO_NUL)


class CollectionOut(BaseModel):
    model_config = examples(
        {
            "id": 1,
            "name": "yong-glyphs",
            "description": "永 from 73 font designs",
            "n_shapes": 73,
            "created_at": "2026-01-01T12:00:00Z",
            "updated_at": "2026-01-01T12:00:00Z",
        },
    )

    id: int
    name: str
    description: str
    n_shapes: int
    created_at: datetime
    updated_at: datetime


# --- shapes ----------------------------------------------------------------------------------


Point = tuple[float, float]
#: A coordinate of an uploaded point: at most ``max_coordinate`` in absolute value.
Coordinate = Annotated[
    float,
    Field(json_schema_extra=bounds(minimum="-max_coordinate", maximum="max_coordinate")),
]
InputPoint = tuple[Coordinate, Coordinate]


class ShapeJSON(BaseModel):
    """A shape sent as JSON: a name and its (x, y) points in the user's own units.

    The bounds are this server's settings ``min_points``, ``max_points_per_shape`` and
    ``max_coordinate``.
    """

    model_config = examples({"name": "outline-1", "points": example("points")})

    name: str | None = Field(default=None, min_length=1, max_length=300, pattern=NO_NUL)
    points: list[InputPoint] = Field(
        description="{min_points} to {max_points_per_shape} points [x, y], each coordinate "
        "within ±{max_coordinate:g} (settings min_points, max_points_per_shape, max_coordinate).",
        json_schema_extra=bounds(minItems="min_points", maxItems="max_points_per_shape"),
    )


class ShapeBatchJSON(BaseModel):
    """Several shapes in one JSON body; all are stored or none."""

    shapes: list[ShapeJSON] = Field(
        min_length=1,
        description="1 to {max_batch_files} shapes (setting max_batch_files); the collection "
        "may hold {max_shapes_per_collection} in all (setting max_shapes_per_collection).",
        json_schema_extra=bounds(maxItems="max_batch_files"),
    )


class BBox(BaseModel):
    min_x: float
    min_y: float
    max_x: float
    max_y: float


class ShapeOut(BaseModel):
    model_config = examples(
        {
            "id": 7,
            "collection_id": 1,
            "name": "fish-1",
            "source_format": "json",
            "n_points": 91,
            "bbox": {"min_x": -1.2, "min_y": -0.8, "max_x": 1.3, "max_y": 0.9},
            "created_at": "2026-01-01T12:00:00Z",
        },
    )

    id: int
    collection_id: int
    name: str
    source_format: str
    n_points: int
    bbox: BBox
    created_at: datetime


class ShapeDetail(ShapeOut):
    points: list[Point]


class ShapeBatchOut(BaseModel):
    """The shapes stored by one upload, in upload order."""

    items: list[ShapeOut]
    count: int


# --- jobs ------------------------------------------------------------------------------------


def _cpd_rules(schema: dict[str, Any]) -> None:
    """State the library's rules of each CPD option (``CPDOptions.RANGES``) in the schema.

    Run when the OpenAPI document is built, so the library is imported then, not at start.
    """
    from registration._cpd import DTYPES, MIXTURES, CPDOptions

    properties = schema.get("properties", {})
    for name, allowed in CPDOptions.RANGES.items():
        prop = properties[name]
        if allowed.low is not None:
            prop["minimum" if allowed.low_closed else "exclusiveMinimum"] = allowed.low
        if allowed.high is not None:
            prop["maximum" if allowed.high_closed else "exclusiveMaximum"] = allowed.high
    properties["dtype"]["enum"] = list(DTYPES)
    # Optional[str]: pydantic states it as anyOf [string, null]
    for branch in properties["mixture_weights"].get("anyOf", []):
        if branch.get("type") == "string":
            branch["enum"] = list(MIXTURES)


class CPDParams(BaseModel):
    """Coherent Point Drift options (Myronenko & Song 2010): the library's ``CPDOptions``.

    The library validates every value (``CPDOptions.check``), so a 422 says what its
    ``ValueError`` says; the service adds only upper limits of its own on the cost.
    """

    model_config = ConfigDict(extra="forbid", json_schema_extra=_cpd_rules)

    beta: float = Field(default=2.0, le=1e3, description="Gaussian kernel width.")
    lmbda: float = Field(default=3.0, le=1e6, description="Smoothness weight.")
    w: float = Field(default=0.1, description="Outlier weight in [0, 1).")
    max_iter: int = Field(default=150, le=10_000)
    tol: float = Field(
        default=1e-5,
        le=1,
        description="Stop when the objective changes by at most this, relatively; 0 runs "
        "max_iter iterations.",
    )
    dtype: str = Field(
        default="float32",
        description="Precision of CPD's E-step: float32 is about 1.35x faster and agrees with "
        "float64 to about 1e-4 (same tree, e within 2e-5 on the 73 glyphs benchmark).",
    )
    mixture_weights: str | None = Field(
        default=None,
        description="The mixture's weights: 'uniform' (every model point alike, as CPD), "
        "'sampling' (each model point weighted by the outline length it stands for, so the "
        "clusters of a randomly sampled shape do not outweigh its gaps), or null: the "
        "method's own ('sampling' for the dynamic tree, 'uniform' for direct CPD and the "
        "static tree, the paper's baselines).",
    )

    @field_validator("beta", "lmbda", "w", "max_iter", "tol", "dtype", "mixture_weights")
    @classmethod
    def _library_rule(cls, value: Any, info: ValidationInfo) -> Any:
        # imported here, not at module level, so that the API starts without numpy
        from registration._cpd import CPDOptions

        return CPDOptions.check(str(info.field_name), value)


def _finite_positive(value: float | None) -> float | None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ValueError("must be a finite number > 0, or null for automatic")
    return value


class JobCreate(BaseModel):
    model_config = examples(
        {
            "collection_id": 1,
            "collection_name": "永 from 73 fonts",
            "model_shape_id": 7,
            "model_name": "yong_song",
            "method": "dynamic_tree",
            "similarity_threshold": None,
            "error_threshold": None,
            "compare_direct": True,
            "cpd": {"beta": 2.0, "lmbda": 3.0, "w": 0.1, "max_iter": 150, "tol": 1e-5},
        },
        extra="forbid",
    )

    collection_id: DbId
    model_shape_id: DbId | None = Field(
        default=None,
        description="The model shape; it must be in the collection. Required by the "
        "registration methods; a grouping has no model (one given is ignored: the job's is "
        "null).",
    )
    method: Method = Field(
        default=DEFAULT_METHOD,
        description="dynamic_tree, static_tree or direct register the model onto the "
        "collection; grouping groups the collection's shapes by the mould that printed them "
        "(result: GET /v1/jobs/{job_id}/groups).",
    )
    group_threshold: float | None = Field(
        default=None,
        description="Grouping only: the cut of the average-linkage tree (units: the shapes' "
        "RMS radius); null = automatic (2x the median nearest-instance distance; a lone "
        "shape then joins its nearest group of 3+ within 1.5x the cut).",
    )
    similarity_threshold: float | None = Field(
        default=None, description="Largest similarity distance D for a tree edge; null = auto."
    )
    error_threshold: float | None = Field(
        default=None, description="Largest registration error e to accept; null = automatic."
    )
    compare_direct: bool = Field(
        default=DEFAULT_COMPARE_DIRECT,
        description="Also register every subject directly from the model (plain comparison; "
        "doubles the registrations).",
    )
    pose: PoseName | None = Field(default=None, description=POSE_DESCRIPTION)
    max_rotation: float | None = Field(
        default=None,
        ge=0,
        le=180,
        description="Half-width in degrees of the upright pose: the pre-alignment only "
        "considers rotations within +-max_rotation of the shapes as uploaded, without mirror "
        "images. Only with pose upright or without pose (then it means upright); with another "
        "pose it is refused (422). null = 30 for upright. 30 suits glyphs: see "
        "bench/RESULTS.md.",
    )
    cpd: CPDParams = Field(default_factory=CPDParams)
    working_points: int | None = Field(
        default=DEFAULT_WORKING_POINTS,
        description="Decide the tree (similarity, candidates, acceptance) with every shape "
        "subsampled to at most this many points, then register each edge once at the stored "
        "resolution, warm-started from that decision (a dynamic tree then polishes its "
        "subjects again there): the result (warped points, correspondences, transforms, e) "
        "is at the stored resolution. Shapes with at most this "
        "many points are used as they are. null or 0: decide at the stored resolution "
        "(slower on large shapes). At least 20 otherwise.",
    )
    callback_url: str | None = Field(
        default=None,
        max_length=2000,
        description="Called (POST, signed JSON: job_id, state, result_url) when the job ends; "
        "see GET /v1/jobs/{job_id}/deliveries. Must be http(s) on a host of the setting "
        "callback_allowed_hosts (else 422).",
    )

    _check_similarity = field_validator("similarity_threshold")(_finite_positive)
    _check_error = field_validator("error_threshold")(_finite_positive)
    _check_group = field_validator("group_threshold")(_finite_positive)

    @model_validator(mode="after")
    def _check_method(self) -> JobCreate:
        if self.method == GROUPING_METHOD:
            if self.pose not in (None, "upright"):
                raise ValueError("a grouping takes no pose other than upright (max_rotation)")
        else:
            if self.model_shape_id is None:
                raise ValueError(f"model_shape_id is required by method {self.method}")
            if self.group_threshold is not None:
                raise ValueError("group_threshold is for method grouping only")
        return self

    @field_validator("working_points", mode="before")
    @classmethod
    def _check_working_points(cls, value: Any) -> Any:
        # the library's one rule, imported here so that the API starts without numpy
        from registration._tree._resolution import check_working_points

        return None if value is None else check_working_points(value)  # ValueError: 422

    @model_validator(mode="after")
    def _check_pose(self) -> JobCreate:
        # The library's own rule (registration._pose.PoseSpec.resolve); imported here, not at
        # module level, so that the API starts without the numerical stack.
        if self.pose is not None or self.max_rotation is not None:
            from registration._pose import PoseSpec

            PoseSpec.resolve(self.pose, self.max_rotation)  # a ValueError is a 422
        return self


class Progress(BaseModel):
    stage: str | None
    done: int
    total: int
    fraction: float | None = Field(
        default=None, ge=0.0, le=1.0,
        description="Estimated share of the whole job done (0-1; it never goes back and "
        "reaches 1 when the job succeeds), from the stages run so far weighted by their "
        "measured cost (a registration's and a grouping's alike); null while no stage is "
        "known.")
    seconds_left: float | None = Field(
        default=None, ge=0.0,
        description="Estimated seconds until the job ends, from the time it has run and "
        "`fraction`; null until 3% is done, and once the job is not running.")


class JobLinks(BaseModel):
    self: str
    result: str
    cancel: str
    deliveries: str | None = None


class JobOut(BaseModel):
    model_config = examples(
        {
            "id": 3,
            "collection_id": 1,
            "model_shape_id": 7,
            "method": "dynamic_tree",
            "params": {
                "similarity_threshold": None,
                "error_threshold": None,
                "compare_direct": True,
                "pose": "upright",
                "max_rotation": 30.0,
                "pose_source": "default for image collections",
                "cpd": {"beta": 2.0, "lmbda": 3.0, "w": 0.1, "max_iter": 150, "tol": 1e-5},
            },
            "n_shapes": 73,
            "status": "running",
            "progress": {"stage": "register", "done": 12, "total": 72},
            "attempts": 1,
            "max_attempts": 3,
            "cancel_requested": False,
            "error": None,
            "created_at": "2026-01-01T12:00:00Z",
            "updated_at": "2026-01-01T12:00:05Z",
            "started_at": "2026-01-01T12:00:01Z",
            "finished_at": None,
            "links": {
                "self": "/v1/jobs/3",
                "result": "/v1/jobs/3/result",
                "cancel": "/v1/jobs/3/cancel",
            },
        },
    )

    id: int
    collection_id: int
    collection_name: str | None = Field(
        default=None, description="The collection's name; null once it is deleted."
    )
    model_shape_id: int | None = Field(
        description="The model shape; null for a grouping, which has no model."
    )
    model_name: str | None = Field(
        default=None,
        description="The model shape's name; null once the shape is deleted, and for a "
        "grouping.",
    )
    method: Method
    params: dict[str, Any] = Field(
        description="The job's options as it runs them: the thresholds, compare_direct, cpd, "
        "and the pose of the pre-alignment resolved from the request (pose, max_rotation) "
        "with pose_source saying where it came from: request, default for image "
        "collections, or default; and max_points, the most points of any of the job's shapes "
        "(above working_points, the job ends registering its tree at the stored resolution)."
    )
    n_shapes: int
    status: JobStatusName
    progress: Progress
    attempts: int
    max_attempts: int
    cancel_requested: bool
    error: str | None = Field(
        description="Why it failed; while queued for a retry, why the last attempt did not end."
    )
    outcome: JobOutcomeName | None = Field(
        default=None,
        description="How it ended (null until then): succeeded, failed, cancelled (while "
        "queued: it never ran, or was waiting for a retry) or aborted (while running: its "
        "worker stopped the registrations in progress). Both of the last have status "
        "cancelled.",
    )
    next_attempt_at: datetime | None = Field(
        default=None,
        description="While queued for a retry (after a transient failure: database busy, a "
        "lost worker), when it may be claimed again; attempts counts those used, up to "
        "max_attempts.",
    )
    callback_url: str | None = None
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    links: JobLinks


class DeliveryAttemptOut(BaseModel):
    attempt: int
    started_at: datetime
    duration_ms: int
    status_code: int | None = Field(description="The receiver's HTTP status; null: no answer.")
    error: str | None = Field(description="null for a 2xx answer, else what went wrong.")


class DeliveriesOut(BaseModel):
    """A job's callback: its state and every try at delivering it."""

    job_id: int
    callback_url: str | None
    state: Literal["none", "waiting", "pending", "delivered", "failed"] = Field(
        description="none: the job has no callback_url; waiting: the job has not ended; "
        "pending: to be tried (again) at next_attempt_at; delivered: a 2xx answer; failed: "
        "every try failed."
    )
    attempts: int
    max_attempts: int | None
    next_attempt_at: datetime | None
    items: list[DeliveryAttemptOut]


# --- results ---------------------------------------------------------------------------------


#: The result document: defined once, in service.contract.result.
ResultOut = ResultDocument


class TransformRequest(BaseModel):
    model_config = examples({"points": [[0.0, 0.0], [1.0, 2.0]]}, extra="forbid")

    points: Annotated[list[Point], Field(min_length=1)] = Field(
        description="Points in the model shape's coordinates: 1 to {max_points_per_shape} "
        "(setting max_points_per_shape).",
        json_schema_extra=bounds(maxItems="max_points_per_shape"),
    )

    @field_validator("points")
    @classmethod
    def _finite(cls, points: list[Point]) -> list[Point]:
        for x, y in points:
            if not (math.isfinite(x) and math.isfinite(y)):
                raise ValueError("every coordinate must be a finite number")
        return points


class TransformOut(BaseModel):
    job_id: int
    shape_id: int
    points: list[Point] = Field(description="The points mapped onto the subject's coordinates.")


class InverseTransformOut(BaseModel):
    job_id: int
    shape_id: int
    points: list[Point | None] = Field(
        description="The points mapped back onto the model's coordinates; null where no "
        "preimage was found (see converged)."
    )
    converged: list[bool] = Field(description="Per point: whether its preimage was found.")

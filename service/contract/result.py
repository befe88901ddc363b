"""Pydantic models of a job's result document, defined once.

The routes use them as ``response_model`` (so OpenAPI describes the result, its subjects,
transforms and similarity), :mod:`service.client` reads the server's JSON through them, and
:mod:`service.plots` reads the summary through them.

Every model allows extra keys: a newer server may add keys (additions only), and a client
keeps what it does not know in ``raw``. Fields that older results lack have defaults; the
rules that fill them (``attached``, ``status``) are :mod:`service.contract.names`'s.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.contract.names import SubjectStatus, is_attached, subject_status

__all__ = [
    "AffineStep",
    "Attempt",
    "ChainTransformDoc",
    "DirectSummary",
    "ErrorStats",
    "GroupedInstance",
    "GroupingDocument",
    "MouldGroupDoc",
    "NearShape",
    "NonrigidStep",
    "NormalizationDoc",
    "Quality",
    "ResultDocument",
    "ShapeNeighbours",
    "SimilarityDocument",
    "SubjectDetail",
    "Summary",
    "TransformStep",
    "TreeNode",
]

Point = tuple[float, float]


class _Open(BaseModel):
    """A model that keeps keys it does not declare (the document may grow)."""

    model_config = ConfigDict(extra="allow")


# --- statistics ------------------------------------------------------------------------------


class ErrorStats(_Open):
    """Count, mean and 95th percentile of e (eq. 10), as the paper reports them
    (``registration.error_statistics``); mean and p95 are null for no subjects."""

    count: int = 0
    mean: float | None = None
    p95: float | None = None


class DirectSummary(_Open):
    """Direct CPD's e on the same subjects, grouped by the tree's layers."""

    layer_ge_3: ErrorStats = Field(default_factory=ErrorStats)
    all: ErrorStats = Field(default_factory=ErrorStats)
    per_layer: dict[str, ErrorStats] = Field(default_factory=dict)


class Summary(_Open):
    """Counts over every subject of the result (whatever a request filters), and e statistics
    at layer >= 3 (where a tree differs from direct CPD), over all attached subjects, and per
    layer (keys are layer numbers as strings); ``direct`` when the job compared with it."""

    subjects: int = 0
    attached: int = Field(default=0, description="Attached subjects, low-confidence leaves too.")
    leaves: int = 0
    unattached: int = 0
    depth: int = 1
    layer_ge_3: ErrorStats = Field(default_factory=ErrorStats)
    all: ErrorStats = Field(default_factory=ErrorStats)
    per_layer: dict[str, ErrorStats] = Field(default_factory=dict)
    direct: DirectSummary | None = None


# --- a subject -------------------------------------------------------------------------------


class Attempt(_Open):
    """One registration tried while building the tree: member -> subject."""

    member: int = Field(description="Position of the member in the job's input.")
    member_shape_id: int | None = Field(default=None, description="The member's shape id.")
    layer: int
    similarity: float | None = None
    error: float | None = None
    limit: float | None = Field(default=None, description="The e threshold it was held to.")
    min_jacobian: float | None = None
    accepted: bool
    reason: str = ""


class Quality(_Open):
    """The checks of a subject's last registration (see ``registration._quality``), the pose
    it started from and the e every pose reached."""

    error: float | None = None
    spacing2: float | None = None
    min_jacobian: float | None = Field(
        default=None, description="The smallest Jacobian determinant of the CPD warp over "
        "the model's points; <= 0: the warp folds the model (confidence 0). On a model drawn "
        "as a lone stroke (most of its points with no model point across them) the stretch "
        "along the stroke stands in at those points: across it the field folds nothing.")
    distortion: float | None = None
    anisotropy: float | None = None
    cpd_rotation: float | None = None
    coverage: float | None = None
    error_ratio: float | None = None
    confidence: float | None = None
    pose: str | None = None
    pose_angle: float | None = None
    pose_errors: dict[str, float | None] | None = None
    pose_margin: float | None = Field(
        default=None, description="The ratio to the pose as given's e below which the "
        "other start's e had to fall to replace it (0.7 for a turn, 0.5 for 'aligned'; the "
        "kept start's when another start was kept). Null when only the pose as given "
        "was tried: no other pose fitted clearly better, or its registration already fitted "
        "within the sampling floor. The other start is 'rotated', or 'aligned' (the pose as "
        "given, aligned by affine ICP) when the model is nearly symmetric under the turn (a "
        "turned O, S or straight stroke), which would only be wrong by the whole turn.")
    pose_compared_by: Literal["e", "subject"] | None = Field(
        default=None, description="What the starts' registrations were compared by: 'e', "
        "or 'subject' (the mean squared distance from each subject point to the nearest "
        "model point alone) when the pose as given left part of the model with no "
        "counterpart on the subject (the subject is part of the model: occluded, cut off), "
        "where e would favour a turn that squeezes the whole model onto the part.")
    leaf_compared_by: Literal["e", "root", "subject"] | None = Field(
        default=None, description="A low-confidence leaf (the tree did not accept it): how "
        "its registration was chosen among those tried. 'e': the lowest e. 'root': the "
        "root's own, when the subject has points scattered off the registered model "
        "(outliers), which e pulls the model over. 'subject': the one closest to every "
        "subject point (the mean squared distance from each subject point to the nearest "
        "model point) when the root's registration leaves part of the model with no "
        "counterpart on the subject (the subject is part of the model: occluded, cut off), "
        "where e would favour squeezing the whole model onto the part; such a leaf is not "
        "polished. Null for subjects the tree accepted.")
    symmetric_edge: bool | None = Field(
        default=None, description="The dynamic tree's edge was made symmetric: CPD's "
        "registration moved halfway to the subject's registered back onto the member.")
    symmetric_edge_reason: str | None = Field(
        default=None, description="Why the edge was not made symmetric (empty when it was).")
    edge_start: Literal["annealed", "held"] | None = Field(
        default=None, description="Which of CPD's two starts the dynamic tree's edge kept, "
        "the one reaching the lower e: 'annealed' from the spread of all pairs (the paper's) "
        "or 'held' from the member's warped model where it lies.")
    edge_start_errors: dict[str, float] | None = Field(
        default=None, description="The e each of CPD's starts reached on the edge.")


class NormalizationDoc(_Open):
    """``u = (p - center) / scale``: a shape's user coordinates to size-normalised ones."""

    center: Point
    scale: float


class AffineStep(_Open):
    """``x -> A x + t`` in normalised coordinates (the affine pre-alignment of an edge)."""

    type: Literal["affine"] = "affine"
    kind: Literal["affine"] = "affine"
    version: int = 1
    A: list[list[float]]
    t: list[float]


class NonrigidStep(_Open):
    """CPD's Gaussian-RBF displacement field (``registration.NonrigidTransform``):
    ``z = (p - model_shift) / model_scale``, ``out = (z + G(z, control_points) coefficients)
    subject_scale + subject_shift``, ``G = exp(-|a - b|^2 / (2 beta^2))``."""

    type: Literal["nonrigid"] = "nonrigid"
    kind: Literal["cpd_nonrigid"] = "cpd_nonrigid"
    version: int = 1
    beta: float
    control_points: list[Point]
    coefficients: list[Point]
    model_shift: Point
    model_scale: float
    subject_shift: Point
    subject_scale: float


#: One step of a transform: every step has ``type`` (``affine`` or ``nonrigid``), ``kind``
#: and ``version``.
TransformStep = Annotated[AffineStep | NonrigidStep, Field(discriminator="type")]


class ChainTransformDoc(_Open):
    """The map from the root model onto a subject (``registration.ChainTransform``): the
    root's normalisation, the steps along the tree path in normalised coordinates, then the
    subject's normalisation inverted. The root's own transform has no steps (identity)."""

    source: NormalizationDoc
    target: NormalizationDoc
    path: list[int] = Field(description="Positions in the job's input, root first.")
    path_shape_ids: list[int | None] | None = Field(
        default=None, description="The same path as shape ids."
    )
    steps: list[TransformStep]


class SubjectDetail(_Open):
    """One subject: its place in the tree, its similarity D and error e, and (with
    ``full=true``, or from ``/result/subjects/{shape_id}``) the model warped onto it, the
    correspondences and the transform.

    ``index``/``parent``/``path`` are positions in the job's input (the library's);
    ``shape_id``/``parent_shape_id``/``path_shape_ids`` the same as shape ids.
    """

    index: int | None = Field(default=None, description="Position in the job's input.")
    position: int | None = Field(default=None, description="Position in the job's input.")
    shape_id: int
    name: str = ""
    parent: int | None = Field(default=None, description="The parent's position; null: none.")
    parent_shape_id: int | None = None
    layer: int | None = Field(
        default=None,
        description="Depth in the tree: the root is layer 1, a subject one more than its "
        "parent (the length of its path); null: unattached.",
    )
    path: list[int] = Field(default_factory=list, description="Positions, root to subject.")
    path_shape_ids: list[int | None] = Field(default_factory=list)
    similarity: float | None = Field(default=None, description="D (eq. 9) from the parent.")
    error: float | None = Field(default=None, description="e (eq. 10) on normalised shapes.")
    direct_error: float | None = Field(default=None, description="Direct CPD's e, if compared.")
    attached: bool = False
    status: SubjectStatus = "unattached"
    confidence: float | None = Field(
        default=None, description="Estimated probability (0 to 1) that its correspondences "
        "are right; null when unattached."
    )
    disagreement: float | None = Field(
        default=None, description="How far apart two registrations of the subject that err "
        "differently put the model's points (the polish's, and the subject registered back onto "
        "the model: its symmetric finish), RMS in units of the subject's RMS radius. A second "
        "sign beside confidence: where they disagree, at least one is off by about that much; "
        "where they agree, both may have slid alike. Null when no symmetric finish ran (direct "
        "CPD, the static tree, polish off, the root, unattached subjects)."
    )
    leaf: bool = Field(default=False, description="A low-confidence leaf, never a parent.")
    root: bool = Field(default=False, description="The model itself (identity transform).")
    reason: str = ""
    quality: Quality | None = None
    attempts: list[Attempt] = Field(default_factory=list)
    warped: list[Point] | None = Field(
        default=None, description="The model warped onto the subject, subject coordinates."
    )
    correspondence: list[int] | None = Field(
        default=None, description="For each model point, the index of its subject point."
    )
    probability: list[float] | None = None
    transform: ChainTransformDoc | None = None
    direct: SubjectDetail | None = Field(
        default=None, description="Direct CPD's registration of this subject, if compared."
    )

    @model_validator(mode="before")
    @classmethod
    def _derived(cls, data: Any) -> Any:
        """``attached`` and ``status`` by the one rule, for documents that lack them."""
        if isinstance(data, dict) and ("attached" not in data or "status" not in data):
            data = dict(data)
            data.setdefault("attached", is_attached(data))
            data.setdefault("status", subject_status(data))
        return data


# --- the document ----------------------------------------------------------------------------


class TreeNode(_Open):
    """A node of the tree by shape id: the root, a member, or a low-confidence leaf."""

    shape_id: int
    name: str = ""
    parent_shape_id: int | None = None
    layer: int | None = None
    status: Literal["root", "tree", "leaf"]
    children_shape_ids: list[int] = Field(default_factory=list)


class ResultDocument(_Open):
    """A job's result (``GET /v1/jobs/{id}/result``): the tree and, per subject, its place,
    similarity D, error e, confidence and quality.

    Subjects name shapes by ``shape_id``; ``parent_shape_id`` and ``path_shape_ids`` give the
    tree (``tree`` lists its nodes by shape id, root included). Each subject has
    ``confidence`` (0 to 1, the estimated probability that its correspondences are right;
    null when unattached), ``disagreement`` (how far apart two registrations that err
    differently put the model's points, in units of its RMS radius; null where no
    symmetric finish ran), ``leaf`` (true for a low-confidence leaf: given its best
    registration after the tree stopped growing, never a parent; its ``reason`` says why)
    and ``quality`` (the checks of its last registration). Heavy arrays (warped points,
    correspondences, transforms) are left out unless ``?full=true``;
    ``/result/subjects/{shape_id}`` always has them. ``summary`` counts over all subjects
    (``subjects``, ``attached`` with leaves, ``leaves``, ``unattached``), whatever
    ``min_confidence`` and ``leaf`` list.
    """

    job_id: int
    method: str
    root: int | None = Field(default=None, description="The model's position in the input.")
    root_shape_id: int
    shape_ids: list[int] = Field(default_factory=list, description="The job's input, in order.")
    names: list[str] = Field(default_factory=list, description="Shape names, input order.")
    thresholds: dict[str, Any] = Field(default_factory=dict)
    options: dict[str, Any] = Field(default_factory=dict)
    similarity_pairs: int = Field(default=0, description="ICP runs done for the similarity.")
    summary: Summary = Field(default_factory=Summary)
    subjects: list[SubjectDetail] = Field(default_factory=list)
    tree: list[TreeNode] | None = Field(
        default=None, description="The tree's nodes by shape id: the root first, then every "
        "attached subject in input order (results from before it was added lack it)."
    )


# --- the similarity --------------------------------------------------------------------------


class NearShape(_Open):
    """A shape near another one, with D from it onto the other."""

    shape_id: int
    name: str = ""
    D: float


class ShapeNeighbours(_Open):
    """A shape of the job and its nearest shapes: the smallest D(other -> this shape)."""

    shape_id: int
    name: str = ""
    nearest: list[NearShape]


class SimilarityDocument(_Open):
    """The similarity D (eq. 9) a job computed (``GET /v1/jobs/{id}/similarity``).

    ``D[i][j]`` is D from shape ``shape_ids[i]`` (moved by the affine map) onto shape
    ``shape_ids[j]``, on size-normalised shapes: the direction the tree uses (a member onto a
    subject). It is not symmetric; null for pairs the job did not need (the dynamic tree
    computes D lazily); 0 on the diagonal.
    """

    job_id: int
    shape_ids: list[int]
    names: list[str]
    direction: str = "D[i][j]: shape_ids[i] moved onto shape_ids[j] (member -> subject)"
    computed_pairs: int = Field(description="Off-diagonal pairs with a value.")
    D: list[list[float | None]] | None = Field(
        default=None, description="The matrix (left out with matrix=false)."
    )
    nearest: list[ShapeNeighbours] = Field(
        description="For each shape, the k other shapes with the smallest D onto it."
    )


# --- a grouping job's result (method grouping, issue 11) ---------------------------------------


class GroupedInstance(_Open):
    """One shape of a grouping: its group and how sure that is."""

    position: int = Field(description="Position in the job's input (shape_ids order).")
    shape_id: int
    name: str = ""
    label: int = Field(description="Its group (groups are numbered by decreasing size).")
    confidence: float = Field(
        description="Silhouette in [0, 1]: (b - a) / b with a its mean distance to its "
        "group and b the smallest mean distance to another group; 0 when alone."
    )
    representative_shape_id: int
    distance_to_representative: float
    dropped_points: int = Field(0, description="Points dropped as ink specks.")


class MouldGroupDoc(_Open):
    label: int
    size: int
    shape_ids: list[int]
    representative_shape_id: int = Field(description="The member nearest the others.")
    spread: float = Field(description="Largest distance of a member to the representative.")


class GroupingDocument(_Open):
    """``GET /v1/jobs/{job_id}/groups``: which shapes came from one mould."""

    kind: Literal["grouping"] = "grouping"
    job_id: int
    shape_ids: list[int]
    names: list[str] = Field(default_factory=list)
    n_groups: int
    threshold: float = Field(description="Cut of the average-linkage tree (RMS radius units).")
    threshold_source: str
    noise_level: float = Field(description="Median distance of a shape to its nearest other.")
    pairs_computed: int = 0
    labels: dict[str, int] = Field(description="Group label by shape id.")
    instances: list[GroupedInstance]
    groups: list[MouldGroupDoc]
    distances: list[list[float]] = Field(
        description="Mould distances in shape_ids order (units: the shapes' RMS radius)."
    )
    linkage: list[list[float]] = Field(
        default_factory=list, description="Average-linkage tree, scipy's format."
    )

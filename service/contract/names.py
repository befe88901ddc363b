"""The vocabulary of the API, written once: every surface (schemas, routes, runner, client,
CLI, plots) takes its names from here.

Standard library only, so that the ``regtree`` command line can import it before numpy (it
limits BLAS threads first).
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import StrEnum
from typing import Any, Literal, get_args

__all__ = [
    "DEFAULT_COMPARE_DIRECT",
    "DEFAULT_IMAGE_MODE",
    "DEFAULT_METHOD",
    "DEFAULT_ON_CONFLICT",
    "DEFAULT_WORKING_POINTS",
    "GROUPING_METHOD",
    "IMAGE_MODES",
    "IMAGE_SOURCE_PREFIXES",
    "JOB_STATUSES",
    "METHODS",
    "METHOD_FUNCTIONS",
    "ON_CONFLICT_POLICIES",
    "POSES",
    "REGISTRATION_METHODS",
    "SUBJECT_SORTS",
    "SUBJECT_STATUSES",
    "TERMINAL_STATUSES",
    "ImageMode",
    "JobOutcomeName",
    "JobStatusName",
    "Method",
    "OnConflict",
    "PoseName",
    "ProblemType",
    "SubjectSort",
    "SubjectStatus",
    "is_attached",
    "made_from_image",
    "subject_status",
]

#: Methods of a job (the library's function for each: :data:`METHOD_FUNCTIONS`): three
#: registrations, and ``grouping`` (which instances came from one mould, issue 11; no model).
Method = Literal["dynamic_tree", "static_tree", "direct", "grouping"]
METHODS: tuple[str, ...] = get_args(Method)
GROUPING_METHOD: Method = "grouping"
#: The methods that register a model onto the collection (a result with subjects and a tree).
REGISTRATION_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m != GROUPING_METHOD)
DEFAULT_METHOD: Method = "dynamic_tree"
#: Whether a job also registers every subject directly from the model, for comparison: off
#: on every surface (library, HTTP, client, CLI), since it doubles the registrations and the
#: tree's own result does not need it.
DEFAULT_COMPARE_DIRECT = False
#: Points per shape a job decides its tree at (similarity, candidates, acceptance); every
#: edge is then registered once at the stored resolution, warm-started from that decision,
#: the dynamic tree's subjects are polished again there, and the result is at the stored
#: resolution. None or 0: decide at the stored resolution.
#: The library's default (``registration._tree._resolution.DEFAULT_WORKING_POINTS``; a
#: test checks that they agree).
DEFAULT_WORKING_POINTS: int | None = 400
#: The library function (``registration.<name>``) that runs each method.
METHOD_FUNCTIONS: dict[str, str] = {
    "dynamic_tree": "build_dynamic_tree",
    "static_tree": "build_static_tree",
    "direct": "register_direct",
    "grouping": "group_instances",
}

#: How an uploaded image becomes points: its outer contours, its edges, or the centre lines
#: of its strokes.
ImageMode = Literal["contour", "edges", "skeleton"]
IMAGE_MODES: tuple[str, ...] = get_args(ImageMode)
DEFAULT_IMAGE_MODE: ImageMode = "contour"

#: What an upload does with a name the collection already holds: ``refuse`` (the default:
#: a 409 naming the existing shapes, nothing stored), ``replace`` them, or ``keep`` both.
OnConflict = Literal["refuse", "replace", "keep"]
ON_CONFLICT_POLICIES: tuple[str, ...] = get_args(OnConflict)
DEFAULT_ON_CONFLICT: OnConflict = "refuse"

#: The pose modes of the affine pre-alignment: ``registration._pose.POSE_MODES`` (a test
#: checks that they agree; the library is not imported here, so the API starts fast).
PoseName = Literal["as_given", "upright", "rotation", "affine"]
POSES: tuple[str, ...] = get_args(PoseName)

JobStatusName = Literal["queued", "running", "succeeded", "failed", "cancelled"]
#: How a job ended (``service.models.JobOutcome``): ``cancelled`` while queued, ``aborted``
#: while running (both have status ``cancelled``).
JobOutcomeName = Literal["succeeded", "failed", "cancelled", "aborted"]
JOB_STATUSES: tuple[str, ...] = get_args(JobStatusName)
TERMINAL_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})

#: Orders of a result's subjects (``sort`` of ``GET /v1/jobs/{id}/result``): a key,
#: descending with a leading "-".
SubjectSort = Literal["position", "confidence", "-confidence", "error", "-error",
                      "disagreement", "-disagreement"]
SUBJECT_SORTS: tuple[str, ...] = get_args(SubjectSort)

#: Where a subject ended up: a tree member, a low-confidence leaf (attached, never a parent),
#: or unattached.
SubjectStatus = Literal["tree", "leaf", "unattached"]
SUBJECT_STATUSES: tuple[str, ...] = get_args(SubjectStatus)


class ProblemType(StrEnum):
    """The ``type`` of the API's problem documents (RFC 9457), relative URIs."""

    BODY_TOO_LARGE = "/problems/body-too-large"
    CALLBACK_REFUSED = "/problems/callback-refused"
    COLLECTION_FULL = "/problems/collection-full"
    DUPLICATE_NAMES = "/problems/duplicate-names"
    IDEMPOTENCY_KEY_REUSED = "/problems/idempotency-key-reused"
    INTERNAL = "/problems/internal"
    INVALID_JOB = "/problems/invalid-job"
    INVALID_SHAPE = "/problems/invalid-shape"
    JOB_FINISHED = "/problems/job-finished"
    NAME_CONFLICT = "/problems/name-conflict"
    NO_SIMILARITY = "/problems/no-similarity"
    NO_TRANSFORM = "/problems/no-transform"
    NOT_A_GROUPING = "/problems/not-a-grouping"
    NOT_A_REGISTRATION = "/problems/not-a-registration"
    NOT_FOUND = "/problems/not-found"
    RESULT_NOT_READY = "/problems/result-not-ready"
    SHAPE_DELETED = "/problems/shape-deleted"
    SHAPE_IN_USE = "/problems/shape-in-use"
    TRANSFORM = "/problems/transform"
    UNAUTHORIZED = "/problems/unauthorized"
    UNAVAILABLE = "/problems/unavailable"
    UNSUPPORTED_MEDIA_TYPE = "/problems/unsupported-media-type"
    VALIDATION_ERROR = "/problems/validation-error"


#: ``source_format`` prefixes of shapes made from an image (PNG or JPEG upload): their points
#: are pixel coordinates (y grows downwards) and their pose is the image's.
IMAGE_SOURCE_PREFIXES = ("png:", "jpeg:", "image:")


def made_from_image(source_format: str) -> bool:
    """Whether a shape with this ``source_format`` was made from an uploaded image: the
    pictures of every surface (HTTP, export, CLI) then draw it with y growing downwards."""
    return source_format.startswith(IMAGE_SOURCE_PREFIXES)


def is_attached(subject: Mapping[str, Any]) -> bool:
    """Whether a subject of a result document has a place in the tree (a layer and a parent,
    or the root itself): tree members and low-confidence leaves are, unattached subjects not.

    The result document states it as ``attached``; documents from before that key existed
    say it by their ``layer`` (None when unattached). The library's rule is the same
    (``SubjectResult.attached``).
    """
    value = subject.get("attached")
    if isinstance(value, bool):
        return value
    return subject.get("layer") is not None


def subject_status(subject: Mapping[str, Any]) -> SubjectStatus:
    """``leaf`` (a low-confidence leaf), ``tree`` (a member) or ``unattached``."""
    if subject.get("leaf"):
        return "leaf"
    return "tree" if is_attached(subject) else "unattached"

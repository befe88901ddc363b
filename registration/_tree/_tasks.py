"""Task plumbing of the tree methods: one registration of a member's warped model onto a
subject (every start pose, CPD, quality; one kept), and a batch of them run on an executor."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any, ParamSpec, TypeVar

import numpy as np
from numpy.typing import NDArray

from .._cpd import CPDOptions, cpd_nonrigid
from .._error import registration_error
from .._executor import Executor, owned_executor
from .._icp import affine_icp
from .._pointmap import PointTransform
from .._pose import PoseSpec, angle_between, rotation_angle
from .._quality import RegistrationQuality, measure_quality
from .._similarity import ProgressCallback, Similarity
from .._transform import AffineTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
P = ParamSpec("P")
R = TypeVar("R")
T = TypeVar("T")

# A pose that differs from the pose as given by more than POSE_DISTINCT_DEG (or in
# handedness) and whose D is below POSE_D_RATIO times the pose as given's is registered
# too; it replaces the pose as given only when its e is below POSE_MARGIN times the pose
# as given's (see `_starts` and `_register_task`). Measured on ground truth
# (bench/calibrate_thresholds.py): on collections given upright every rotated pose was
# wrong (0 of 82 good) and its D was 0.34-0.97 (median 0.78-0.81) of the pose as given's;
# on glyphs turned by 90 degrees 63-78% of them were right, at 0.07-0.65 (median 0.23-0.26).
POSE_DISTINCT_DEG = 20.0
POSE_D_RATIO = 0.6
POSE_MARGIN = 0.5


@dataclass(frozen=True)
class _Start:
    """A pose to start a registration from: the pose as given (no affine step: CPD runs
    on the size-normalised shapes as they are) or an affine-ICP map of another pose."""

    label: str  # "as given" or "rotated"
    A: FloatArray | None = None
    t: FloatArray | None = None


@dataclass(frozen=True)
class _RegTask:
    subject: int
    member: int
    layer: int
    similarity: float
    q: FloatArray  # root model warped onto the member, normalised coordinates
    y: FloatArray  # subject, normalised coordinates
    starts: tuple[_Start, ...]  # the pose as given first
    cpd: CPDOptions
    prealign: bool
    pose: PoseSpec
    spacing2: float  # the subject's squared point spacing h^2


@dataclass(frozen=True)
class _RegOutcome:
    subject: int
    member: int
    layer: int
    similarity: float
    warped: FloatArray  # normalised coordinates of the subject
    error: float
    min_jacobian: float
    correspondence: IntArray
    probability: FloatArray
    steps: tuple[PointTransform, ...]
    pose: str  # which start was kept: "as given", "rotated" or "plain" (prealign=False)
    pose_angle: float  # rotation of the pre-alignment, degrees (0 without one)
    pose_errors: dict[str, float]  # e reached from every start tried
    quality: RegistrationQuality


def _register_from(task: _RegTask, start: _Start | None) -> _RegOutcome:
    steps: list[PointTransform] = []
    q = task.q
    angle = 0.0
    if start is not None and start.A is not None and start.t is not None:
        icp = affine_icp(q, task.y, init=(start.A, start.t), pose=task.pose.mode,
                         max_rotation=task.pose.max_rotation)
        affine = AffineTransform(A=icp.A, t=icp.t)
        steps.append(affine)
        q = affine.apply(q)
        angle = rotation_angle(icp.A)
    o = task.cpd
    res = cpd_nonrigid(q, task.y, beta=o.beta, lmbda=o.lmbda, w=o.w, max_iter=o.max_iter, tol=o.tol,
                       dtype=o.dtype)
    steps.append(res.transform)
    warped = np.asarray(res.warped, dtype=np.float64)
    e = registration_error(warped, task.y)
    quality = measure_quality(q, warped, task.y, res.transform, e, task.spacing2)
    label = "plain" if start is None else start.label
    return _RegOutcome(
        subject=task.subject,
        member=task.member,
        layer=task.layer,
        similarity=task.similarity,
        warped=warped,
        error=e,
        min_jacobian=quality.min_jacobian,
        correspondence=np.asarray(res.correspondence, dtype=np.intp),
        probability=np.asarray(res.probability, dtype=np.float64),
        steps=tuple(steps),
        pose=label,
        pose_angle=angle,
        pose_errors={label: e},
        quality=quality,
    )


def _register_task(task: _RegTask) -> _RegOutcome:
    """Register the member's warped model onto the subject from every start; keep one.

    The pose as given (the first start) is kept unless another start's registration does
    not fold and reaches an e below ``POSE_MARGIN`` times the pose as given's, or the
    pose as given folds and the other reaches no larger an e. A rotated pose thus earns
    its place by the registration it leads to, not by D alone.
    """
    if not task.prealign:
        return _register_from(task, None)
    outs = [_register_from(task, st) for st in task.starts]
    chosen = outs[0]
    for other in outs[1:]:
        if not other.min_jacobian > 0:
            continue
        folded = not chosen.min_jacobian > 0
        if other.error < POSE_MARGIN * chosen.error or (folded and other.error <= chosen.error):
            chosen = other
    errors = {o.pose: o.error for o in outs}
    return replace(chosen, pose_errors=errors)


def _starts(sim: Similarity, member: int, subject: int) -> tuple[_Start, ...]:
    """The pose as given; and the similarity's best pose when it is another pose (turned
    by more than ``POSE_DISTINCT_DEG`` or of the other handedness) that fits clearly
    better: its D below ``POSE_D_RATIO`` times the D reached from the pose as given."""
    given = _Start("as given")
    A = sim.A[member, subject]
    A_g = sim.A_given[member, subject]
    d, d_g = sim.D[member, subject], sim.D_given[member, subject]
    if not (np.isfinite(d) and np.isfinite(d_g)) or not d < POSE_D_RATIO * d_g:
        return (given,)
    distinct = (np.sign(np.linalg.det(A)) != np.sign(np.linalg.det(A_g))
                or angle_between(rotation_angle(A), rotation_angle(A_g)) > POSE_DISTINCT_DEG)
    if not distinct:
        return (given,)
    return (given, _Start("rotated", A, sim.t[member, subject]))


def _owns_executor(fn: Callable[P, R]) -> Callable[P, R]:
    """Run a method with one executor for all its stages: the caller's, or a default one
    (a local pool for larger collections) that is closed when the method returns."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        shapes = args[0] if args else kwargs["shapes"]
        given = kwargs.get("executor")
        with owned_executor(given, len(shapes) ** 2) as ex:  # type: ignore[arg-type]
            kwargs["executor"] = ex
            return fn(*args, **kwargs)

    return wrapper


def _run_tasks(
    tasks: list[_RegTask],
    executor: Executor | None,
    progress: ProgressCallback | None,
    stage: str,
) -> list[_RegOutcome]:
    """Every registration of `tasks`, on the executor, in the order of the tasks."""
    return _map_tasks(_register_task, tasks, executor, progress, stage)


def _map_tasks(
    fn: Callable[[T], R],
    tasks: list[T],
    executor: Executor | None,
    progress: ProgressCallback | None,
    stage: str,
) -> list[R]:
    """``fn`` (a picklable top-level function) on every task, on the executor, reporting
    progress as `stage`; the results in the order of the tasks."""
    if not tasks:
        return []
    results: list[R | None] = [None] * len(tasks)
    with owned_executor(executor, 8 * len(tasks)) as ex:
        if progress is not None:
            progress(stage, 0, len(tasks))
        done = 0
        for pos, out in ex.map_unordered(fn, tasks):
            results[pos] = out
            done += 1
            if progress is not None:
                progress(stage, done, len(tasks))
    return [r for r in results if r is not None]


def _options_dict(
    cpd: CPDOptions, prealign: bool, max_candidates: int, pose: PoseSpec
) -> dict[str, Any]:
    return {"cpd": asdict(cpd), "affine_prealign": prealign, "max_candidates": max_candidates,
            **pose.to_dict()}

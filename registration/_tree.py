"""The dynamic tree of Du et al. 2016 (section 3.3) and the baselines it is compared with.

All three methods register the root model to every other shape of a collection:

- :func:`build_dynamic_tree`: layer by layer, each waiting subject that is similar
  (affine-ICP distance D below the similarity threshold) to a tree member not yet tried
  for it is registered from that member: the root model *as already warped onto the
  member* is pre-aligned by affine ICP and warped by CPD onto the subject. The subject is
  accepted when e (eq. 10) is below the error threshold and the CPD displacement field
  does not fold the model; otherwise it waits for a later layer. Growth stops when every
  subject is attached or a layer adds nothing; what is left is reported unattached.
- :func:`build_static_tree`: the heuristic tree of Du et al. 2015: the same layered
  growth over the similarity graph, each subject attached to its most similar member of
  the previous layer, without any rejection; then CPD along the tree's edges.
- :func:`register_direct`: CPD from the root to every subject.

Direction of D: ``D[m, s]`` is computed with the member ``m`` as the moving model and the
subject ``s`` fixed, matching the direction of the registration that follows.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, ParamSpec, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from ._cpd import cpd_nonrigid
from ._error import registration_error
from ._executor import Executor, owned_executor
from ._icp import affine_icp
from ._points import Normalization, normalise
from ._pose import PoseSpec, angle_between, rotation_angle
from ._quality import RegistrationQuality, measure_quality
from ._result import Attempt, CollectionResult, SubjectResult
from ._similarity import ProgressCallback, Similarity, candidate_pairs
from ._transform import AffineTransform, ChainTransform, PointTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
P = ParamSpec("P")
R = TypeVar("R")

__all__ = [
    "CPDOptions",
    "build_dynamic_tree",
    "build_static_tree",
    "register_direct",
]

# Automatic thresholds (see `_similarity_limits` and `_auto_error_threshold`).
CAPTURE_D = 0.01
SIMILAR_NEIGHBOURS = 4
ERROR_FACTOR = 3.0
SPACING_FACTOR = 0.5
MAX_EXHAUSTIVE_SHAPES = 64
DEFAULT_CANDIDATES = 12
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
# A registration is accepted into the tree only with at least this confidence (the
# calibrated probability that its correspondences are right; `_quality`). Measured in
# bench/calibrate_thresholds.py: 1.1% of the registrations scored below 0.2 were good
# (95 of 742, mostly turned, mirrored and slid ones that e alone accepts).
MIN_CONFIDENCE = 0.2
# Refinement moves a subject when the new path confidence is higher by more than this, or
# within it and with a lower e.
REFINE_TIE = 0.02


@dataclass(frozen=True)
class CPDOptions:
    """Options of the CPD non-rigid registration used on every tree edge.

    The algorithm's defaults follow the reference MATLAB implementation of Myronenko & Song
    (2010); the E-step runs in float32 unless ``dtype="float64"``.
    """

    beta: float = 2.0
    lmbda: float = 3.0
    w: float = 0.1
    max_iter: int = 150
    tol: float = 1e-5
    #: Precision of CPD's E-step (see :func:`cpd_nonrigid`). float32 by default: on the 73
    #: 永 edge glyphs (400 points) it built the same tree as float64 (72 of 72 parents), e
    #: within 2e-5 relative, 1.35x faster end to end (bench/RESULTS.md).
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.dtype not in ("float64", "float32"):
            raise ValueError(f"dtype must be 'float64' or 'float32'; got {self.dtype!r}")
        if not (self.beta > 0 and self.lmbda > 0):
            raise ValueError(f"beta and lmbda must be positive; got {self.beta}, {self.lmbda}")
        if not 0 <= self.w < 1:
            raise ValueError(f"w must be in [0, 1); got {self.w}")
        if self.max_iter < 1:
            raise ValueError(f"max_iter must be at least 1; got {self.max_iter}")
        if not self.tol > 0:
            raise ValueError(f"tol must be positive; got {self.tol}")


# ----------------------------------------------------------------------------- tasks


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


# ----------------------------------------------------------------------------- setup


@dataclass
class _Collection:
    normed: list[FloatArray]
    norms: list[Normalization]
    names: list[str]
    root: int
    spacing2: list[float]  # each shape's mean squared nearest-neighbour spacing h^2

    @classmethod
    def prepare(
        cls, shapes: Sequence[ArrayLike], root: int, names: Sequence[str] | None
    ) -> _Collection:
        if len(shapes) < 2:
            raise ValueError(f"need at least 2 shapes (a root and a subject); got {len(shapes)}")
        if not 0 <= root < len(shapes):
            raise ValueError(
                f"root must be an index into shapes (0..{len(shapes) - 1}); got {root}"
            )
        if names is not None and len(names) != len(shapes):
            raise ValueError(f"names has {len(names)} entries for {len(shapes)} shapes")
        normed, norms = [], []
        for k, s in enumerate(shapes):
            p, nm = normalise(s, name=f"shapes[{k}]")
            normed.append(p)
            norms.append(nm)
        label = list(names) if names is not None else [f"shape-{k}" for k in range(len(shapes))]
        return cls(normed=normed, norms=norms, names=label, root=root,
                   spacing2=[_spacing2(p) for p in normed])

    @property
    def n(self) -> int:
        return len(self.normed)

    def root_chain(self) -> ChainTransform:
        r = self.root
        return ChainTransform(source=self.norms[r], target=self.norms[r], steps=(), path=(r,))


@dataclass
class _Node:
    q: FloatArray  # root model warped onto this member (normalised coords of the member)
    chain: ChainTransform
    layer: int
    confidence: float = 1.0  # the weakest registration on the path from the root


def _subject_from_outcome(
    coll: _Collection, out: _RegOutcome, parent: _Node, *, layer: int | None = None,
    leaf: bool = False,
) -> tuple[SubjectResult, _Node]:
    s = out.subject
    chain = parent.chain.extended(out.steps, coll.norms[s], s)
    layer = out.layer if layer is None else layer
    confidence = min(parent.confidence, out.quality.confidence)
    res = SubjectResult(
        index=s,
        name=coll.names[s],
        parent=out.member,
        layer=layer,
        path=list(chain.path),
        similarity=out.similarity,
        error=out.error,
        warped=coll.norms[s].invert(out.warped),
        correspondence=out.correspondence,
        probability=out.probability,
        transform=chain,
        confidence=confidence,
        leaf=leaf,
        quality={**out.quality.to_dict(), "pose": out.pose, "pose_angle": out.pose_angle,
                 "pose_errors": dict(out.pose_errors)},
    )
    return res, _Node(q=out.warped, chain=chain, layer=layer, confidence=confidence)


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
    if not tasks:
        return []
    results: list[_RegOutcome | None] = [None] * len(tasks)
    with owned_executor(executor, 8 * len(tasks)) as ex:
        if progress is not None:
            progress(stage, 0, len(tasks))
        done = 0
        for pos, out in ex.map_unordered(_register_task, tasks):
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


# ----------------------------------------------------------------------------- thresholds


@dataclass(frozen=True)
class _SimilarityRule:
    """Which (member, subject) pairs count as similar.

    Explicit: ``D <= threshold`` for every pair, as in the paper. Automatic: ``D`` at
    most the largest of ``CAPTURE_D``, the D from the subject's ``SIMILAR_NEIGHBOURS``-th
    nearest shape and the D to the member's ``SIMILAR_NEIGHBOURS``-th nearest shape
    (a k-nearest-neighbour graph, both ways), so that

    - a pair within CPD's capture range is always similar: measured on data with ground
      truth (bench/calibrate_thresholds.py), after the affine pre-alignment 95% of pairs
      with D < 0.01 registered with an RMS correspondence error under 5% of the shape's
      size, against 65% for 0.01-0.02 and 26% for 0.02-0.04;
    - every shape, the root included, has a few similar shapes whatever the scale of D in
      the collection (D grows with genuine shape variety and shrinks with denser
      sampling), so a far subject waits for one of its nearest shapes to join the tree
      and is registered from it, which is the point of the tree.
    """

    explicit: float | None
    into: dict[int, float]  # subject -> D from its k-th nearest shape
    out_of: dict[int, float]  # member -> D to its k-th nearest shape

    @classmethod
    def build(cls, sim: Similarity, explicit: float | None) -> _SimilarityRule:
        if explicit is not None:
            return cls(explicit=explicit, into={}, out_of={})
        n = sim.D.shape[0]
        off = ~np.eye(n, dtype=bool)

        def kth(values: FloatArray) -> float:
            v = np.sort(values[np.isfinite(values)])
            return float(v[min(SIMILAR_NEIGHBOURS, v.size) - 1]) if v.size else 0.0

        return cls(
            explicit=None,
            into={s: kth(sim.D[:, s][off[:, s]]) for s in range(n)},
            out_of={m: kth(sim.D[m, :][off[m, :]]) for m in range(n)},
        )

    def limit(self, member: int, subject: int) -> float:
        if self.explicit is not None:
            return self.explicit
        return max(CAPTURE_D, self.into[subject], self.out_of[member])

    def similar(self, sim: Similarity, member: int, subject: int) -> bool:
        d = sim.D[member, subject]
        return bool(np.isfinite(d) and d <= self.limit(member, subject))


def _similarity_report(rule: _SimilarityRule) -> dict[str, Any]:
    values = list(rule.into.values())
    return {
        "similarity": rule.explicit if rule.explicit is not None
        else max(CAPTURE_D, float(np.median(values))) if values else None,
        "similarity_rule": "explicit" if rule.explicit is not None
        else f"auto, per pair: max({CAPTURE_D}, D from the subject's {SIMILAR_NEIGHBOURS}th "
        f"nearest shape, D to the member's {SIMILAR_NEIGHBOURS}th nearest shape); "
        "'similarity' is the median over subjects",
    }


def _auto_error_threshold(outcomes: Sequence[_RegOutcome]) -> float:
    """``ERROR_FACTOR`` times the lower quartile of the second layer's e.

    Those are registrations of the root to the subjects similar to it. The best of them
    measure what "registered" means for this collection (its point density, noise and
    genuine shape variation); failed registrations sit an order of magnitude above
    (generated families: 2e-4 to 5e-4 against about 5e-3). The lower quartile rather
    than the median, because every shape's few nearest shapes count as similar, so the
    root's similar subjects can include far ones that fail. Applied per subject together
    with a floor from the subject's own sampling (:func:`_spacing_floor`).
    """
    errs = [o.error for o in outcomes if math.isfinite(o.error)]
    if not errs:
        return math.inf
    return ERROR_FACTOR * float(np.percentile(errs, 25))


def _spacing2(normalised: FloatArray) -> float:
    """Mean squared nearest-neighbour spacing h^2 of a shape's points."""
    d, _ = cKDTree(normalised).query(normalised, k=2)
    return float(np.mean(d[:, 1] ** 2))


def _spacing_floor(spacing2: float) -> float:
    """``SPACING_FACTOR`` times the subject's mean squared nearest-neighbour spacing h^2.

    An e below it means the warped model lies on the subject as closely as the sampling
    allows. Measured on data with ground truth (bench/calibrate_thresholds.py): every
    registration with an RMS correspondence error under 5% of the shape's size had
    e < 0.5 h^2. Without this floor a collection whose easiest subjects register almost
    exactly (synthetic deformations of the same points) gets an error threshold so small
    that even correct registrations of its harder subjects are refused.
    """
    return SPACING_FACTOR * spacing2


def _prepare_similarity(
    coll: _Collection,
    similarity_threshold: float | None,
    candidates: int | None,
    executor: Executor | None,
    progress: ProgressCallback | None,
    pose: PoseSpec,
) -> tuple[Similarity, set[tuple[int, int]] | None]:
    """Build the similarity store; compute up front what the automatic threshold needs.

    Returns the store and the allowed pairs (None: any pair, computed lazily).
    """
    sim = Similarity.empty(coll.normed, pose=pose)
    allowed: set[tuple[int, int]] | None = None
    if candidates is None and coll.n > MAX_EXHAUSTIVE_SHAPES:
        candidates = DEFAULT_CANDIDATES
    if candidates is not None:
        allowed = set(candidate_pairs(coll.normed, candidates))
        # the root may always be tried: direct registration is the paper's first layer
        allowed |= {(coll.root, s) for s in range(coll.n) if s != coll.root}
    if similarity_threshold is None:
        if allowed is None:
            pairs = [(i, j) for i in range(coll.n) for j in range(coll.n) if i != j]
        else:
            pairs = sorted(allowed)
        sim.ensure(pairs, executor=executor, progress=progress)
    return sim, allowed


def _ensure_frontier(
    sim: Similarity,
    frontier: Sequence[int],
    waiting: set[int],
    allowed: set[tuple[int, int]] | None,
    executor: Executor | None,
    progress: ProgressCallback | None,
    layer: int,
) -> None:
    """Compute D from the newest members to the waiting subjects (lazily: only the pairs
    that can give a subject its next candidate)."""
    pairs = [(m, s) for m in frontier for s in sorted(waiting)]
    if allowed is not None:
        pairs = [p for p in pairs if p in allowed]
    sim.ensure(pairs, executor=executor, progress=progress, stage=f"similarity layer {layer}")


def _check_threshold(name: str, value: float | None) -> None:
    if value is not None and not (value > 0 and math.isfinite(value)):
        raise ValueError(f"{name} must be a positive finite number or None; got {value}")


def _error_limit(tau_err: float, explicit: bool, floor: float) -> float:
    """The e a subject's registration must stay below: the explicit threshold, or the
    automatic one raised to the subject's sampling floor."""
    return tau_err if explicit else max(tau_err, floor)


def _rejection(out: _RegOutcome, limit: float, fold_check: bool) -> str | None:
    """Why the tree's rule refuses a registration (None: it accepts it): a fold, e at or
    above `limit`, or a confidence below ``MIN_CONFIDENCE``, checked in that order."""
    if fold_check and not out.min_jacobian > 0:
        return "folded (Jacobian determinant <= 0)"
    if not out.error < limit:
        return f"e={out.error:.4g} >= error threshold {limit:.4g}"
    if not out.quality.confidence >= MIN_CONFIDENCE:
        return f"confidence {out.quality.confidence:.2f} < {MIN_CONFIDENCE}"
    return None


def _refine_parents(
    coll: _Collection,
    sim: Similarity,
    sim_rule: _SimilarityRule,
    nodes: dict[int, _Node],
    results: dict[int, SubjectResult],
    tried: set[tuple[int, int]],
    tau_err: float | None,
    floors: dict[int, float],
    explicit_error: bool,
    fold_check: bool,
    cpd: CPDOptions,
    prealign: bool,
    pose: PoseSpec,
    executor: Executor | None,
    progress: ProgressCallback | None,
) -> None:
    """Move childless subjects to a later, more similar member when that registers better.

    The layers fix a subject's parent at the first layer with an acceptable
    registration; a member that joined later can be more similar to it (a smaller D:
    a smaller deformation for CPD to bridge). For every subject without children, the
    most similar such member not yet tried (and not the subject itself or below it) is
    tried; the subject moves when the new registration passes the tree's rule and is
    better: a higher path confidence, or one within ``REFINE_TIE`` with a lower e.
    """
    parents = {r.parent for r in results.values() if r.parent is not None}
    tasks: list[_RegTask] = []
    for s, r in sorted(results.items()):
        if s in parents or r.parent is None or r.leaf or r.layer is None:
            continue
        d_parent = float(sim.D[r.parent, s])
        later = sorted(
            (float(sim.D[m, s]), m) for m, node in nodes.items()
            if m != s and node.layer >= r.layer and (m, s) not in tried
            and s not in node.chain.path and np.isfinite(sim.D[m, s])
            and sim.D[m, s] < d_parent and sim_rule.similar(sim, m, s)
        )
        if not later:
            continue
        d, m = later[0]
        tried.add((m, s))
        tasks.append(_RegTask(
            subject=s, member=m, layer=nodes[m].layer + 1, similarity=d, q=nodes[m].q,
            y=coll.normed[s], starts=_starts(sim, m, s), cpd=cpd, prealign=prealign,
            pose=pose, spacing2=coll.spacing2[s],
        ))
    moved: set[int] = set()
    for out in sorted(_run_tasks(tasks, executor, progress, "refine"), key=lambda o: o.subject):
        s = out.subject
        old = results[s]
        if s in parents or out.member in moved or s in nodes[out.member].chain.path:
            # a move earlier in this pass made s a parent, moved m (this registration
            # started from m's former warped model), or put s above m
            continue
        limit = math.inf if tau_err is None else _error_limit(tau_err, explicit_error, floors[s])
        parent = nodes[out.member]
        conf = min(parent.confidence, out.quality.confidence)
        ok = _rejection(out, limit, fold_check) is None
        assert old.confidence is not None and old.error is not None
        better = conf > old.confidence + REFINE_TIE or (
            conf >= old.confidence - REFINE_TIE and out.error < old.error)
        accepted = ok and better
        old.attempts.append(Attempt(
            member=out.member, layer=out.layer, similarity=out.similarity, error=out.error,
            limit=limit, min_jacobian=out.min_jacobian, accepted=accepted,
            reason=("refined: moved here, more similar and a better registration" if accepted
                    else "refinement not taken: not better than the registration it had"),
        ))
        if not accepted:
            continue
        res, node = _subject_from_outcome(coll, out, parent, layer=parent.layer + 1)
        res.attempts = [replace(a, accepted=a is old.attempts[-1]) for a in old.attempts]
        res.reason = (f"registered from {coll.names[out.member]} (layer {parent.layer}), "
                      f"moved there from {coll.names[old.parent or 0]} by refinement")
        results[s] = res
        nodes[s] = node
        parents.add(out.member)
        moved.add(s)


def _attach_leaves(
    coll: _Collection,
    sim: Similarity,
    nodes: dict[int, _Node],
    results: dict[int, SubjectResult],
    waiting: set[int],
    rejected: dict[int, list[_RegOutcome]],
    tried: set[tuple[int, int]],
    allowed: set[tuple[int, int]] | None,
    cpd: CPDOptions,
    prealign: bool,
    pose: PoseSpec,
    max_candidates: int,
    executor: Executor | None,
    progress: ProgressCallback | None,
) -> None:
    """Give every subject the tree could not take its best registration, as a leaf.

    When the tree stops growing, each waiting subject is registered from the root and
    from its most similar members not yet tried (up to `max_candidates`); with the
    registrations rejected while the tree grew, the one with the highest path confidence
    (then the lowest e) that does not fold is kept; when all fold, the best by the
    confidence model with the fold set aside (a leaf is never a parent, so a local fold
    does not spread), reporting confidence 0. The subject is attached as a leaf: never a
    parent, its confidence and the reason it was not accepted reported. It stays
    unattached only when no registration could be run.
    """
    pairs = [(m, s) for s in waiting for m in nodes
             if (m, s) not in tried and (allowed is None or (m, s) in allowed)]
    sim.ensure(pairs, executor=executor, progress=progress, stage="similarity leaves")
    tasks: list[_RegTask] = []
    for s in sorted(waiting):
        untried = sorted((float(sim.D[m, s]), m) for m in nodes
                         if (m, s) not in tried and np.isfinite(sim.D[m, s]))
        chosen = [m for _, m in untried[:max_candidates]]
        if (coll.root, s) not in tried and coll.root not in chosen:
            chosen.append(coll.root)
        for m in chosen:
            tried.add((m, s))
            tasks.append(_RegTask(
                subject=s, member=m, layer=nodes[m].layer + 1, similarity=float(sim.D[m, s]),
                q=nodes[m].q, y=coll.normed[s], starts=_starts(sim, m, s), cpd=cpd,
                prealign=prealign, pose=pose, spacing2=coll.spacing2[s],
            ))
    for out in _run_tasks(tasks, executor, progress, "leaves"):
        rejected.setdefault(out.subject, []).append(out)
    for s in sorted(waiting):
        pool = rejected.get(s, [])
        usable = [o for o in pool if o.min_jacobian > 0]
        r = results[s]
        if not pool:
            r.reason = "unattached: no registration could be tried"
            continue
        # unfolded first; among those that all fold, by the confidence model's estimate
        # with the fold set aside (a leaf is never a parent: a local fold does not spread)
        best = max(pool, key=lambda o: (
            o.min_jacobian > 0, min(nodes[o.member].confidence, o.quality.fit_confidence),
            -o.error))
        parent = nodes[best.member]
        res, _ = _subject_from_outcome(coll, best, parent, layer=parent.layer + 1, leaf=True)
        why = next((a.reason for a in reversed(r.attempts) if a.member == best.member), None)
        if not best.min_jacobian > 0:
            why = (f"its warp folds the model locally (min Jacobian determinant "
                   f"{best.min_jacobian:.3g}): confidence 0; {len(usable)} of the {len(pool)} "
                   "registrations tried do not fold")
        res.attempts = r.attempts
        res.reason = (
            f"low-confidence leaf: best of {len(pool)} registrations, from "
            f"{coll.names[best.member]}; not accepted into the tree"
            + (f" ({why})" if why else " (the tree stopped growing before reaching it)")
        )
        results[s] = res


# ----------------------------------------------------------------------------- methods


@_owns_executor
def build_dynamic_tree(
    shapes: Sequence[ArrayLike],
    root: int = 0,
    *,
    similarity_threshold: float | None = None,
    error_threshold: float | None = None,
    cpd: CPDOptions | None = None,
    max_candidates: int = 3,
    candidates: int | None = None,
    prealign: bool = True,
    pose: str | None = None,
    max_rotation: float | None = None,
    fold_check: bool = True,
    refine: bool = True,
    compare_direct: bool = False,
    names: Sequence[str] | None = None,
    executor: Executor | None = None,
    progress: ProgressCallback | None = None,
) -> CollectionResult:
    """Register the root model to every shape through a dynamic tree (Du et al. 2016).

    Parameters
    ----------
    shapes : sequence of array_like, shape (n_i, 2)
        The collection, in the user's coordinates; each shape is size-normalised first.
    root : int
        Index of the model shape.
    similarity_threshold : float, optional
        A subject is similar to a member when ``D[member, subject]`` (eq. 9, normalised
        shapes) is at most this. Default: automatic, per pair: the largest of CPD's
        measured capture range (D = 0.01), the D from the subject's 4th nearest shape and
        the D to the member's 4th nearest shape (see `_SimilarityRule`).
    error_threshold : float, optional
        A registration is accepted when e (eq. 10, normalised shapes) is below this.
        Default: automatic, ``3 x`` the lower quartile of the second layer's e, and never
        below half the subject's squared point spacing.
    cpd : CPDOptions, optional
    max_candidates : int
        When several members are similar to a waiting subject, the `max_candidates`
        most similar (smallest D) members not yet tried for it are tried in one layer
        and the accepted registration with the smallest e is kept.
    candidates : int, optional
        Only pairs joining each shape to its `candidates` nearest by a cheap descriptor
        are considered (and the root to every subject). Default: all pairs for up to 64
        shapes, 12 nearest beyond.
    prealign : bool
        Pose handling: CPD from the pose as given, and also from the similarity's
        affine-ICP map when that is another pose that fits clearly better (see `pose`).
        False: CPD from the pose as given only (the paper's plain CPD).
    pose : {"rotation", "as_given", "upright", "affine"}, optional
        Which poses may be tried (see :mod:`registration._pose`): any rotation (default),
        the shapes as given only, rotations within +-`max_rotation` of them, or any affine
        map including reflections (the paper's ``det(A) != 0``). Outside "affine" the
        affine ICP never mirrors. The pose as given is always registered; another pose is
        tried when its D is below 0.6 of the pose as given's and replaces it only when
        CPD from it reaches less than half the pose as given's e.
    max_rotation : float, optional
        Half-width in degrees of the "upright" mode (default 30); given alone, it
        selects that mode (glyph scans, aligned outlines).
    fold_check : bool
        Also reject registrations whose displacement field folds the model (Jacobian
        determinant <= 0 at a model point): e can be small while correspondences are wrong.
    refine : bool
        After the tree stops growing, a subject without children may move to a member
        that joined the tree after it and is more similar to it than its parent, when
        the registration from there is better (higher confidence, or as confident with a
        lower e). No cycles: a subject never moves below itself.
    compare_direct : bool
        Also run direct CPD from the root on every subject, for comparison.
    names : sequence of str, optional
    executor : Executor, optional
        Where ICP and CPD run; default: serial for small jobs, else a local process pool.
    progress : callable(stage, done, total), optional
        Called as work completes; an exception it raises stops the run and propagates.

    Returns
    -------
    CollectionResult

    Raises
    ------
    ValueError
        On invalid shapes, root, names or thresholds.
    """
    _check_threshold("similarity_threshold", similarity_threshold)
    _check_threshold("error_threshold", error_threshold)
    if max_candidates < 1:
        raise ValueError(f"max_candidates must be at least 1; got {max_candidates}")
    cpd = cpd if cpd is not None else CPDOptions()
    spec = PoseSpec.resolve(pose, max_rotation)
    coll = _Collection.prepare(shapes, root, names)
    sim, allowed = _prepare_similarity(
        coll, similarity_threshold, candidates, executor, progress, spec
    )
    subjects_idx = [k for k in range(coll.n) if k != root]
    sim_rule = _SimilarityRule.build(sim, similarity_threshold)
    tau_err = error_threshold
    floors = {s: _spacing_floor(coll.spacing2[s]) for s in subjects_idx}

    nodes: dict[int, _Node] = {root: _Node(q=coll.normed[root], chain=coll.root_chain(), layer=1)}
    results: dict[int, SubjectResult] = {
        s: SubjectResult(index=s, name=coll.names[s]) for s in subjects_idx
    }
    waiting = set(subjects_idx)
    tried: set[tuple[int, int]] = set()
    rejected: dict[int, list[_RegOutcome]] = {}
    frontier = [root]
    layer = 1
    while waiting and frontier:
        layer += 1
        _ensure_frontier(sim, frontier, waiting, allowed, executor, progress, layer)
        tasks: list[_RegTask] = []
        for s in sorted(waiting):
            cands = sorted(
                (float(sim.D[m, s]), m)
                for m in nodes
                if (m, s) not in tried and sim_rule.similar(sim, m, s)
            )[:max_candidates]
            for d, m in cands:
                tried.add((m, s))
                tasks.append(
                    _RegTask(
                        subject=s, member=m, layer=layer, similarity=d, q=nodes[m].q,
                        y=coll.normed[s], starts=_starts(sim, m, s), cpd=cpd,
                        prealign=prealign, pose=spec, spacing2=coll.spacing2[s],
                    )
                )
        if not tasks:
            break
        outcomes = _run_tasks(tasks, executor, progress, f"layer {layer}")
        if tau_err is None:
            tau_err = _auto_error_threshold(outcomes)
        best: dict[int, _RegOutcome] = {}
        for out in outcomes:
            limit = _error_limit(tau_err, error_threshold is not None, floors[out.subject])
            rejection = _rejection(out, limit, fold_check)
            ok = rejection is None
            reason = rejection or "accepted candidate"
            if not ok:
                rejected.setdefault(out.subject, []).append(out)
            results[out.subject].attempts.append(
                Attempt(member=out.member, layer=layer, similarity=out.similarity,
                        error=out.error, limit=limit, min_jacobian=out.min_jacobian,
                        accepted=False,
                        reason=reason)
            )
            if ok and (out.subject not in best or out.error < best[out.subject].error):
                best[out.subject] = out
        new_frontier = []
        for s, out in sorted(best.items()):
            res, node = _subject_from_outcome(coll, out, nodes[out.member])
            res.attempts = [
                Attempt(**{**asdict(a), "accepted": a.member == out.member and a.layer == layer})
                for a in results[s].attempts
            ]
            res.reason = f"registered from {coll.names[out.member]} (layer {out.layer - 1})"
            results[s] = res
            nodes[s] = node
            waiting.discard(s)
            new_frontier.append(s)
        frontier = new_frontier
    # leaves first: they may reuse registrations made while the tree grew, which start
    # from their member's warped model as it was then; refinement then moves no member
    # that has a child, leaves included, so every chain stays the one it was built on
    if waiting:
        _attach_leaves(coll, sim, nodes, results, waiting, rejected, tried, allowed, cpd,
                       prealign, spec, max_candidates, executor, progress)
    if refine:
        _refine_parents(coll, sim, sim_rule, nodes, results, tried, tau_err, floors,
                        error_threshold is not None, fold_check, cpd, prealign, spec, executor,
                        progress)
    out_subjects = [results[s] for s in subjects_idx]
    direct = (
        _direct_results(coll, sim, cpd, prealign, executor, progress) if compare_direct else None
    )
    return CollectionResult(
        method="dynamic_tree",
        root=root,
        names=coll.names,
        subjects=out_subjects,
        thresholds={
            **_similarity_report(sim_rule),
            "error": tau_err,
            "error_rule": "explicit" if error_threshold is not None
            else f"auto: max({ERROR_FACTOR} x lower quartile of layer-2 e, "
            f"{SPACING_FACTOR} x the subject's squared point spacing)",
            "fold_check": fold_check,
        },
        options=_options_dict(cpd, prealign, max_candidates, spec),
        direct=direct,
        similarity_pairs=sim.computed,
        similarity=sim.D,
    )


@_owns_executor
def build_static_tree(
    shapes: Sequence[ArrayLike],
    root: int = 0,
    *,
    similarity_threshold: float | None = None,
    error_threshold: float | None = None,
    cpd: CPDOptions | None = None,
    candidates: int | None = None,
    prealign: bool = True,
    pose: str | None = None,
    max_rotation: float | None = None,
    compare_direct: bool = False,
    names: Sequence[str] | None = None,
    executor: Executor | None = None,
    progress: ProgressCallback | None = None,
) -> CollectionResult:
    """The static (heuristic) tree of Du et al. 2015: built once, no rejection.

    The tree grows layer by layer over the similarity graph (``D <= similarity
    threshold``, automatic as in :func:`build_dynamic_tree`); each subject joins the
    most similar member of the previous layer. Then CPD runs along its edges, each edge
    starting from the root model as warped onto the parent. `error_threshold` is accepted
    for a uniform interface and ignored: no registration is rejected. Subjects the
    similarity graph does not reach from the root are reported unattached.

    Parameters
    ----------
    shapes, root, similarity_threshold, candidates, cpd, prealign, pose, max_rotation, names,
    compare_direct, executor, progress
        As for :func:`build_dynamic_tree`.
    error_threshold : float, optional
        Ignored (the static tree rejects nothing); accepted for a uniform interface.

    Returns
    -------
    CollectionResult
        ``method == "static_tree"``; every attempt is accepted.

    Raises
    ------
    ValueError
        On invalid shapes, root, names or thresholds.
    """
    _check_threshold("similarity_threshold", similarity_threshold)
    del error_threshold
    cpd = cpd if cpd is not None else CPDOptions()
    spec = PoseSpec.resolve(pose, max_rotation)
    coll = _Collection.prepare(shapes, root, names)
    sim, allowed = _prepare_similarity(
        coll, similarity_threshold, candidates, executor, progress, spec
    )
    subjects_idx = [k for k in range(coll.n) if k != root]
    sim_rule = _SimilarityRule.build(sim, similarity_threshold)
    # 1. the tree, from the similarity alone
    parent: dict[int, int] = {}
    layers: list[list[int]] = [[root]]
    waiting = set(subjects_idx)
    while waiting and layers[-1]:
        frontier = layers[-1]
        _ensure_frontier(sim, frontier, waiting, allowed, executor, progress, len(layers) + 1)
        new = []
        for s in sorted(waiting):
            cands = [(float(sim.D[m, s]), m) for m in frontier if sim_rule.similar(sim, m, s)]
            if cands:
                parent[s] = min(cands)[1]
                new.append(s)
        waiting -= set(new)
        layers.append(new)
    # 2. CPD along the edges, a layer at a time
    nodes: dict[int, _Node] = {root: _Node(q=coll.normed[root], chain=coll.root_chain(), layer=1)}
    results: dict[int, SubjectResult] = {
        s: SubjectResult(index=s, name=coll.names[s]) for s in subjects_idx
    }
    for depth, members in enumerate(layers[1:], start=2):
        tasks = [
            _RegTask(subject=s, member=parent[s], layer=depth,
                     similarity=float(sim.D[parent[s], s]), q=nodes[parent[s]].q,
                     y=coll.normed[s], starts=_starts(sim, parent[s], s),
                     cpd=cpd, prealign=prealign, pose=spec, spacing2=coll.spacing2[s])
            for s in members
        ]
        for out in _run_tasks(tasks, executor, progress, f"layer {depth}"):
            res, node = _subject_from_outcome(coll, out, nodes[out.member])
            res.reason = f"static edge from {coll.names[out.member]}"
            results[out.subject] = res
            nodes[out.subject] = node
    for s in waiting:
        results[s].reason = "not reached: no similar shape on a path from the root"
    direct = (
        _direct_results(coll, sim, cpd, prealign, executor, progress) if compare_direct else None
    )
    return CollectionResult(
        method="static_tree",
        root=root,
        names=coll.names,
        subjects=[results[s] for s in subjects_idx],
        thresholds={
            **_similarity_report(sim_rule),
            "error": None,
            "error_rule": "none: the static tree does not reject",
        },
        options=_options_dict(cpd, prealign, 1, spec),
        direct=direct,
        similarity_pairs=sim.computed,
        similarity=sim.D,
    )


def _direct_results(
    coll: _Collection,
    sim: Similarity,
    cpd: CPDOptions,
    prealign: bool,
    executor: Executor | None,
    progress: ProgressCallback | None,
) -> list[SubjectResult]:
    r = coll.root
    subjects_idx = [k for k in range(coll.n) if k != r]
    if prealign:
        sim.ensure([(r, s) for s in subjects_idx], executor=executor, progress=progress,
                   stage="similarity direct")
    tasks = [
        _RegTask(subject=s, member=r, layer=2, similarity=float(sim.D[r, s]),
                 q=coll.normed[r], y=coll.normed[s], starts=_starts(sim, r, s),
                 cpd=cpd, prealign=prealign, pose=sim.pose, spacing2=coll.spacing2[s])
        for s in subjects_idx
    ]
    root_node = _Node(q=coll.normed[r], chain=coll.root_chain(), layer=1)
    out_by_subject = {}
    for out in _run_tasks(tasks, executor, progress, "direct"):
        res, _ = _subject_from_outcome(coll, out, root_node)
        res.reason = "direct CPD from the root"
        out_by_subject[out.subject] = res
    return [out_by_subject[s] for s in subjects_idx]


@_owns_executor
def register_direct(
    shapes: Sequence[ArrayLike],
    root: int = 0,
    *,
    similarity_threshold: float | None = None,
    error_threshold: float | None = None,
    cpd: CPDOptions | None = None,
    prealign: bool = True,
    pose: str | None = None,
    max_rotation: float | None = None,
    compare_direct: bool = False,
    names: Sequence[str] | None = None,
    executor: Executor | None = None,
    progress: ProgressCallback | None = None,
) -> CollectionResult:
    """Direct CPD from the root model to every subject (the paper's baseline).

    With `prealign` (default) the pose handling of :func:`build_dynamic_tree` applies (CPD
    from the pose as given, and from a clearly better other pose when ICP finds one); the
    paper's plain CPD is ``prealign=False``: no pose search of any kind.
    Every subject is at layer 2 with the root as parent.

    Parameters
    ----------
    shapes : sequence of array_like, shape (n_i, 2)
        The collection, in the user's coordinates; each shape is size-normalised first.
    root : int
        Index of the model shape.
    similarity_threshold, error_threshold, compare_direct
        Ignored; accepted so that the three methods take the same arguments.
    cpd : CPDOptions, optional
    prealign : bool
        Pose handling as in :func:`build_dynamic_tree`; False for plain CPD.
    pose, max_rotation
        As for :func:`build_dynamic_tree`.
    names : sequence of str, optional
    executor : Executor, optional
    progress : callable(stage, done, total), optional

    Returns
    -------
    CollectionResult
        ``method == "direct"``.

    Raises
    ------
    ValueError
        On invalid shapes, root or names.
    """
    del similarity_threshold, error_threshold, compare_direct
    cpd = cpd if cpd is not None else CPDOptions()
    spec = PoseSpec.resolve(pose, max_rotation)
    coll = _Collection.prepare(shapes, root, names)
    sim = Similarity.empty(coll.normed, pose=spec)
    subjects = _direct_results(coll, sim, cpd, prealign, executor, progress)
    return CollectionResult(
        method="direct",
        root=root,
        names=coll.names,
        subjects=subjects,
        thresholds={"similarity": None, "error": None, "error_rule": "none"},
        options=_options_dict(cpd, prealign, 1, spec),
        direct=None,
        similarity_pairs=sim.computed,
        similarity=sim.D,
    )

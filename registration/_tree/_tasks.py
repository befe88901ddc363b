"""Task plumbing of the tree methods: one registration of a member's warped model onto a
subject (every start pose, CPD, quality; one kept), and a batch of them run on an executor."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, ParamSpec, TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .._cpd import CPDOptions, CPDResult, cpd_nonrigid
from .._cpd._estep import _posterior_max
from .._error import directed_errors, registration_error, scattered_extra, unmatched_side
from .._executor import Executor, owned_executor
from .._icp import AffineICPResult, affine_icp, rigid_turns
from .._icp._pairwise import _refine, fit_rigid
from .._pointmap import PointTransform, composed_with_jacobian
from .._pose import PoseSpec, angle_between, rotation_angle
from .._quality import RegistrationQuality, measure_quality
from .._similarity import ProgressCallback, Similarity
from .._transform import AffineTransform
from ._symmetric import NoHalfway, halfway_back

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
# The margin, on the glyph chains of bench_groundtruth.py turned at random (書水心東龍 in
# two fonts, every registration the tree and direct CPD ran; bench/RESULTS.md 7.46): of
# 704 turns to the truth 542 reached below 0.5x the e as given and 613 below 0.7x, while
# of 41 wrong turns 8 did (each where the pose as given was wrong too). Given upright,
# no turn tried reached below 1.0x (908 registrations of the same characters), and at 0.7
# the 208 upright runs of the default bench kept their results (one within 0.001).
POSE_DISTINCT_DEG = 20.0
POSE_D_RATIO = 0.6
POSE_MARGIN = 0.7
#: The pose as given has failed, and another start's unfolded registration replaces it at
#: no larger an e (not only below its margin: `_register_posed`), when CPD from it folds
#: clearly: its least Jacobian determinant is below ``-FAILED_FOLD``. A warp that must
#: turn the model to reach a really turned subject folds deeply: on real MPEG-7, 5 of the
#: 6 poses as given that gave way so (lmfish, bird, camel) had -0.29 to -3.2; the sixth
#: (horse, -0.009) gave way to a turn at 0.97x its e, which e cannot rank. A fold
#: of a few hundredths is a kink over a few noisy points: on the Chui & Rangarajan noise
#: series (fish, trial 0, level 5) CPD as given reached -0.015 at 0.72 of the radius from
#: the truth, and a turn of 105 degrees won at 0.73x its e, 1.81 from the truth, making
#: direct CPD 1.93x plain CPD on that run (bench/RESULTS.md 7.61). A registration that
#: folds at all still counts as folded everywhere else (the acceptance rule, the leaves).
FAILED_FOLD = 0.1
#: The margin of an ``"aligned"`` start (`_Start.decided`): the pose as given again,
#: pre-aligned by affine ICP with a turn of the model's (or root's) symmetry undone. Its
#: e differs from the pose as given's only by how the two fit what breaks the symmetry,
#: and on a straight stroke by a stretch across it that affine ICP leaves to chance: the
#: skeleton of 一 (Noto Sans, seed 0) reached 0.56x the e as given from it at a
#: correspondence error of 0.34 of the radius against 0.10 (bench/RESULTS.md 7.46).
ALIGNED_MARGIN = 0.5
#: The sampling floor of e: ``SPACING_FACTOR`` times the subject's mean squared point
#: spacing h^2 (the automatic error threshold's floor too, `_rules._spacing_floor`). On
#: data with ground truth every registration within 5% of the shape's size had e below it
#: (bench/calibrate_thresholds.py): below it e cannot tell one fit from another, so a
#: registration from the pose as given that reaches it, without folding, is kept and no
#: other start is tried (`_register_task`). Of a straight stroke both ends of a half turn
#: fit that closely: on the skeleton of 一 (sans serif, 217 points) a turned start won at
#: 0.48x an e of 8e-5 as given, under a floor of 1.2e-4, and its registration was the
#: stroke reversed (bench/RESULTS.md 7.42).
SPACING_FACTOR = 0.5
# How far a map of a model onto itself may move the model's points from where the
# nearest similarity (a rotation and one scale) puts them, RMS over the model's RMS
# radius, and still count as one of its symmetries (`_self_map`): an exact symmetry
# is an isometry (0). 0.11 is about what a stretch of 1.25 between the map's singular
# values gives on a round outline (the bound this replaces); the half turns of O, 0, S,
# 8, H, N, Z and straight strokes settle at 0-0.04 on glyphs of 400 points, a stretch
# that folds a non-symmetric outline onto itself at 0.32-0.47 (MPEG-7 bat, bird, horse).
# Measured on the points rather than by the map's singular values, because of a straight
# stroke affine ICP may shrink the width it does not have at no cost: a bent stroke's
# half turn settled at singular values 1.0 and 0.79 (bench/RESULTS.md 7.42).
SYMMETRY_MAX_DEVIATION = 0.11
# A turn under which the model fits itself at least 1 / SYMMETRY_D_RATIO times as
# closely as the turned pose fits the subject is a near-symmetry of the model
# (`_ratio_to_pose`). The turned pose then says nothing the pose as given does not: its
# correspondences are wrong by the symmetry (a Latin O in a serif font, turned half a
# turn by direct CPD at 0.47x the e: 1.99 of the radius against 0.20 as given; 7.39), so
# the start is the pose as given aligned instead, the turn undone (`_Start.decided`).
SYMMETRY_D_RATIO = 0.5
#: A turn of the member's warped model onto the subject found by rigid ICP (a rotation,
#: no shear or scale: `_rigid_start`) is registered too when its D is below
#: ``TURN_D_RATIO`` times the D rigid ICP reaches from the pose as given: whenever rigid
#: ICP fits another turn more closely than it settles from the pose as given, and the
#: registration from it then earns its place by CPD's e, as the similarity's best pose
#: does (``POSE_MARGIN``). Affine ICP fits a glyph of many parallel strokes about as well
#: at several turns, so on glyphs turned apart its best pose is often not the truth and,
#: when it is, often above ``POSE_D_RATIO`` (書 in Noto Sans turned at random: 1 of 20
#: true turns offered from the root). Rigid D ranks turns by the shape alone, but not by
#: much everywhere: on 書 turned about 160 degrees rigid ICP settles from the pose as
#: given 25 degrees off, within 8% of the true turn's D. Over pairs of 書水心東龍 in two
#: fonts (bench/RESULTS.md 7.46, 7.48): of 1390 pairs turned apart the true turn is
#: offered on 1153 (on 1071 below 0.8x), a wrong one on 121; of 1590 pairs given upright
#: a turn is offered on 150 (9%). Raised from 0.8 to 1.0, the default bench's 208 upright
#: runs came out identical but one direct CPD run (1.00 -> 0.99 of plain CPD), while
#: turned collections went from 47 to 28 subjects wrong under direct CPD and from 14 to
#: 10 in the tree (240 subjects).
TURN_D_RATIO = 1.0

#: The dynamic tree's edges are symmetric (see `_symmetric_link`): CPD's registration of
#: the member's model onto the subject is moved halfway to where the subject registered
#: back onto the model puts its points. One CPD's slide along a stroke runs partly the
#: other way when the roles are swapped, so halfway part of it cancels, and a chain of
#: such edges gathers less of it (bench/RESULTS.md 7.29). Only where the tree is decided
#: at the stored resolution (`_methods._Run.symmetric_edges`); baselines (direct CPD, the
#: static tree) keep the paper's one-way edges.
SYMMETRIC_LINKS = True
#: Shapes of fewer points keep one-way edges: at 100 points the backward registration's
#: own sampling noise is as large as the slide it would cancel (the Chui & Rangarajan
#: series, 98-105 points: 0.42 -> 0.50 and 0.25 -> 0.29 of plain CPD with symmetric
#: edges; 200-400 point families gained; bench/RESULTS.md 7.29), as for the polish's
#: consensus partner (`_polish.CONSENSUS_PARTNER_MIN_POINTS`).
SYMMETRIC_LINK_MIN_POINTS = 150
#: The dynamic tree's edges run CPD from two starts and keep the registration with the
#: lower e (see `_held_start`): annealed from the spread of all pairs, as the paper's CPD
#: does, and held, from the member's warped model as it lies, with sigma^2 from its
#: residual (as the polish's stages start). Both fit the same field with the same
#: options, so e compares like with like: they differ only in the local optimum EM
#: reaches. Annealing from a wide variance can settle a group of parallel strokes one
#: stroke off at a higher e than the truth's basin has (書 and 龍 in sans regular: single
#: links from a perfect parent erring 0.08-0.15 of the radius; CPD started at the truth
#: stays at 0.03-0.07 on 17 of 19 of them, at a lower e on 18); the held start keeps each
#: model point near the subject points it already lies on. Ground truth: bench/RESULTS.md
#: 7.36. Direct CPD and the static tree keep the paper's one start.
HELD_START_EDGES = True
#: Shapes of fewer points keep the annealed start alone. At 100 points e ranks the two
#: starts no better than chance on smooth outlines, whose points can slide or turn along
#: the outline at no cost in e: on generated chains of 100 points a held start reached a
#: lower e than the annealed one from the root while turned by tens of degrees, and its
#: children inherited it (ground truth 0.056 -> 0.18 of the radius, bench/RESULTS.md
#: 7.36). The same bound as the symmetric edges' (:data:`SYMMETRIC_LINK_MIN_POINTS`).
HELD_START_MIN_POINTS = 150


@dataclass(frozen=True)
class _Start:
    """A pose to start a registration from: the pose as given (no affine step: CPD runs
    on the size-normalised shapes as they are) or an affine-ICP map of another pose."""

    label: str  # "as given", "rotated" or "aligned" (see `decided`)
    A: FloatArray | None = None
    t: FloatArray | None = None
    # the e, relative to the pose as given's, below which this start's registration
    # replaces it (`_register_task`)
    margin: float = POSE_MARGIN
    # what `_self_map` and `_ratio_to_pose` need besides A while it is still to be
    # decided whether the turn is a near-symmetry of the model: the member's own
    # (normalised) shape and this pose's D. `decided` decides it in the worker that runs
    # the task (with the task's `root_shape`), not in the process that builds the tasks
    # (one or two affine ICPs of a shape onto itself per turned start).
    symmetry: tuple[FloatArray, float] | None = None

    def decided(self, root: FloatArray | None = None) -> _Start:
        """This start once it is decided whether its turn is a near-symmetry of the model
        (`_ratio_to_pose`; itself when that is decided already). A turned registration
        then differs from the pose as given's only by the symmetry, wrong by the whole
        turn, and e can only compare the few parts that break the symmetry (the Latin O
        in a serif font, turned half a turn by direct CPD at 0.47x the e: 1.99 of the
        radius against 0.20 as given; 7.39). So the start becomes ``"aligned"``: the pose
        as given in this pose's place, the turn of the model's own symmetry undone
        (``A R^T``, R the rotation the symmetry makes on the model's points: stable where
        affine ICP squashed a stroke's width, which inverting its map would blow up),
        where the pose as given's CPD, with no affine step, can fall short (a straight
        stroke that turned a little on a chain, 9e-4 against 7e-5 from either end).

        A turn (not a mirror: a rotation's angle is the same in the member's frame and
        the root's, a mirror's axis is not) the `root`'s shape (None when the member is
        the root) is nearly symmetric under is treated so too, when the member is not:
        the correspondences are the root's, and the turn changes no fit of the root, only
        which deformation explains the subject. A bar bent one way along its chain fits
        a bar bent the other way turned end for end at 0.2-0.4x the e as given, while the
        bent member no longer fits itself turned (the edges of a 65 x 22 rectangle, seed
        1: 3.9x plain CPD's correspondence error, two subjects end for end;
        bench/RESULTS.md 7.45)."""
        if self.symmetry is None or self.A is None or self.t is None:
            return self
        model, d = self.symmetry
        settled = _self_map(model, self.A)
        if settled is not None and _ratio_to_pose(settled, d) <= SYMMETRY_D_RATIO:
            undo = _turn_between(model, settled.A, np.eye(2)).T
            return _Start("aligned", self.A @ undo, self.t - self.A @ undo @ settled.t,
                          margin=ALIGNED_MARGIN)
        if root is not None and np.linalg.det(self.A) > 0:
            # the turn as a near-symmetry of the root's shape
            settled = _self_map(root, _turn_between(model, self.A, np.eye(2)))
            if settled is not None and _ratio_to_pose(settled, d) <= SYMMETRY_D_RATIO:
                undo = _turn_between(root, settled.A, np.eye(2)).T
                return _Start("aligned", self.A @ undo, self.t, margin=ALIGNED_MARGIN)
        return replace(self, symmetry=None)


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
    # the root's normalised shape when the member is another shape: the root's symmetry
    # test of every turned start (`_Start.decided`)
    root_shape: FloatArray | None = None
    symmetric: bool = False  # make the edge symmetric (`_symmetric_link`): the dynamic tree's
    held: bool = False  # also run CPD from the held start (`_held_start`): the dynamic tree's


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
    pose: str  # which start was kept: "as given", "rotated", "aligned" (`_Start.decided`) or
    # "plain" (prealign=False)
    pose_angle: float  # rotation of the pre-alignment, degrees (0 without one)
    pose_errors: dict[str, float]  # e reached from every start tried
    quality: RegistrationQuality
    # the registration was made symmetric (`_symmetric_link`); why not, when it was asked
    # for and not made
    symmetric: bool = False
    symmetric_reason: str = ""
    # which of CPD's starts was kept ("annealed" or "held", `_held_start`) and the e each
    # reached; empty when only the annealed one ran
    cpd_start: str = ""
    cpd_start_errors: dict[str, float] | None = None
    # the margin the other start's e (relative to the pose as given's) had to be under to
    # replace it (`_Start.margin`); None when only the pose as given was tried
    pose_margin: float | None = None
    # what the starts' registrations were compared by (`_pose_term`): "e", or "subject"
    # (the subject's half of e alone: the subject is part of the model)
    pose_compared_by: str = "e"
    # how scattered the subject's points without counterpart on the registration are
    # (:func:`~registration._error.scattered_extra`; None: it has none, or too few)
    scattered: float | None = None


@dataclass(frozen=True)
class _Then:
    """`first`, then `second`: the map whose Jacobians the quality checks read for a
    symmetric edge (CPD's warp, then the step halfway to the backward registration)."""

    first: PointTransform
    second: PointTransform

    def apply(self, points: Any) -> FloatArray:
        return self.second.apply(self.first.apply(points))

    def apply_with_jacobian(self, points: Any) -> tuple[FloatArray, FloatArray]:
        out = composed_with_jacobian((self.first, self.second), points)
        if out is None:
            raise TypeError("both steps must give their Jacobians")
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"type": "composed", "steps": [self.first.to_dict(), self.second.to_dict()]}


def _symmetric_link(q: FloatArray, y: FloatArray, warped: FloatArray, o: CPDOptions
                    ) -> tuple[PointTransform, FloatArray] | str:
    """The registration `warped` (CPD's of the model `q` onto the subject `y`) moved
    halfway to where the subject registered back onto the model puts the model's points
    (:func:`~registration._tree._symmetric.halfway_back`): the step and the points it
    moves `warped` to, or why there is none.

    The backward registration is CPD with the edge's options and the roles swapped, and
    the step is CPD's field at the edge's kernel width. As the polish's symmetric finish
    does for the whole chain (`_polish._symmetric`), here for each edge: on the glyph
    chains of bench/bench_groundtruth.py, edges along the true generation path err
    0.88-0.95x as much one generation step from the root and further (bench/RESULTS.md
    7.29)."""
    def backward(start: FloatArray) -> PointTransform:
        return cpd_nonrigid(y, q, **o.keywords(), init_warped=start).transform

    found = halfway_back(q, y, warped, o.beta, backward, o.beta)
    if isinstance(found, NoHalfway):
        return found.reason
    return found.step, found.moved


def _held_start(q: FloatArray, y: FloatArray, o: CPDOptions, spacing2: float,
                annealed: CPDResult) -> tuple[CPDResult, str, dict[str, float]]:
    """CPD of the model `q` onto the subject `y` from the held start, beside `annealed`
    (CPD from the spread of all pairs, the paper's start): the model's points start where
    they lie, with sigma^2 from their residual (half e, never below the squared point
    spacing, as the polish's stages start). The registration with the lower e is kept
    (:data:`HELD_START_EDGES`); returns it, which start it was, and each start's e."""
    held = cpd_nonrigid(q, y, **o.keywords(), init_warped=q,
                        sigma2=max(0.5 * registration_error(q, y), spacing2))
    errors = {"annealed": registration_error(annealed.warped, y),
              "held": registration_error(held.warped, y)}
    if errors["held"] < errors["annealed"]:
        return held, "held", errors
    return annealed, "annealed", errors


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
    res = cpd_nonrigid(q, task.y, **o.keywords())
    cpd_start, start_errors = "", None
    if task.held and min(len(q), len(task.y)) >= HELD_START_MIN_POINTS:
        res, cpd_start, start_errors = _held_start(q, task.y, o, task.spacing2, res)
    steps.append(res.transform)
    warped = np.asarray(res.warped, dtype=np.float64)
    warp: PointTransform = res.transform
    symmetric, why_not = False, ""
    if task.symmetric and min(len(q), len(task.y)) < SYMMETRIC_LINK_MIN_POINTS:
        why_not = f"fewer than {SYMMETRIC_LINK_MIN_POINTS} points"
    elif task.symmetric:
        found = _symmetric_link(q, task.y, warped, o)
        if isinstance(found, str):
            why_not = found
        else:
            step, warped = found
            steps.append(step)
            warp = _Then(res.transform, step)
            symmetric = True
    # the held start's comparison already took e of the kept points, unless they moved
    e = (start_errors[cpd_start] if start_errors is not None and not symmetric
         else registration_error(warped, task.y))
    quality = measure_quality(q, warped, task.y, warp, e, task.spacing2)
    correspondence, probability = res.correspondence, res.probability
    if symmetric:
        # each moved point's most probable subject point, at the variance the polish
        # starts from (as its symmetric finish reads them)
        correspondence, probability = _posterior_max(
            warped, task.y, max(0.5 * e, task.spacing2), o.w)
    label = "plain" if start is None else start.label
    return _RegOutcome(
        subject=task.subject,
        member=task.member,
        layer=task.layer,
        similarity=task.similarity,
        warped=warped,
        error=e,
        min_jacobian=quality.min_jacobian,
        correspondence=np.asarray(correspondence, dtype=np.intp),
        probability=np.asarray(probability, dtype=np.float64),
        steps=tuple(steps),
        pose=label,
        pose_angle=angle,
        pose_errors={label: e},
        quality=quality,
        symmetric=symmetric,
        symmetric_reason=why_not,
        cpd_start=cpd_start,
        cpd_start_errors=start_errors,
    )


def _register_task(task: _RegTask) -> _RegOutcome:
    """Register the member's warped model onto the subject from every start; keep one.

    The pose as given (the first start) is kept unless another start's registration does
    not fold and reaches an e below its start's margin (``POSE_MARGIN``) times the pose
    as given's, or the pose as given folds clearly (``FAILED_FOLD``) and the other
    reaches no larger an e. A rotated pose thus earns its place by the registration it
    leads to, not by D alone; a turn the model is nearly symmetric under is not tried at
    all, the pose as given aligned by affine ICP in its place (`_Start.decided`). No
    other start is tried when the pose as given's registration does not fold and its e
    is within the sampling floor (``SPACING_FACTOR`` times the subject's h^2): e cannot
    show a closer fit. The registration kept records how scattered the subject's points
    without counterpart on it are (``scattered``), for the tree's acceptance rule.
    """
    out = _register_posed(task)
    return replace(out, scattered=scattered_extra(out.warped, task.y, task.spacing2))


def _register_posed(task: _RegTask) -> _RegOutcome:
    """`_register_task`'s registration, from the start it keeps."""
    if not task.prealign:
        return _register_from(task, None)
    chosen = _register_from(task, task.starts[0])
    if chosen.min_jacobian > 0 and chosen.error <= SPACING_FACTOR * task.spacing2:
        # as close as the sampling lets e show: no other start is tried
        return replace(chosen, pose_errors={chosen.pose: chosen.error}, pose_margin=None)
    starts = task.starts
    if task.pose.any_rotation:
        turned = _rigid_start(task.q, task.y, starts)
        if turned is not None:
            starts = (*starts, turned)
    starts = tuple(st.decided(task.root_shape) for st in starts)
    outs = [chosen, *(_register_from(task, st) for st in starts[1:])]
    # the margin reported: the kept start's, or the first other start's when none beat
    # the pose as given
    margin = starts[1].margin if len(starts) > 1 else None
    # with one start there is nothing to compare: reported as "e", the default
    term, compared_by = _pose_term(chosen, task) if len(starts) > 1 else (None, "e")
    for st, other in zip(starts[1:], outs[1:], strict=True):
        if not other.min_jacobian > 0:
            continue
        failed = chosen.min_jacobian < -FAILED_FOLD
        assert term is not None
        if term(other) < st.margin * term(chosen) or (failed and other.error <= chosen.error):
            chosen, margin = other, st.margin
    errors: dict[str, float] = {}
    for o in outs:  # two turned starts: the lower e
        errors[o.pose] = min(o.error, errors.get(o.pose, math.inf))
    return replace(chosen, pose_errors=errors, pose_margin=margin,
                   pose_compared_by=compared_by)


def _pose_term(given: _RegOutcome, task: _RegTask
               ) -> tuple[Callable[[_RegOutcome], float], str]:
    """What the registrations from a task's starts are compared by (`_register_task`): e;
    or, when the pose as given leaves part of the model with no counterpart on the
    subject (:func:`~registration._error.unmatched_side` ``"model"``: the subject is part
    of the model, occluded or cut off), the mean squared distance from each subject point
    to the nearest model point alone. e counts the model's points without counterpart
    against the pose as given, where a turn that squeezes the whole model onto the part
    fits closer: on the Chui & Rangarajan occlusion series turns of 77-137 degrees won so
    at 0.13-0.55x the e as given, their correspondences wrong by more than the shape's
    radius (bench/RESULTS.md 7.58). A turn still wins when it covers the subject's
    points closer by the start's margin, as a true turn does. Returns the term and its
    name (``pose_compared_by``: "e" or "subject")."""
    if unmatched_side(given.warped, task.y, task.spacing2) != "model":
        return (lambda out: out.error), "e"
    return _subject_half(task.y), "subject"


def _subject_half(y: FloatArray) -> Callable[[_RegOutcome], float]:
    """The subject's half of e of a registration onto `y`: the mean squared distance from
    each subject point to the nearest registered model point. What registrations of a
    subject that is part of the model are compared by: e also counts
    the model's points without counterpart, and falls most where the whole model is
    squeezed onto the part the subject has (`_pose_term`,
    `_passes._attach_leaves`)."""
    return lambda out: directed_errors(out.warped, y)[1]


def _rigid_start(q: FloatArray, y: FloatArray, starts: Sequence[_Start]) -> _Start | None:
    """The turn of the model `q` onto the subject `y` that rigid ICP fits best
    (:func:`~registration._icp.rigid_turns`), as a start to register from, when it is
    distinct (by more than ``POSE_DISTINCT_DEG``) from the turn rigid ICP reaches from
    the pose as given and from the turns of `starts`, and its D is below
    ``TURN_D_RATIO`` times that of the pose as given (:data:`TURN_D_RATIO`); else None.
    Affine ICP refines it into the start's map, and its D is the one the symmetry tests
    of :meth:`_Start.decided` weigh, as for the similarity's pose (`_starts`)."""
    R, t, D = rigid_turns(q, y)
    angles = [rotation_angle(r) for r in R]
    others = [k for k in range(1, len(D))
              if angle_between(angles[k], angles[0]) > POSE_DISTINCT_DEG]
    if not others:
        return None
    best = min(others, key=lambda k: float(D[k]))
    if not D[best] < TURN_D_RATIO * D[0]:
        return None
    if any(st.A is not None and not _distinct(_turn_between(q, st.A, np.eye(2)), R[best])
           for st in starts):
        return None
    icp = affine_icp(q, y, init=(R[best], t[best]), pose="rotation")
    return _Start("rotated", icp.A, icp.t, symmetry=(q, float(icp.distance)))


def _lowest_error(outs: Sequence[_RegOutcome],
                  key: Callable[[_RegOutcome], Any] = lambda o: o.error) -> _RegOutcome:
    """The registration of one subject kept among several, from different members: the
    lowest `key` (e first), except that a registration which turned its member's pose
    (``pose == "rotated"``) is kept only when its e is below ``POSE_MARGIN`` times the
    lowest e of those that did not (and do not fold, unless it folds too), as the pose
    as given is kept within one task (`_register_task`).

    Within one task the pose as given gives way at no larger an e when its own warp
    folds; across members an unfolded registration that keeps its member's pose may
    exist at much the same e. On a straight stroke the two are the stroke's two ends, a
    half turn apart, and e cannot tell them apart: the skeleton of 丨 (Noto Sans) took
    two such turns from one member at 0.92-0.98x the e another member reached as given
    (bench/RESULTS.md 7.43)."""
    if not outs:
        raise ValueError("no registrations to choose from")
    best = min(outs, key=key)
    kept = [o for o in outs if o.pose != "rotated"
            and (o.min_jacobian > 0 or not best.min_jacobian > 0)]
    if best.pose == "rotated" and kept:
        other = min(kept, key=key)
        if not best.error < POSE_MARGIN * other.error:
            return other
    return best


def _turns_wait(best: dict[int, _RegOutcome], joined: Sequence[int]) -> dict[int, _RegOutcome]:
    """Take out of one round's `best` registrations (subject -> kept registration) those
    that turned their member's pose (``pose == "rotated"``) and return them, when the
    tree grows as given: others of the round keep their member's pose, and at least
    twice as many subjects keep it as turn it, counting those of the round with the
    subjects joined before (`joined`: how many kept the pose, how many turned). Those
    subjects wait: they stay among the waiting ones, so the next rounds' new members are
    tried on them too, and each one's turned registration competes with theirs by
    :func:`_lowest_error` (a turn must reach below ``POSE_MARGIN`` times the e of those
    that keep their pose). When a round adds no subject as given, the turns join.

    A turn the similarity offers between two members far apart on the collection's
    deformations can fit better than the pose as given does, though the truth is the pose
    as given: the subject's near neighbours, which would register it as given, have not
    joined yet. On the skeleton of an isosceles triangle (a Y whose arms affine ICP fits
    about as well a third of a turn round), chained (bench/bench_heldout.py, seed 2), an
    edge between two chains' members turned the Y 119 degrees at 0.45x the e as given,
    and the subject's chain neighbour, registered later, followed it: both 1.8 of the
    radius from the truth. Waiting, the subject joined from that neighbour as given, at
    about the turn's e (bench/RESULTS.md 7.63).

    Only where the collection is upright does the pose as given deserve that wait: there
    nearly every registration keeps it, while in a collection turned at random about a
    third do, those whose turn affine ICP reaches from the pose as given. At the rounds
    where a turn was kept: 80-95% on MPEG-7 (eight classes, two roots each), but for
    lmfish, 31-54% (its instances lie at many angles), and flatfish from one root, none;
    10-54% (median 28%) on glyphs turned at random within +-180 degrees. There, later
    members' registrations as given won over right turns: with the turns waiting at any
    share, 11 -> 21 of those 240 subjects were registered wrong; waiting from half, 12."""
    turned = [s for s, out in best.items() if out.pose == "rotated"]
    kept = joined[0] + len(best) - len(turned)
    if len(turned) == len(best) or kept < 2 * (joined[1] + len(turned)):
        return {}
    return {s: best.pop(s) for s in turned}


def _starts(sim: Similarity, member: int, subject: int) -> tuple[_Start, ...]:
    """The pose as given; and the similarity's best pose when it is another pose (turned
    by more than ``POSE_DISTINCT_DEG`` or of the other handedness) that fits clearly
    better: its D below ``POSE_D_RATIO`` times the D reached from the pose as given.
    Whether its turn is a near-symmetry of the model, or of the root's shape (then the
    pose as given, aligned, is tried in its place) is decided by :meth:`_Start.decided`
    where the task runs."""
    given = _Start("as given")
    A = sim.A[member, subject]
    A_g = sim.A_given[member, subject]
    d, d_g = sim.D[member, subject], sim.D_given[member, subject]
    if not (np.isfinite(d) and np.isfinite(d_g)) or not d < POSE_D_RATIO * d_g:
        return (given,)
    model = sim.shape(member)
    if not _distinct(_turn_between(model, A, A_g), np.eye(2)):
        return (given,)
    return (given, _Start("rotated", A, sim.t[member, subject], symmetry=(model, float(d))))


def _turn_between(points: FloatArray, A: FloatArray, B: FloatArray) -> FloatArray:
    """The turn that carries the centred `points` as `B` maps them closest to where `A`
    maps them (Procrustes, :func:`~registration._icp._pairwise.fit_rigid`; a
    rotation-reflection where the two maps differ in handedness). For a shape that spans
    the plane it is the rotation nearest ``A B^-1``; of a straight stroke affine ICP
    leaves the map across the stroke to chance, and only the points say how far the
    stroke turned."""
    mirror = bool(np.linalg.det(A) * np.linalg.det(B) < 0)
    return fit_rigid(points @ B.T, points @ A.T, mirror=mirror)[0]


def _distinct(A: FloatArray, B: FloatArray) -> bool:
    """Whether two linear maps are different poses: of the other handedness, or turned
    apart by more than ``POSE_DISTINCT_DEG``."""
    return bool(np.sign(np.linalg.det(A)) != np.sign(np.linalg.det(B))
                or angle_between(rotation_angle(A), rotation_angle(B)) > POSE_DISTINCT_DEG)


def _self_map(model: FloatArray, A: FloatArray) -> AffineICPResult | None:
    """The turn (or mirror) of the pose `A` from the pose as given (the model as it is:
    the pose as given's CPD runs on the normalised shapes without an affine step), settled
    by affine ICP of the model onto itself; None when it settles on no distinct pose or,
    on the model's points, far from a similarity (`_deviation_from_similarity`: a
    symmetry is an isometry; affine ICP can otherwise fold a shape onto itself by a 5:1
    stretch at a D as low as a genuine turn's, as on a generated outline turned by 120
    degrees). The model's points are centred (the similarity's normalised shapes), so
    the symmetry is about the centroid."""
    turn, shift = _rigid_self_fit(model, _turn_between(model, A, np.eye(2)))
    mode = "affine" if np.linalg.det(turn) < 0 else "rotation"
    icp = affine_icp(model, model, init=(turn, shift), pose=mode)
    if not (_distinct(_turn_between(model, icp.A, np.eye(2)), np.eye(2))
            and _deviation_from_similarity(icp.A, model) <= SYMMETRY_MAX_DEVIATION):
        return None
    return icp


def _rigid_self_fit(model: FloatArray, turn: FloatArray, max_iter: int = 50
                    ) -> tuple[FloatArray, FloatArray]:
    """The isometry nearest `turn` (a rotation, or a rotation-reflection) that maps the
    model onto itself: ICP with bidirectional closest points, as affine ICP's (eq. 9),
    each step the best rigid map of that handedness (Procrustes); ``(R, t)``.

    `_self_map`'s affine ICP starts from it. From the turn alone, affine ICP of a
    straight stroke one or two pixels wide stops where it starts: the stroke has no width
    to fit an affine map's second column to, so the first step's map is near singular
    (the skeleton of 一 in Noto Sans, turned 172 degrees, stayed at D 0.037 against 0.002
    for the pose). A rigid step needs no width."""
    R, t, *_ = _refine(model, model, cKDTree(model), turn, np.zeros(2), max_iter, 1e-6,
                       proper=bool(np.linalg.det(turn) > 0), rigid=True)
    return R, t


def _ratio_to_pose(settled: AffineICPResult | None, d_pose: float) -> float:
    """How closely the turn (or mirror) of a pose from the pose as given maps the model
    onto itself (`settled`, :func:`_self_map`), relative to how closely the pose maps it
    onto the subject: D(model, model) over ``d_pose``; infinite when the turn is no
    symmetry (no self-map) or there is no positive ``d_pose``.

    A small ratio means the two poses differ by a near-symmetry of the model (an O
    turned half a turn, an S, a straight stroke): e then compares how the two
    registrations fit the few parts that break the symmetry, and a lower e from the
    turned start may say only which start CPD settled better from, while the turned
    correspondences are wrong by the whole turn (the Latin O in a serif font: direct CPD
    took a 160-degree turn at 0.47x the e, correspondence error 1.99 of the radius
    against 0.20 as given; bench/RESULTS.md 7.39).
    """
    if settled is None or not d_pose > 0:
        return math.inf
    return float(settled.distance / d_pose)


def _deviation_from_similarity(A: FloatArray, points: FloatArray) -> float:
    """RMS distance between the linear map `A` of centred `points` and the similarity of
    `A`'s handedness that best matches it on them (Procrustes: the rotation, or
    rotation-reflection, and scale that best carry the points where `A` does), over the
    points' RMS radius: 0 for a similarity, and for a map that only shears or stretches
    across a straight stroke, where there are no points to move."""
    mapped = points @ A.T
    rotated = points @ _turn_between(points, A, np.eye(2)).T
    size = float(np.sum(points * points))
    if not size > 0:
        return math.inf
    scale = float(np.sum(mapped * rotated)) / size
    return math.sqrt(float(np.sum((mapped - scale * rotated) ** 2)) / size)


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

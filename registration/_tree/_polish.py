"""A final polish of each of the tree's registrations: CPD from the root model as warped
along the subject's chain (at layer 2: its one edge) onto the subject, coarse to fine, so
the slide the chain accumulated can relax and a single edge's CPD can finish fitting; two
links or more from the root, then a consensus with the root's own registration.

Each edge of a tree path registers the root model, as already warped onto the parent,
onto the child; the error of one link adds up along the path (on the 永 skeleton chains
one CPD link started from the parent's true image leaves 0.04-0.05 of the subject's size,
where CPD started on the subject's true image settles at 0.015-0.03). After the tree is
built, every attached subject at layer >= ``POLISH_MIN_LAYER`` is registered again, in
the stages of ``POLISH_BETA_FACTORS``: each stage's CPD moves the root's points, where the
previous stage (first: the chain) left them, onto the subject (the tree's CPD options but
a kernel width beta scaled by the stage's factor; the points keep the root's order), with
sigma^2 starting from that start's residual rather than from the spread of all pairs (it
starts aligned), its EM accelerated (``cpd_nonrigid(accelerate=True)``; see `_stages`),
and the model normalised by CPD's own frame only as far as the difference of the two
shapes' centroids and radii is more than their samplings' noise (`_model_frame`).
A stage is kept only when it passes the checks the tree holds every registration to: its
warp does not fold, its e is no larger than its start's, and its own confidence is at least
``MIN_CONFIDENCE``; a finer stage must also lower e by a fifth
(``POLISH_FINER_MAX_E_RATIO``). A rejected stage is skipped: the next starts
where the last kept one (or the chain) left the points. A chain's composed field has more
freedom than one CPD's, so its e can be lower than a wide stage's while its points have
slid: there the finer stage, from the chain, still lowers e and the correspondence error.
At layer 2, where the chain is one CPD from the root and its e already at the sampling
floor or above, the whole polish (the finishes below included) must lower that e by a
fifth too, or the edge's own registration stays (``SINGLE_EDGE_MAX_E_RATIO``; recorded
in ``quality["polish_not_kept"]``); below the floor, so must one that moves the points
less than a spacing (``SINGLE_EDGE_MIN_MOVE``).

Subjects are polished a tree level at a time, parents first. At layer >=
``POLISH_FROM_PARENT_MIN_LAYER`` a subject whose parent's polish moved it also registers
its edge again, from the parent's polished points (the tree made it from the parent's
chained ones, so the child inherited the parent's slide). When that edge's e is no larger
than the chain's, both are polished and the subject moves halfway between the two
polished registrations, polished again (kept at up to ``CONSENSUS_MAX_E_RATIO`` times
the lower e of the two; else the lower of the two); the subject's transform then extends
the parent's polished chain (unless the chain's own polish won).

At layer >= ``POLISH_CONSENSUS_MIN_LAYER`` the subject is also registered from a partner
(`consensus_partner`: the member nearest it by D, other than its parent and already
polished, carried onto it by one edge; the root itself, a direct registration, when no
member is nearer or the subject has fewer than ``CONSENSUS_PARTNER_MIN_POINTS`` points)
and polished the same way, and the chain's polished points are moved halfway to those
and polished again (`_consensus`): kept when that e is at most
``CONSENSUS_MAX_E_RATIO`` (1.1) times the chain's, or else when, once it and the chain are
each finished (below), its e is no higher than the chain's (`_finished_apart`). The
subject's transform stays its chain, extended by the polish's steps (the chain's stages,
the step halfway, the stages from there), so the stored-resolution stage reads the edge
the tree built and the polish apart (:mod:`._resolution`).
Last, every polished subject is finished by one CPD from the root model itself, started
where the polish left it (`_finish`): every registration before it penalised its field
from its own start, the finish's from the root. Then the finish is made symmetric
(`_symmetric`): the subject is registered back onto the root from there, and the model's
points move halfway to where the inverse of that backward field puts them.
A tree decided at a working resolution (:mod:`._resolution`) is polished once more on
the stored points, without the consensus, every subject's edge registered again there,
its fields fitted through the stored stage's control points, its stages' through twice
as many (``quality["stored_polish"]``; 7.31, 7.32).
Once every subject is polished, each whose polish was kept moves its points a fifth of
the way to plain CPD's along the subject's outline, where plain CPD fits the subject
about as closely (`_along_plain`, at the resolution the result is reported at; 7.56).
Figures: bench/RESULTS.md, sections 0.4 (one stage), 0.5 (coarse to fine), 0.6
(layer 2, skipping) and 0.9 (the consensus); 7.4 (accelerated EM), 7.5 (the
consensus's e rule), 7.7 (edges from polished parents, the halfway step), 7.11 (the
stages' normalisation), 7.12 (the finish), 7.16 (the symmetric finish), 7.25 (a
refused consensus judged again once finished) and 7.27 (the consensus's partner).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection
from dataclasses import dataclass, replace
from functools import cached_property, partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .._cpd import CPDOptions, CPDResult, cpd_nonrigid
from .._cpd._estep import _posterior_max
from .._error import SCATTER_MIN, registration_error, scattered_extra
from .._executor import Executor, owned_executor
from .._icp._pairwise import fit_rigid
from .._pointmap import PointTransform, jacobian_determinants
from .._points import farthest_point_indices, rms_distance, sampling_irregularity
from .._pose import rotation_angle
from .._quality import RegistrationQuality, measure_quality, outline_tangents
from .._result import SubjectResult
from .._similarity import ProgressCallback
from .._transform import AffineTransform, ChainTransform
from ._collection import _Collection
from ._rules import MIN_CONFIDENCE, _spacing_floor
from ._symmetric import Halfway, NoHalfway, fitted_step, halfway_back
from ._tasks import _distinct, _register_task, _RegOutcome, _RegTask

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Subjects at this tree layer or deeper are polished: every attached subject. Layer 2 is
#: registered from the root directly, so no chain accumulated there, but its CPD stopped
#: at its tolerance from a start far from the subject; restarted from where it stopped
#: (sigma^2 from the residual) it keeps fitting. Ground truth (bench/RESULTS.md 0.6):
#: Chui fish 0.76 -> 0.26 of plain CPD, Chinese 0.64 -> 0.44, glyph edges and skeletons
#: within +-0.02 (their layer-2 subjects gain little).
POLISH_MIN_LAYER = 2
#: The polish's CPD stages, coarse to fine: the kernel width beta of each as a fraction of
#: the tree's. The first, with the edges' own kernel, relaxes the slide the chain
#: accumulated; the second, from there (already aligned, so a finer kernel cannot wander),
#: fits the finer deformation the edges' smooth kernel leaves out. Each stage is kept only
#: when it passes the checks; a rejected one is skipped.
POLISH_BETA_FACTORS = (1.0, 0.5)
#: A stage with a finer kernel than the first is kept only when its e is at most this
#: fraction of its start's. A finer kernel always lowers e a little: it fits where the
#: subject's own points happen to lie, sliding the model's points along the outline. Over
#: the finer stages of seven ground-truth families (bench/RESULTS.md 0.8; geometric
#: mean change of the correspondence error), those that lowered e by less than a fifth
#: worsened the correspondences on MPEG-7 (x1.21, 68 stages) and on lmfree2d / Momocs
#: outlines of 80-120 randomly subsampled points (x1.14, 137) and did next to nothing on
#: the 永 edges and skeletons (x0.98, 26); those that lowered it by more than 30 % improved
#: them on every family but those outlines (MPEG-7 x0.81, edges x0.75, skeletons x0.85,
#: Chui x0.14-0.19). With the rule the MPEG-7 chains go from 0.81 to 0.75 of plain CPD
#: (worst run 1.28 -> 1.12) and those outlines from 1.16 to 1.12; every other family
#: moves by at most 0.015.
POLISH_FINER_MAX_E_RATIO = 0.8
#: At layer 2 the chain is one CPD from the root, and the whole polish (stages, finish,
#: symmetric finish) only goes on fitting that one registration (:data:`POLISH_MIN_LAYER`);
#: there is no slide of a chain for it to relax. When the edge's e is at or above the
#: subject's sampling floor (``SPACING_FACTOR`` h^2, the e two independent samplings of
#: one outline leave), its residual can be the samples' noise alone, and the polish is
#: kept only when it lowers that e to at most this fraction, the finer stages' margin.
#: Prints of one type (each subject one small warp from the root, bench/RESULTS.md 7.53)
#: sit at 0.5-1 h^2 and are polished to 0.83-0.97x the e with their correspondences
#: 1.1-1.3x worse. Below the floor the two samplings coincide (the same points moved, as
#: in the Chui series), so what is left is deformation: a Chui fish edge CPD left at
#: 0.17 h^2 (correspondence error 0.15) is polished to 0.91x the e and 0.09. Below the
#: floor see :data:`SINGLE_EDGE_MIN_MOVE`. Decided at the working resolution; a single
#: edge whose polish is not kept there is not polished at the stored resolution either.
SINGLE_EDGE_MAX_E_RATIO = POLISH_FINER_MAX_E_RATIO
#: Below the sampling floor, a single edge's polish that lowers e by less than
#: :data:`SINGLE_EDGE_MAX_E_RATIO` is kept only when it moves the model's points by at
#: least this many of the subject's spacings h (RMS). The floor is set for independent,
#: irregular samplings; evenly spaced ones (a farthest-point subsample, as the working
#: resolution of a large shape is) leave an e near h^2 / 12 between two samplings of one
#: outline, under the floor, so there a residual below it can still be noise. A move
#: shorter than the spacing only exchanges which of the subject's samples a point sits
#: nearest, which the samples cannot decide; a longer one that lowers e leaves a wrong
#: minimum. Ground truth (bench/RESULTS.md 7.54): 1200-point prints of one type, at the
#: 400-point working resolution, e 0.12-0.17 h^2, polished 0.80-0.96x the e with moves of
#: 0.10-0.59 h, correspondences 1.14x plain CPD's; the Chui fish edge above moved 1.10 h.
SINGLE_EDGE_MIN_MOVE = 1.0
#: Subjects at this layer or deeper (two links or more from the root) are also registered
#: from a partner, for a consensus with their chain (see `_consensus`; the root directly
#: until bench/RESULTS.md 7.27, see `CONSENSUS_PARTNER_MIN_POINTS`). At layer 2 the chain
#: is the root's direct registration. Ground truth, with the root as the partner
#: (bench/RESULTS.md 0.9, 63 runs; tree / plain CPD before -> after): 永 skeletons
#: 0.79 -> 0.74, edges 0.60 -> 0.58, Chui fish 0.26 -> 0.25, Chinese 0.44 -> 0.33,
#: generated 0.46 -> 0.40, MPEG-7 0.75 -> 0.73, evenly sampled outlines 0.71 -> 0.68, other
#: characters 0.78 -> 0.76; random subsets of outlines 1.12 -> 1.15. Up to five more CPD
#: per subject.
POLISH_CONSENSUS_MIN_LAYER = 3
#: The kernel width of the step that moves the chain's model halfway to the partner's
#: registration, as a fraction of the tree's beta: at a quarter it reproduces the halfway
#: points to 0.0004-0.006 of the subject's size (0.006-0.03 at the tree's own width, which
#: cannot follow the two registrations' difference along a stroke) and the ground truth of
#: the exact halfway start (bench/RESULTS.md 0.9).
CONSENSUS_KERNEL_FACTOR = 0.25
#: The consensus is kept when its e is at most this multiple of the polished chain's. A
#: chain's composed field has more freedom than one CPD's and slides along the subject's
#: own sampling to a lower e (see the module doc), so the consensus, which undoes part of
#: that slide, may sit at a slightly higher e while its correspondences are better; a
#: direct registration that went wrong leaves an e far above. Ground truth
#: (bench/RESULTS.md 7.5; tree / plain CPD at 1 -> 1.1): MPEG-7 0.738 -> 0.730 (worst run
#: 1.11 -> 1.08), 永 edges 0.581 -> 0.576, skeletons 0.729 -> 0.726, evenly sampled
#: outlines 0.685 -> 0.681, random subsets 1.143 -> 1.139, Chui and generated unchanged; at
#: 1.25 generated gains (0.344) and the rest move by at most 0.004, but the worst runs of
#: MPEG-7 and the random subsets lose (1.08 -> 1.10, 1.27 -> 1.30).
CONSENSUS_MAX_E_RATIO = 1.1
#: A consensus refused by that rule is judged again once both it and the chain are
#: finished from the root model (see `_finished_apart`): kept when its finished e is at
#: most this multiple of the finished chain's. Ground truth (bench/RESULTS.md 7.25, 89
#: runs; tree / plain CPD before -> after): 永 skeletons 0.564 -> 0.557 (worst run 0.782
#: -> 0.744), edges 0.510 -> 0.509, random subsets of outlines 1.043 -> 1.040 (runs above
#: 1.05x: 7 -> 6), outline-arc 0.962 -> 0.964 (one run 1.028 -> 1.060), MPEG-7, even
#: outlines, other glyphs, generated shapes and the Chui series within 0.001. At 0.95 the
#: skeletons gain half as much; at 1.1 the edges lose (0.513) and outline-arc too (0.969).
#: One more CPD for each subject whose consensus was refused after its halfway step.
CONSENSUS_FINISHED_MAX_E_RATIO = 1.0
#: The consensus's partner (see `consensus_partner`) is the member nearest the subject by
#: D (the root when none is nearer) for subjects of at least this many points, and the
#: root itself for sparser ones. A second chain of about the chain's own length errs about
#: as much as the chain, and differently: halfway between the two, more of each error
#: cancels than against one CPD from the root across the whole difference. But every link
#: adds the field noise of a CPD fitted to a sample of the subject, which grows as the
#: points get fewer (the field's degrees of freedom over the points: about 0.03 at 400
#: points and 0.09 at 100 for the edges' kernel, bench/RESULTS.md 7.22). Ground truth
#: (bench/RESULTS.md 7.27; tree / plain CPD, with the member as partner at every size
#: against the root): 永 edges 0.509 -> 0.484 and skeletons 0.558 -> 0.543 (400 points;
#: far halves above 0.6x on 5 of 24 runs -> 2), generated shapes (200) 0.404 -> 0.364,
#: MPEG-7 (400) 0.584 -> 0.571, other glyphs (400) 0.658 -> 0.655; but outlines of 80-120
#: points lose: random subsets 1.041 -> 1.064 (runs above 1.05x: 6 -> 8), outlines
#: sampled anew on each shape 0.964 -> 0.970 (1 -> 2), the lmfree2d landmarks 0.859 ->
#: 0.875 of plain CPD's landmark error. 150 lies between the two groups.
CONSENSUS_PARTNER_MIN_POINTS = 150
#: Subjects at this layer or deeper whose parent's polish moved it also register their
#: edge again, from the parent's polished points (see `_edge_from_parent`): the tree's
#: edges were made from each parent's chained registration, and a child inherits its
#: parent's slide. Both registrations of the edge are polished and the subject moves
#: halfway between them, polished again (`_halfway`; else the one with the lower e). The
#: subjects are polished a tree level at a time, parents first. Ground truth
#: (bench/RESULTS.md 7.7, 80 runs; tree / plain CPD before -> after): 永 edges 0.593 ->
#: 0.554 (far half 0.537 -> 0.490), skeletons 0.652 -> 0.606 (0.603 -> 0.546, worst run's
#: far half 0.894 -> 0.807), other glyphs 0.756 -> 0.736, MPEG-7 0.731 -> 0.706, outlines
#: 0.682 -> 0.655, generated 0.430 -> 0.406; Chui Chinese 0.333 -> 0.360 and randomly
#: subsampled outlines 1.139 -> 1.155 lose.
POLISH_FROM_PARENT_MIN_LAYER = 3
#: The finish (see `_finish`): the kernel width of its CPD as a fraction of the tree's
#: beta, and its regulariser as a multiple of the tree's lambda.
FINISH_BETA_FACTOR = 0.5
FINISH_LMBDA_FACTOR = 2.0
#: The finish is kept when its e is at most this multiple of the e it started from: like
#: the consensus (:data:`CONSENSUS_MAX_E_RATIO`), it undoes part of a slide the subject's
#: own sampling let the chain settle into, at an e that may be a little higher.
FINISH_MAX_E_RATIO = 1.1
#: The last step of the polish (`_along_plain`): how far each model point moves, along
#: the subject's outline, towards where plain CPD from the root puts it; only when the
#: polished e is above ``ALONG_PLAIN_MIN_E_RATIO`` times plain CPD's.
#: Along the outline neither e nor CPD's data term sees where a point lies; there the
#: tree's registration and plain CPD's are two estimates of one correspondence, each with
#: its own slide (the tree's gathered link by link, plain CPD's from bridging the whole
#: difference at once), and moving the tree's part of the way to plain CPD's averages
#: part of the two slides out. Where plain CPD's e is more than twice the tree's, plain
#: CPD has not fitted the subject and its place along the outline says nothing. Measured
#: on the default ground-truth bench's families (bench/RESULTS.md 7.56). Shapes of any
#: size take it (bench/RESULTS.md 7.57): it was first kept off shapes under 150 points, the
#: symmetric edges' bound, but the e rules alone keep it off the Chui & Rangarajan and
#: generated families (4 of their 60 polished subjects have plain CPD's e within twice
#: the polished e, and the full step's e is above 1.1x on all 4; 2 take the half step of
#: ``ALONG_PLAIN_BACKTRACK``), and on outlines of 80-120 points it gains (random subsets
#: 0.938 -> 0.924 of plain CPD, worst run 1.14 -> 1.12).
ALONG_PLAIN_WEIGHT = 0.2
ALONG_PLAIN_MIN_E_RATIO = 0.5
#: A step refused (its e above :data:`FINISH_MAX_E_RATIO` times the polished e, its
#: confidence, a fold) is tried once more this fraction of the way: along the tangent a
#: point leaves a curved outline, and half the step leaves it a quarter as far. On the
#: Latin letters 48 of 403 steps were refused on e and would have gained (0.95 of the
#: polished ground-truth error). At half the weight (bench/RESULTS.md 7.57) Latin goes
#: 0.855 -> 0.852 of plain CPD (runs above 1.05x 2 -> 1), outlines of random subsets
#: 0.924 -> 0.918; the Chui fish lose 0.415 -> 0.428 (one subject, 0.090 -> 0.095 against
#: plain CPD's 0.150), evenly sampled outlines, strokes and the generated family 0.001.
ALONG_PLAIN_BACKTRACK = 0.5
#: The progress stage of the polish at the stored resolution (see :class:`AtStored`); it
#: counts subjects, as ``full resolution``.
STORED_STAGE = "polish full resolution"


@dataclass(frozen=True)
class AtStored:
    """The polish at the stored resolution (:func:`registration._tree._resolution.
    _polish_stored`): `control`, the root indices every CPD's field through the model's
    points is fitted with (the backward CPD's with as many farthest points of the
    subject; None: every point), but for the polish's stages (:func:`_stages`), which fit
    theirs with `stage_control`; `edge_affines`, each subject's edge's affine
    pre-alignment. There every subject registers its edge again (from the root's own
    points at layer 2, else from the parent as polished there, moved or not) whatever
    that edge's e; the polish is recorded in ``quality["stored_polish"]``, reported as
    :data:`STORED_STAGE`, and the subject keeps the confidence the decisions were taken
    with."""

    control: IntArray | None
    edge_affines: dict[int, tuple[PointTransform, ...]]
    # the root indices the polish's stages fit their fields with (None: every point)
    stage_control: IntArray | None = None

@dataclass(frozen=True)
class _PolishTask:
    subject: int
    start: FloatArray  # the root model warped along the chain (subject's normalised coords)
    error: float  # the chained registration's e
    y: FloatArray  # the subject, normalised coordinates
    cpd: CPDOptions
    spacing2: float
    # the root's sampling_irregularity (the model's points keep the root's sampling)
    model_irregularity: float
    # the root model itself (its normalised coordinates), for the finish (see `_finish`)
    model: FloatArray
    # the consensus's partner registration (layer >= POLISH_CONSENSUS_MIN_LAYER; see
    # `_consensus` and `consensus_partner`): the root model as warped onto the partner
    # member, registered onto the subject as an edge (to run, or already run; the root's
    # own: the direct registration), else None
    partner: _RegTask | _RegOutcome | None = None
    # the parent's polished points (the parent's normalised coordinates) when its polish
    # moved it (layer >= POLISH_FROM_PARENT_MIN_LAYER), and the affine pre-alignment steps
    # the subject's edge started with; the edge is registered again from there
    from_parent: FloatArray | None = None
    edge_affine: tuple[PointTransform, ...] = ()
    # whether that edge goes on only at no larger an e than the chain's (else the halfway's
    # own rule decides: the stored resolution's polish, see `_polish_subjects`)
    edge_within_chain_e: bool = True
    # the model (root) indices every CPD's field through the model's points is fitted
    # with but the stages' (`stage_control`), and the subject indices the backward CPD's
    # is (None: every point)
    control: IntArray | None = None
    subject_control: IntArray | None = None
    # the model indices the polish's stages (`_stages`) fit their fields with
    stage_control: IntArray | None = None
    # the subject's chain is one CPD from the root (layer 2, at the working resolution):
    # the polish is kept only as `_single_edge_refusal` allows
    single_edge: bool = False
    # the subject is a leaf that is part of the model (``quality["leaf_compared_by"]``
    # "subject", `_passes._attach_leaves`): no polish (`_part_refusal`)
    part_of_model: bool = False
    # end with the step towards plain CPD (`_along_plain`): at the resolution the result
    # is reported at, once (not at a working resolution a stored one follows)
    along_plain: bool = True

    @cached_property
    def irregularity(self) -> float:
        """The subject's :func:`~registration._points.sampling_irregularity`, computed
        once for the polish's several calls of :func:`_stages`."""
        return sampling_irregularity(self.y)


@dataclass(frozen=True)
class _Stages:
    """Where the polish's CPD stages left the model: the stages kept (none: the start)."""

    warped: FloatArray
    error: float
    steps: tuple[PointTransform, ...]
    quality: tuple[RegistrationQuality, ...]  # of each stage kept
    correspondence: IntArray
    probability: FloatArray


@dataclass(frozen=True)
class _PolishOutcome:
    subject: int
    warped: FloatArray
    error: float
    correspondence: IntArray  # of `warped` (empty when `refused`: the edge's own stay)
    probability: FloatArray
    steps: tuple[PointTransform, ...]  # the transform's steps after the chain (none: rejected)
    quality: tuple[RegistrationQuality, ...]  # of each CPD stage among them
    consensus: dict[str, Any] | None = None  # what the consensus found (see `_consensus`)
    # the edge registered again from the parent's polished points, when kept: its steps
    # (they lead `steps`, which then extend the parent's polished chain), and what it found
    edge_steps: tuple[PointTransform, ...] = ()
    edge_quality: RegistrationQuality | None = None
    from_parent: dict[str, Any] | None = None
    finish: dict[str, Any] | None = None  # what the finish found (see `_finish`)
    symmetric: dict[str, Any] | None = None  # what the symmetric finish found (`_symmetric`)
    along_plain: dict[str, Any] | None = None  # what the step towards plain CPD found
    # the registration with that step, when kept: applied once every subject is polished
    # (`_polish_subjects`), so that no child's polish starts from it
    along_stages: _Stages | None = None
    # a single edge's polish not kept (`single_edge`): the e it reached, and why; recorded
    # in the subject's ``quality["polish_not_kept"]`` (``"polish"`` stays a kept polish's)
    refused: dict[str, Any] | None = None


def _model_frame(cur: FloatArray, y: FloatArray, model_irregularity: float,
                 irregularity: float) -> tuple[FloatArray, float]:
    """The shift and scale a polish stage's CPD normalises the model `cur` by (the
    subject `y` keeps its own centroid and RMS radius).

    CPD normalises each set by its own centroid and radius, which moves `cur` by the
    difference of the two centroids and scales it by the ratio of the two radii. Started
    on the subject, that difference is the model's drift (the field penalises a shift; the
    normalisation is what lets CPD undo one) plus the two shapes' sampling noise: two
    independent random samples of one outline, of m and n points, differ in centroid by
    about ``s^2 (1/m + 1/n)`` in square (``s`` the radius) and in log radius by ``k (1/m +
    1/n) / 4`` (``k`` the relative variance of the squared radii), where evenly spaced
    samples differ by next to nothing. So each difference is shrunk by the part that
    sampling noise explains (``d -> d max(0, 1 - v / d^2)``, ``v`` that noise, each set's
    share weighted by the square of its :func:`~registration._points.
    sampling_irregularity`, at most 1): an evenly sampled pair is normalised as CPD would
    (the full difference), a pair of sparse random samples about as one frame. Squared,
    because a centroid's noise comes from the sampling's long-range unevenness, which
    nearly even samples (jittered spacing, irregularity 0.1-0.4) lack: with the weight
    linear in the irregularity the 永 chains lost 0.01 of plain CPD's error, squared they
    do not (bench/RESULTS.md 7.11, where the ground truth of both is)."""
    cc, cy = cur.mean(axis=0), y.mean(axis=0)
    r2c = np.sum((cur - cc) ** 2, axis=1)
    r2y = np.sum((y - cy) ** 2, axis=1)
    sc, sy = float(np.sqrt(r2c.mean())), float(np.sqrt(r2y.mean()))
    if not (sc > 0 and sy > 0):  # a collapsed set: CPD's own frame (scale 1 if none)
        return cc, sc if sc > 0 else 1.0
    rho_m, rho_y = min(1.0, model_irregularity) ** 2, min(1.0, irregularity) ** 2
    m, n = len(cur), len(y)
    d = cy - cc
    d2 = float(d @ d)
    noise = rho_m * sc * sc / m + rho_y * sy * sy / n
    k_shift = max(0.0, d2 - noise) / d2 if d2 > 0 else 0.0
    ds = math.log(sy / sc)
    noise = (rho_m * float(r2c.var()) / float(r2c.mean()) ** 2 / (4 * m)
             + rho_y * float(r2y.var()) / float(r2y.mean()) ** 2 / (4 * n))
    k_scale = max(0.0, ds * ds - noise) / (ds * ds) if ds != 0 else 0.0
    f = math.exp(k_scale * ds)  # the model's scale change, as CPD's normalisation sees it
    # normalised model (cur - shift) / scale == the moved model normalised by the subject's
    # own frame: moved = cc + k_shift d + f (cur - cc)
    scale = sy / f
    shift = cc + (1.0 - k_shift) * d / f
    return shift, scale


def _stages(start: FloatArray, e_start: float, y: FloatArray, o: CPDOptions,
            spacing2: float, model_irregularity: float,
            irregularity: float | None = None, control: IntArray | None = None) -> _Stages:
    """The polish's CPD stages (:data:`POLISH_BETA_FACTORS`) from `start`, each kept only
    when it passes the checks (see the module doc).

    Each stage's EM is accelerated: started aligned, plain EM converges linearly (the
    objective's relative change falls about 0.8x per iteration on the 永 glyphs), and
    SQUAREM's extrapolation, checked against the objective, reaches the same fixed point in
    about half the iterations (bench/RESULTS.md 7.4: correspondence error against plain
    CPD within 0.007 of plain EM's on seven families, 0.017 better on the eighth; the
    polish of 73 glyphs in 0.68x the CPU). The tree's own edges, which start far from
    their subject and whose EM path through the shrinking variance matters, are not
    accelerated.

    Each stage normalises the model by :func:`_model_frame` (`model_irregularity`: the
    root's :func:`~registration._points.sampling_irregularity`; `irregularity`: the
    subject's, computed here when not given)."""
    if irregularity is None:
        irregularity = sampling_irregularity(y)
    cur, e_cur = start, e_start
    steps: list[PointTransform] = []
    quality: list[RegistrationQuality] = []
    last: CPDResult | None = None  # the last stage kept
    for stage, factor in enumerate(POLISH_BETA_FACTORS):
        # the start already lies on the subject: sigma^2 from its residual (e = mean
        # squared nearest distance, both ways; sigma^2 is per coordinate), not from the
        # spread of all pairs, which would let CPD wander off again; never below the
        # squared point spacing
        sigma2 = max(0.5 * e_cur, spacing2)
        res = cpd_nonrigid(cur, y, **o.keywords(beta=factor * o.beta), sigma2=sigma2,
                           accelerate=True, control=control,
                           model_frame=_model_frame(cur, y, model_irregularity, irregularity))
        warped = np.asarray(res.warped, dtype=np.float64)
        e = registration_error(warped, y)
        q = measure_quality(cur, warped, y, res.transform, e, spacing2)
        max_e = e_cur if stage == 0 else POLISH_FINER_MAX_E_RATIO * e_cur  # finer: see above
        if not (q.min_jacobian > 0 and e <= max_e and q.confidence >= MIN_CONFIDENCE):
            continue  # this stage is not kept; the next starts where the last kept left
        steps.append(res.transform)
        quality.append(q)
        cur, e_cur = warped, e
        last = res
    # the correspondences of the last stage kept only (each is a pass over every pair)
    corr = np.zeros(0, dtype=np.intp) if last is None else np.asarray(last.correspondence,
                                                                       dtype=np.intp)
    prob = np.zeros(0) if last is None else np.asarray(last.probability, dtype=np.float64)
    return _Stages(warped=cur, error=e_cur, steps=tuple(steps), quality=tuple(quality),
                   correspondence=corr, probability=prob)


def consensus_partner(distance: FloatArray, results: dict[int, SubjectResult],
                      members: Collection[int], subject: int, root: int, n_points: int) -> int:
    """The member whose registration the consensus of `subject` pairs with its chain.

    `distance[m]` is D(m, subject) (NaN where the pair was not computed). The candidates
    are the root and the tree's members (not its leaves) already polished when `subject`
    is (nearer the root: fewer links on their path), other than its parent, whose
    registration the subject's own chain and its edge from the polished parent already
    carry. The nearest by D wins, the root on a tie; a subject of fewer than
    :data:`CONSENSUS_PARTNER_MIN_POINTS` points (`n_points`) takes the root."""
    own = results[subject]
    if n_points < CONSENSUS_PARTNER_MIN_POINTS or own.path is None:
        return root
    d = np.asarray(distance, dtype=np.float64)
    nearer = np.flatnonzero(d < d[root])  # NaN (not computed) never compares less
    for m in (int(i) for i in nearer[np.argsort(d[nearer], kind="stable")]):
        r = results.get(m)
        if (m in members and m not in (root, subject, own.parent) and r is not None
                and r.warped is not None and r.path is not None
                and len(r.path) < len(own.path)):
            return m
    return root


def _consensus(task: _PolishTask, chain: _Stages) -> tuple[_Stages | None, dict[str, Any]]:
    """The consensus of the chain's (polished) registration with its partner's.

    The partner's registration (:func:`consensus_partner`: the root model as warped onto
    a member, polished, carried onto the subject by one edge; or the root's own, a direct
    registration) is run as the tree's edges are (pose handling included) and polished the
    same way; the model is moved halfway between the two (by CPD's field through those
    points, :func:`~registration._cpd.interpolating_field`) and polished from there.
    The two registrations err differently: the chain by its links' slides adding up, the
    partner's by its own links' and by the shape difference its last CPD bridges (the
    whole of it for the root); halfway, part of each cancels (measured, not assumed:
    bench/RESULTS.md 0.9, 7.27). Kept when
    the step and the stages do not fold, at least one stage passes its checks and the e
    reached is at most :data:`CONSENSUS_MAX_E_RATIO` times the chain's: a partner's
    registration that went wrong (as a direct one does on the large differences the tree
    exists for) leaves a far worse e and is not kept.

    Returns the halfway registration (the step and the stages from there, whatever
    passed; None when there is no step: the partner's registration or the step folds) and
    what was found, ``kept`` among it: a refused one is for :func:`_finished_apart` to
    judge again.
    """
    assert task.partner is not None
    partner = (task.partner if isinstance(task.partner, _RegOutcome)
               else _register_task(task.partner))
    info: dict[str, Any] = {"partner": partner.member, "partner_error": partner.error,
                            "pose": partner.pose, "kept": False}
    if not partner.min_jacobian > 0:
        info["reason"] = "the partner's registration folds"
        return None, info
    # Not formed when the partner places the root's points a distinct pose from where the
    # chain places them (turned by more than POSE_DISTINCT_DEG, or mirrored: `_distinct`
    # of the isometry between the two): they disagree on the pose, not on a slide, and
    # the model halfway between two poses is neither. On a near-symmetric outline e cannot
    # refuse it, the halfway points still lying on the subject: an ellipse's edges
    # (generated chains, seed 0) took a consensus with a partner registered turned, at
    # 1.1x the chain's e, and the subject's error went 0.08 -> 0.67 of its radius
    # (bench/RESULTS.md 7.48).
    apart = _isometry_between(chain.warped, partner.warped)
    if _distinct(apart, np.eye(2)):
        info["reason"] = (
            "the partner's registration is mirrored from the chain's"
            if np.linalg.det(apart) < 0 else
            f"the partner's registration is turned {abs(rotation_angle(apart)):.0f} degrees "
            "from the chain's")
        return None, info
    other = _stages(partner.warped, partner.error, task.y, task.cpd, task.spacing2,
                    task.model_irregularity, task.irregularity, task.stage_control)
    info["partner_polished_error"] = other.error
    moved = _polished_halfway(task, chain.warped, other.warped)
    if moved is None:
        info["reason"] = "the step halfway folds"
        return None, info
    step, found = moved
    info["error"] = found.error
    halfway = replace(found, steps=(step, *found.steps))
    if not found.steps:
        info["reason"] = "no stage from halfway passed the checks"
        return halfway, info
    if not found.error <= CONSENSUS_MAX_E_RATIO * chain.error:
        info["reason"] = f"e above {CONSENSUS_MAX_E_RATIO:g}x the chain's"
        return halfway, info
    info["kept"] = True
    info["reason"] = f"e at most {CONSENSUS_MAX_E_RATIO:g}x the chain's"
    return halfway, info


def _isometry_between(a: FloatArray, b: FloatArray) -> FloatArray:
    """The linear part of the isometry that best carries the model points `a` onto `b`
    (the same points placed by another registration; Procrustes): the rotation, or the
    rotation-reflection where that carries them closer."""
    R, t = fit_rigid(a, b)
    Rm, tm = fit_rigid(a, b, mirror=True)
    return Rm if np.sum((a @ Rm.T + tm - b) ** 2) < np.sum((a @ R.T + t - b) ** 2) else R


def _finished_apart(task: _PolishTask, chain: _Stages, halfway: _Stages,
                    info: dict[str, Any]) -> tuple[_Stages, dict[str, Any]]:
    """A consensus refused by :func:`_consensus`, judged again once both it and the chain
    are finished (:func:`_finish`, one CPD from the root model each): the finished
    halfway registration when its finish is kept and its e is at most
    :data:`CONSENSUS_FINISHED_MAX_E_RATIO` times the finished chain's (`info` then says
    the consensus was kept, and why), else the finished chain; with the finish's own
    record. `halfway` extends `chain` (its steps and checks follow the chain's).

    The consensus's rule compares e's reached by different maps: the chain's composed
    field has more freedom than one CPD's and can settle lower by sliding along the
    subject's sampling, and a CPD stage from halfway can raise e while it takes the points
    nearer their true images (bench/RESULTS.md 7.25: 0.000293 -> 0.000837 on a 永 skeleton
    subject whose error against the truth went 0.097 -> 0.084, its chain's being 0.133).
    Finished, both are one penalised field from the root model away from their start, so
    their e's compare on the same terms."""
    by_chain, chain_finish = _finish(task, chain)
    by_halfway, halfway_finish = _finish(task, halfway)
    info["chain_finished_error"] = by_chain.error
    info["finished_error"] = by_halfway.error
    if (halfway_finish["kept"]
            and by_halfway.error <= CONSENSUS_FINISHED_MAX_E_RATIO * by_chain.error):
        info["kept"] = True
        info["reason"] += (f"; kept once finished: e at most "
                           f"{CONSENSUS_FINISHED_MAX_E_RATIO:g}x the finished chain's")
        return by_halfway, halfway_finish
    return by_chain, chain_finish


def _edge_from_parent(task: _PolishTask
                      ) -> tuple[_Stages | None, RegistrationQuality | None, dict[str, Any]]:
    """The subject's edge registered again, from its parent's polished points.

    The same CPD as the tree's edges (not accelerated; after the edge's own affine
    pre-alignment, if it had one), from the parent's registration as polished instead of
    as chained. Kept when it does not fold, its confidence is at least
    :data:`MIN_CONFIDENCE` and its e is no larger than the chain's (that last rule not at
    the stored resolution: ``task.edge_within_chain_e``); `_polish_task` then polishes it
    beside the chain and takes the two halfway."""
    assert task.from_parent is not None
    q = task.from_parent
    for step in task.edge_affine:
        q = step.apply(q)
    o = task.cpd
    res = cpd_nonrigid(q, task.y, **o.keywords(), control=task.control)
    warped = np.asarray(res.warped, dtype=np.float64)
    e = registration_error(warped, task.y)
    quality = measure_quality(q, warped, task.y, res.transform, e, task.spacing2)
    info: dict[str, Any] = {"error": e, "chain_error": task.error, "kept": False}
    if not quality.min_jacobian > 0:
        info["reason"] = "it folds"
    elif not quality.confidence >= MIN_CONFIDENCE:
        info["reason"] = f"confidence below {MIN_CONFIDENCE:g}"
    elif task.edge_within_chain_e and not e <= task.error:
        info["reason"] = "e above the chain's"
    else:
        info["kept"] = True
        info["reason"] = ("e no larger than the chain's" if task.edge_within_chain_e
                          else "it does not fold and its confidence passes")
        return _Stages(warped=warped, error=e, steps=(*task.edge_affine, res.transform),
                       quality=(quality,),
                       correspondence=np.asarray(res.correspondence, dtype=np.intp),
                       probability=np.asarray(res.probability, dtype=np.float64)
                       ), quality, info
    return None, None, info


def _step_onto(points: FloatArray, targets: FloatArray, o: CPDOptions,
               through: IntArray | None = None
               ) -> tuple[PointTransform, FloatArray] | None:
    """CPD's field through `points` onto `targets` (:func:`~registration._tree._symmetric.
    fitted_step`, at :data:`CONSENSUS_KERNEL_FACTOR` of the tree's beta; fitted through the
    `through` points alone when given) and where it puts every one of `points`; None when
    it folds at any of them."""
    return fitted_step(points, targets if through is None else targets[through],
                       CONSENSUS_KERNEL_FACTOR * o.beta, through)


def _polished_halfway(task: _PolishTask, points: FloatArray, other: FloatArray
                      ) -> tuple[PointTransform, _Stages] | None:
    """`points` moved halfway to `other` (:func:`_step_onto`) and the polish's stages from
    there: the step and the stages, or None when the step folds."""
    moved = _step_onto(points, 0.5 * (points + other), task.cpd, task.control)
    if moved is None:
        return None
    step, start = moved
    return step, _stages(start, registration_error(start, task.y), task.y, task.cpd,
                         task.spacing2, task.model_irregularity, task.irregularity,
                         task.stage_control)


def _halfway(task: _PolishTask, a: _Stages, b: _Stages) -> _Stages | None:
    """`b` moved halfway to `a` and polished from there (:func:`_polished_halfway`, as
    the consensus does): its steps after `b`'s, or None when the step folds, no stage
    passes its checks or the e reached is above :data:`CONSENSUS_MAX_E_RATIO` times the
    lower of the two."""
    moved = _polished_halfway(task, b.warped, a.warped)
    if moved is None:
        return None
    step, found = moved
    if not found.steps or not found.error <= CONSENSUS_MAX_E_RATIO * min(a.error, b.error):
        return None
    return replace(found, steps=(*b.steps, step, *found.steps),
                   quality=(*b.quality, *found.quality))


def _finish_keywords(o: CPDOptions) -> dict[str, Any]:
    """The finish's CPD options (and its backward registration's): the tree's, its kernel
    :data:`FINISH_BETA_FACTOR` as wide and its regulariser :data:`FINISH_LMBDA_FACTOR` as
    strong."""
    return o.keywords(beta=FINISH_BETA_FACTOR * o.beta, lmbda=FINISH_LMBDA_FACTOR * o.lmbda)


def _cpd_from_root(model: FloatArray, y: FloatArray, start: FloatArray, sigma2: float,
                   o: CPDOptions, control: IntArray | None = None) -> CPDResult | None:
    """The finish's CPD: the root `model` itself onto `y`, started at `start`
    (``init_warped``) from `sigma2`, its kernel :data:`FINISH_BETA_FACTOR` of the tree's
    beta and its regulariser :data:`FINISH_LMBDA_FACTOR` times the tree's lambda,
    accelerated (fitted with the `control` points when given); None when its field from
    the root folds at any model point."""
    res = cpd_nonrigid(model, y, **_finish_keywords(o), sigma2=sigma2, init_warped=start,
                       accelerate=True, control=control)
    if not float(jacobian_determinants(res.transform, model).min()) > 0:
        return None
    return res


def _finish(task: _PolishTask, best: _Stages) -> tuple[_Stages, dict[str, Any]]:
    """The finish: one CPD from the root model itself onto the subject, started where the
    polish left it, its kernel :data:`FINISH_BETA_FACTOR` of the tree's beta and its
    regulariser :data:`FINISH_LMBDA_FACTOR` times the tree's lambda.

    Every registration before it penalises its field from where it started (an edge from
    its parent's warped model, a polish stage from the chain), so a slide along the
    subject's outline that an earlier link settled into is never undone: nothing in the
    data term resists a slide, and each later field is measured from the slid points. The
    finish's field is measured from the root model (``cpd_nonrigid(init_warped=...)``):
    one field for the whole deformation, penalised as a whole, at half the edges' kernel
    width so that it can follow the local differences between the root and a far subject
    that the edges' smooth fields leave to slides. From the polished points it starts in
    the right basin (from the root's own pose, as plain CPD, the same field at that width
    wanders). The subject's transform extends its chain by CPD's field through the
    polished points to the finished ones (:func:`_step_onto`, as the consensus's step; its
    points are what is reported). Kept when neither field
    folds, the step's confidence is at least :data:`MIN_CONFIDENCE` and its e is at most
    :data:`FINISH_MAX_E_RATIO` times the polished e; else `best` is returned as it is.
    Ground truth: bench/RESULTS.md 7.12."""
    o = task.cpd
    info: dict[str, Any] = {"kept": False, "error_before": best.error}
    res = _cpd_from_root(task.model, task.y, best.warped,
                         max(0.5 * best.error, task.spacing2), o, task.control)
    if res is None:
        info["reason"] = "its field from the root folds"
        return best, info
    found = _step_onto(best.warped, np.asarray(res.warped, dtype=np.float64), o,
                       task.control)
    if found is None:
        info["reason"] = "the step to it folds"
        return best, info
    step, moved = found
    return _finished(task, best, step, moved, info,
                     lambda e: (res.correspondence, res.probability))


def _finished(task: _PolishTask, best: _Stages, step: PointTransform, moved: FloatArray,
              info: dict[str, Any],
              correspondence: Callable[[float], tuple[NDArray[Any], NDArray[Any]]]
              ) -> tuple[_Stages, dict[str, Any]]:
    """The rule of the finish and the symmetric finish: `best` extended by `step`, which
    moves its points to `moved`, when the step's confidence is at least
    :data:`MIN_CONFIDENCE` and its e is at most :data:`FINISH_MAX_E_RATIO` times `best`'s
    (`correspondence(e)`: the correspondences and their probabilities then); else `best`
    as it is. `info` records the e and the reason."""
    e = registration_error(moved, task.y)
    q = measure_quality(best.warped, moved, task.y, step, e, task.spacing2)
    info["error"] = e
    if not q.confidence >= MIN_CONFIDENCE:
        info["reason"] = f"confidence below {MIN_CONFIDENCE:g}"
        return best, info
    if not e <= FINISH_MAX_E_RATIO * best.error:
        info["reason"] = f"e above {FINISH_MAX_E_RATIO:g}x the polished e"
        return best, info
    info["kept"] = True
    info["reason"] = f"e at most {FINISH_MAX_E_RATIO:g}x the polished e"
    corr, prob = correspondence(e)
    return _Stages(warped=moved, error=e, steps=(*best.steps, step),
                   quality=(*best.quality, q), correspondence=np.asarray(corr, dtype=np.intp),
                   probability=np.asarray(prob, dtype=np.float64)), info


def _halfway_back(model: FloatArray, y: FloatArray, warped: FloatArray, error: float,
                  spacing2: float, o: CPDOptions, control: IntArray | None = None,
                  subject_control: IntArray | None = None) -> Halfway | NoHalfway:
    """The registration `warped` (the root `model`'s points on the subject `y`) moved
    halfway to where the subject registered back onto the root puts the model's points
    (:func:`~registration._tree._symmetric.halfway_back`, the step at
    :data:`CONSENSUS_KERNEL_FACTOR` of the tree's beta, as :func:`_step_onto`'s).

    The backward registration is the finish's CPD (:func:`_cpd_from_root`) with the roles
    swapped, the subject onto the root, from a variance of half `error` (at least
    `spacing2`). `control`: the model indices the fields through the model's points are
    fitted with, and so the only ones inverted (every point without them: at the stored
    resolution, 500 preimages instead of 1200-2200); `subject_control`: the subject
    indices the backward CPD's field is fitted with (None: every point). The stored
    resolution's backward CPD runs the tree's EM iterations too: stopped at 20 it saved
    0.5 s of the 73 glyphs' 20 s job and lost on the dense skeletons (bench/RESULTS.md
    7.31)."""
    def backward(start: FloatArray) -> PointTransform:
        return cpd_nonrigid(y, model, **_finish_keywords(o),
                            sigma2=max(0.5 * error, spacing2), init_warped=start,
                            accelerate=True, control=subject_control).transform

    return halfway_back(model, y, warped, o.beta, backward, CONSENSUS_KERNEL_FACTOR * o.beta,
                        control)


def _symmetric(task: _PolishTask, best: _Stages) -> tuple[_Stages, dict[str, Any]]:
    """The symmetric finish: the model's points moved halfway between where the polish
    left them and where the subject registered back onto the root puts them
    (:func:`_halfway_back`).

    CPD is not symmetric, so halfway between the two registrations part of each one's
    slide along the outline cancels (see `registration._tree._symmetric`). Both
    registrations start from the polished one, in its basin: halfway between a forward and
    a backward CPD started from the two shapes' own poses loses on large differences,
    where the backward one alone can go wrong (bench/RESULTS.md 7.15). The subject's
    transform extends its chain by CPD's field through the polished points to the halfway
    ones, and the correspondences are each moved point's most probable subject point at
    the variance the polish starts from (half the e reached, at least the subject's h^2).
    Kept when the inverse is found at :data:`~registration._tree._symmetric.MIN_REACHED`
    of the root points at least (how many lacked one: ``without_inverse``), the step does
    not fold, its confidence is at least :data:`MIN_CONFIDENCE` and its e is at most
    :data:`FINISH_MAX_E_RATIO` times the polished e (the finish's rule); else `best` is
    returned as it is. Ground truth: bench/RESULTS.md 7.16."""
    o = task.cpd
    info: dict[str, Any] = {"kept": False, "error_before": best.error}
    found = _halfway_back(task.model, task.y, best.warped, best.error, task.spacing2, o,
                          task.control, task.subject_control)
    info["without_inverse"] = found.without_inverse
    if isinstance(found, NoHalfway):
        info["reason"] = found.reason
        return best, info
    step, moved = found.step, found.moved
    # how far apart the forward and the backward registration put the model's points:
    # twice the step's move (RMS, in the subject's RMS radius, as the normalised
    # coordinates are); the subject's `disagreement` (bench/RESULTS.md 7.38)
    info["disagreement"] = 2.0 * rms_distance(moved, best.warped)
    return _finished(task, best, step, moved, info,
                     partial(_stepped_correspondence, moved, task.y, task.spacing2, o.w))


def _stepped_correspondence(moved: FloatArray, y: FloatArray, spacing2: float, w: float,
                            e: float) -> tuple[NDArray[Any], NDArray[Any]]:
    """The correspondences of the points a step (the symmetric finish's, the step towards
    plain CPD) moved to `moved` on the subject `y`, where they reached e: CPD's most
    probable ones at a variance of half e (at least the subject's h^2), outlier weight
    `w`."""
    return _posterior_max(moved, y, max(0.5 * e, spacing2), w)


def _along_plain(task: _PolishTask, best: _Stages) -> tuple[_Stages, dict[str, Any]]:
    """The polish's last step: each of the model's points moved along the subject's
    outline :data:`ALONG_PLAIN_WEIGHT` of the way to where plain CPD puts it (one CPD of
    the root model onto the subject from the pose as given, as the paper's baseline, but
    with the tree's CPD options, its weighted mixture included; its field fitted with the
    `control` points when given): the component of the difference along the outline's
    direction at the point's nearest subject point (:func:`~registration._quality.
    outline_tangents`), the step CPD's field through the polished points to there
    (:func:`_step_onto`).

    Tried only when the polished e is above :data:`ALONG_PLAIN_MIN_E_RATIO` times plain
    CPD's (plain CPD fits the subject across the outline about as closely as the tree:
    the two differ along it, where nothing measures which is right); kept by the finish's
    rule (`_finished`). A step refused is tried once more at :data:`ALONG_PLAIN_BACKTRACK`
    of the weight (``info["weight"]``: the last tried; ``info["full_step"]``: the e and
    reason of the full one). Else `best` is returned as it is."""
    o = task.cpd
    info: dict[str, Any] = {"kept": False, "error_before": best.error}
    plain = cpd_nonrigid(task.model, task.y, **o.keywords(), control=task.control)
    e_plain = registration_error(plain.warped, task.y)
    info["plain_error"] = e_plain
    if not best.error > ALONG_PLAIN_MIN_E_RATIO * e_plain:
        info["reason"] = (f"plain CPD's e ({e_plain:.3g}) above "
                          f"{1 / ALONG_PLAIN_MIN_E_RATIO:g}x the polished e: it did not fit "
                          "the subject")
        return best, info
    tangent = outline_tangents(task.y)[cKDTree(task.y).query(best.warped)[1]]
    along = np.einsum("ni,ni->n", np.asarray(plain.warped) - best.warped, tangent)
    for weight in (ALONG_PLAIN_WEIGHT, ALONG_PLAIN_BACKTRACK * ALONG_PLAIN_WEIGHT):
        if "weight" in info:  # the full step was refused: what it reached, and why
            info["full_step"] = {k: info.pop(k) for k in ("error", "reason") if k in info}
        info["weight"] = weight
        found = _step_onto(best.warped, best.warped + weight * along[:, None] * tangent, o,
                           task.control)
        if found is None:
            info["reason"] = "the step to it folds"
            continue
        step, moved = found
        out, info = _finished(task, best, step, moved, info,
                              partial(_stepped_correspondence, moved, task.y,
                                      task.spacing2, o.w))
        if info["kept"]:
            return out, info
    return best, info


def affine_lead(steps: tuple[PointTransform, ...]) -> int:
    """How many of an edge's `steps` are its affine pre-alignment: the affine steps it
    starts with, its last step (the edge's CPD) never counted."""
    lead = 0
    while lead < len(steps) - 1 and isinstance(steps[lead], AffineTransform):
        lead += 1
    return lead


def _extends(chain: _Stages, more: _Stages) -> _Stages:
    """`more` (registered from where `chain` left the points) with `chain`'s steps and
    checks before its own."""
    return replace(more, steps=(*chain.steps, *more.steps),
                   quality=(*chain.quality, *more.quality))


def _single_edge_refusal(task: _PolishTask, best: _Stages) -> dict[str, Any] | None:
    """Why a single edge's polish (`best`, from the edge's registration `task.start`) is
    not kept, as recorded in ``quality["polish_not_kept"]``; None: it is kept. It is kept
    when it lowers e to at most :data:`SINGLE_EDGE_MAX_E_RATIO` of the edge's, or, the
    edge's e below the sampling floor, when it moves the model's points at least
    :data:`SINGLE_EDGE_MIN_MOVE` spacings."""
    if best.error <= SINGLE_EDGE_MAX_E_RATIO * task.error:
        return None
    floor = _spacing_floor(task.spacing2)
    move = rms_distance(best.warped, task.start) / math.sqrt(task.spacing2)
    record = {"error_before": task.error, "error": best.error, "floor": floor, "move": move}
    lowered = (f"e {task.error:.3g} -> {best.error:.3g}, not below "
               f"{SINGLE_EDGE_MAX_E_RATIO:g}x the e of one CPD from the root")
    if task.error >= floor:
        return {**record, "reason": f"{lowered}, which is at the sampling floor or above "
                                    f"({floor:.3g})"}
    if move < SINGLE_EDGE_MIN_MOVE:
        return {**record, "reason": f"{lowered}, and the points moved {move:.2g} of the "
                                    f"subject's point spacing (RMS), less than "
                                    f"{SINGLE_EDGE_MIN_MOVE:g} spacing"}
    return None


def _scattered_refusal(task: _PolishTask) -> dict[str, Any] | None:
    """Why no polish is run for the subject (recorded in ``quality["polish_not_kept"]``),
    or None: its points without counterpart on the registration `task.start` are
    scattered (:func:`~registration._error.scattered_extra` above
    :data:`~registration._error.SCATTER_MIN`: outliers, specks). Each of the polish's
    stages is kept by e, which falls most where the model is pulled over them: on the
    Chui & Rangarajan outlier series (Chinese character, trial 0, level 2) the polish
    took e from 0.034 to 0.011 and the correspondence error from 0.27 to 0.43 of the
    radius (bench/RESULTS.md 7.58, 7.59). A piece of outline the chain has not reached
    is not scattered, and is polished as any subject."""
    scatter = scattered_extra(task.start, task.y, task.spacing2)
    if scatter is None or not scatter > SCATTER_MIN:
        return None
    return {"error_before": task.error, "error": task.error, "scatter": scatter,
            "reason": f"the subject has points scattered off the registration (outliers; "
                      f"scatter {scatter:.2f} > {SCATTER_MIN:g}), which each stage's e "
                      "would pull the model over"}


def _part_refusal(task: _PolishTask) -> dict[str, Any] | None:
    """Why no polish is run for the subject (recorded in ``quality["polish_not_kept"]``),
    or None: it is a leaf that is part of the model (occluded, cut off;
    ``task.part_of_model``). Each of the polish's stages is kept by e, which also counts
    the model's points without counterpart and falls most where the whole model is
    squeezed onto the part: on the Chui & Rangarajan occlusion series (Chinese character,
    trial 2, level 5) the polish of the root's registration took e from 0.038 to 0.005
    and the correspondence error from 0.018 to 0.30 of the radius (bench/RESULTS.md
    7.60)."""
    if not task.part_of_model:
        return None
    return {"error_before": task.error, "error": task.error,
            "reason": "the subject is part of the model (occluded or cut off), and each "
                      "stage's e would squeeze the whole model onto it"}


def _unpolished(task: _PolishTask, refused: dict[str, Any]) -> _PolishOutcome:
    """The outcome of a polish not kept: the subject keeps the registration it starts
    from (`task.start`), whose correspondences it already has."""
    return _PolishOutcome(
        subject=task.subject, warped=task.start, error=task.error,
        correspondence=np.empty(0, dtype=np.intp),
        probability=np.empty(0, dtype=np.float64), steps=(), quality=(), refused=refused)


def _polish_task(task: _PolishTask) -> _PolishOutcome:
    refused = _scattered_refusal(task) or _part_refusal(task)
    if refused is not None:
        return _unpolished(task, refused)
    chain = _stages(task.start, task.error, task.y, task.cpd, task.spacing2,
                    task.model_irregularity, task.irregularity, task.stage_control)
    edge, edge_q, edge_info = None, None, None
    if task.from_parent is not None:
        edge, edge_q, edge_info = _edge_from_parent(task)
    if edge is not None and edge_info is not None:
        # the edge from the polished parent, polished (or alone, when no stage passes)
        other = _stages(edge.warped, edge.error, task.y, task.cpd, task.spacing2,
                        task.model_irregularity, task.irregularity, task.stage_control)
        if not other.steps:
            other = replace(edge, steps=(), quality=())
        # the two polished registrations of the edge err differently: halfway, polished
        # again, when that passes; else the one with the lower e
        mid = _halfway(task, chain, other)
        edge_info.update(chain_polished_error=chain.error, polished_error=other.error,
                         halfway=mid is not None)
        if mid is not None:
            edge_info["halfway_error"] = mid.error
            chain = mid
        elif other.error <= chain.error:
            chain = other
        else:
            edge, edge_q = None, None
            edge_info["kept"] = False
            edge_info["reason"] = "the chain's polish reached a lower e, and halfway failed"
    best, info, finish = chain, None, None
    if task.partner is not None:
        halfway, info = _consensus(task, chain)
        if halfway is not None and info["kept"]:
            best = _extends(chain, halfway)
        elif halfway is not None:
            best, finish = _finished_apart(task, chain, _extends(chain, halfway), info)
    if finish is None:
        best, finish = _finish(task, best)
    best, symmetric = _symmetric(task, best)
    if task.single_edge and best.steps:
        refused = _single_edge_refusal(task, best)
        if refused is not None:
            return _unpolished(task, refused)
    along, along_stages = None, None
    if task.along_plain and (best.steps or edge is not None):
        after, along = _along_plain(task, best)
        along_stages = after if along["kept"] else None
    return _PolishOutcome(subject=task.subject, warped=best.warped, error=best.error,
                          correspondence=best.correspondence, probability=best.probability,
                          steps=best.steps, quality=best.quality, consensus=info,
                          edge_steps=() if edge is None else edge.steps, edge_quality=edge_q,
                          from_parent=edge_info, finish=finish, symmetric=symmetric,
                          along_plain=along, along_stages=along_stages)


def _polished(coll: _Collection, old: SubjectResult, out: _PolishOutcome,
              parent: SubjectResult | None = None, stored: bool = False) -> SubjectResult:
    """`old` with the polished registration in place of the chained one; `parent`: the
    parent as polished, when the subject's edge was registered again from it (None: the
    root's own points). `stored`: the polish at the stored resolution (:class:`AtStored`),
    recorded in ``quality["stored_polish"]``, which keeps `old`'s confidence."""
    record = "stored_polish" if stored else "polish"
    label = "polished again at the stored resolution" if stored else "polished"
    assert old.transform is not None and old.confidence is not None
    assert out.steps or out.edge_steps
    if out.edge_steps:
        assert out.edge_quality is not None
        # the parent's polished chain (none: the root's own points), the edge from it,
        # then the subject's own polish
        before: tuple[PointTransform, ...] = ()
        confidence = out.edge_quality.confidence
        if parent is not None:
            assert parent.transform is not None and parent.confidence is not None
            before = parent.transform.steps
            confidence = min(parent.confidence, confidence)
        chain = replace(old.transform, steps=(*before, *out.edge_steps, *out.steps))
    else:
        chain = replace(old.transform, steps=(*old.transform.steps, *out.steps))
        confidence = old.confidence
    assert isinstance(chain, ChainTransform)
    quality = out.quality
    if out.edge_quality is not None:
        quality = (out.edge_quality, *quality)
    confidence = min([confidence, *(q.confidence for q in out.quality)])
    polish = {
        "error_before": old.error, "steps": len(out.steps), **quality[-1].to_dict(),
        # the e reached (the checks' own "error" is measured on at most QUALITY_POINTS
        # points of each shape: at the stored resolution, on subsamples)
        "error": out.error,
        "confidence": min(q.confidence for q in quality),
        "min_jacobian": min(q.min_jacobian for q in quality)}
    reason = (f"{old.reason}; {label}: {len(out.quality)} more CPD from the chained model "
              f"(e {old.error:.3g} -> {out.error:.3g})")
    if out.from_parent is not None:
        polish["from_parent"] = out.from_parent
    if out.edge_steps:
        how = ("halfway between its chain's registration and its edge's registered again "
               "from the parent as polished" if (out.from_parent or {}).get("halfway")
               else "its edge registered again from the parent as polished")
        reason = (f"{old.reason}; {label}: {how}, {len(out.quality)} more CPD "
                  f"(e {old.error:.3g} -> {out.error:.3g})")
    if out.consensus is not None:
        polish["consensus"] = out.consensus
        if out.consensus["kept"]:
            start = ("its edge from the parent as polished" if out.edge_steps
                     else "its chain")
            m = out.consensus["partner"]
            other = ("the root's direct registration" if m == coll.root
                     else f"the registration from {coll.names[m]}")
            reason = (f"{old.reason}; {label}: the consensus of {start} and {other}, "
                      f"{len(out.quality)} more CPD (e {old.error:.3g} -> {out.error:.3g})")
    if out.finish is not None:
        polish["finish"] = out.finish
        if out.finish["kept"]:
            reason += "; finished by one CPD from the root model"
    if out.symmetric is not None:
        polish["symmetric"] = out.symmetric
        if out.symmetric["kept"]:
            reason += "; moved halfway to the subject's registration back onto the root"
    if out.along_plain is not None:
        polish["along_plain"] = out.along_plain  # applied later (`_moved_along_plain`)
    if stored:
        confidence = old.confidence
    return replace(
        old, error=out.error, warped=coll.norms[out.subject].invert(out.warped),
        correspondence=out.correspondence, probability=out.probability, transform=chain,
        confidence=confidence, quality={**(old.quality or {}), record: polish},
        reason=reason,
    )


def _polish_subjects(
    coll: _Collection,
    results: dict[int, SubjectResult],
    cpd: CPDOptions,
    executor: Executor | None,
    progress: ProgressCallback | None,
    min_layer: int = POLISH_MIN_LAYER,
    partner: Callable[[int], _RegTask | _RegOutcome] | None = None,
    stored: AtStored | None = None,
    along_plain: bool = True,
) -> None:
    """Polish every attached subject at layer >= `min_layer` in place (see the module doc),
    a tree level at a time, parents first: a subject at layer >=
    :data:`POLISH_FROM_PARENT_MIN_LAYER` whose parent's polish moved it also registers
    its edge again from there (`_edge_from_parent`, `_polish_task`). `partner(s)`: the
    registration of subject `s` from its consensus partner (to run, or already run; see
    :func:`consensus_partner`), for the consensus of the subjects at layer >=
    :data:`POLISH_CONSENSUS_MIN_LAYER` (None: no consensus). It is called a level at a
    time, once the levels before are polished.

    `stored`: the polish at the stored resolution (see :class:`AtStored`); None: the
    working resolution's, the edges' affine steps read off the chains in `results`,
    which must then be the tree's as built. `along_plain`: every polished subject ends
    with the step towards plain CPD (`_along_plain`), applied once all are polished; off
    at a working resolution that a stored one follows (the step is taken there)."""
    todo = [
        s for s, r in sorted(results.items())
        if r.warped is not None and r.layer is not None and r.layer >= min_layer
        and r.error is not None and r.transform is not None and r.confidence is not None
        # a single edge whose polish the working resolution did not keep stays the
        # stored CPD's: the decision is the working resolution's, as every decision is
        and not (stored is not None and "polish_not_kept" in (r.quality or {}))
    ]
    if not todo:
        return
    built = {s: r.transform for s, r in results.items() if r.transform is not None}
    stage = "polish" if stored is None else STORED_STAGE
    levels: dict[int, list[int]] = {}
    for s in todo:
        levels.setdefault(len(results[s].path), []).append(s)
    moved: set[int] = set()  # subjects whose polish moved them
    # each subject's registration with the step towards plain CPD, applied last
    along: dict[int, _Stages] = {}
    model_irregularity = sampling_irregularity(coll.normed[coll.root])
    done = 0
    with owned_executor(executor, 8 * len(todo)) as ex:
        if progress is not None:
            progress(stage, 0, len(todo))
        for level in sorted(levels):
            tasks = [_polish_subject_task(coll, results, built, moved, s, cpd, partner,
                                          model_irregularity, stored, along_plain)
                     for s in levels[level]]
            for _, out in ex.map_unordered(_polish_task, tasks):
                if out.steps or out.edge_steps:
                    old = results[out.subject]
                    parent = (results[old.parent] if out.edge_steps
                              and old.parent not in (None, coll.root) else None)
                    results[out.subject] = _polished(coll, old, out, parent,
                                                     stored is not None)
                    moved.add(out.subject)
                    if out.along_stages is not None:
                        along[out.subject] = out.along_stages
                elif out.refused is not None:
                    old = results[out.subject]
                    results[out.subject] = replace(
                        old, quality={**(old.quality or {}), "polish_not_kept": out.refused},
                        reason=f"{old.reason}; polish not kept: {out.refused['reason']}")
                done += 1
                if progress is not None:
                    progress(stage, done, len(todo))
    for s, moved_along in along.items():
        results[s] = _moved_along_plain(coll, results[s], moved_along, stored is not None)


def _moved_along_plain(coll: _Collection, r: SubjectResult, moved: _Stages,
                       stored: bool) -> SubjectResult:
    """`r`, polished, with the polish's step towards plain CPD (`_along_plain`; `moved`:
    the polished registration with it) appended to its transform; its checks join the
    polish's (the confidence too, but at the stored resolution, as `_polished`)."""
    record = "stored_polish" if stored else "polish"
    assert r.transform is not None and r.confidence is not None
    q = moved.quality[-1]
    quality = dict(r.quality or {})
    polish = quality.get(record, {})
    weight = (polish.get("along_plain") or {}).get("weight", ALONG_PLAIN_WEIGHT)
    # the polish's steps in the chain (`_resolution._polish_steps`) include this one
    quality[record] = {
        **polish, "error": moved.error, "steps": polish.get("steps", 0) + 1,
        "confidence": min(polish.get("confidence", q.confidence), q.confidence),
        "min_jacobian": min(polish.get("min_jacobian", q.min_jacobian), q.min_jacobian)}
    return replace(
        r, error=moved.error, warped=coll.norms[r.index].invert(moved.warped),
        confidence=r.confidence if stored else min(r.confidence, q.confidence),
        correspondence=moved.correspondence, probability=moved.probability,
        transform=replace(r.transform, steps=(*r.transform.steps, moved.steps[-1])),
        quality=quality,
        reason=(f"{r.reason}; moved {weight:g} of the way to plain CPD's points along the "
                f"outline (e {r.error:.3g} -> {moved.error:.3g})"))


def _polish_subject_task(
    coll: _Collection,
    results: dict[int, SubjectResult],
    built: dict[int, ChainTransform],
    moved: set[int],
    s: int,
    cpd: CPDOptions,
    partner: Callable[[int], _RegTask | _RegOutcome] | None,
    model_irregularity: float,
    stored: AtStored | None = None,
    along_plain: bool = True,
) -> _PolishTask:
    r = results[s]
    assert r.warped is not None and r.layer is not None and r.error is not None
    from_parent: FloatArray | None = None
    edge_affine: tuple[PointTransform, ...] = ()
    p = r.parent
    if stored is not None and p is not None:
        # every edge again, from the root's own points at layer 2
        if p == coll.root:
            from_parent = coll.normed[p]
        else:
            parent = results[p]
            assert parent.warped is not None
            from_parent = coll.norms[p].apply(parent.warped)
        edge_affine = stored.edge_affines[s]
    elif r.layer >= POLISH_FROM_PARENT_MIN_LAYER and p is not None and p in moved:
        parent = results[p]
        assert parent.warped is not None
        from_parent = coll.norms[p].apply(parent.warped)
        edge = built[s].steps[len(built[p].steps):]  # the edge as the tree made it
        edge_affine = tuple(edge[:affine_lead(edge)])
    y = coll.normed[s]
    control = None if stored is None else stored.control
    stage_control = None if stored is None else stored.stage_control
    subject_control = (None if control is None or len(y) <= len(control)
                       else farthest_point_indices(y, len(control)))
    return _PolishTask(
        subject=s, start=coll.norms[s].apply(r.warped), error=r.error, y=coll.normed[s],
        cpd=cpd, spacing2=coll.spacing2[s], model_irregularity=model_irregularity,
        model=coll.normed[coll.root],
        partner=partner(s) if partner is not None and r.layer >= POLISH_CONSENSUS_MIN_LAYER
        else None,
        from_parent=from_parent, edge_affine=edge_affine,
        edge_within_chain_e=stored is None, control=control,
        subject_control=subject_control, stage_control=stage_control,
        single_edge=stored is None and r.layer == 2, along_plain=along_plain,
        part_of_model=(r.quality or {}).get("leaf_compared_by") == "subject")

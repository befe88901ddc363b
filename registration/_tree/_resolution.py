"""Coarse to fine: decide the tree at a working resolution, register its edges at the
stored one.

Every decision of a tree method (the similarity, the candidates, acceptance, leaves,
refinement, the pose of each edge) is taken on the shapes subsampled to at most
``working_points`` points each (:func:`coarse_collection`: a deterministic farthest-point
subsample, in the shapes' own normalisation, so that every transform fitted on the coarse
shapes applies unchanged to the stored points). Then :func:`at_stored_resolution`
registers each edge of the result once at the stored resolution, parents before
children: the root model at full resolution, as already warped onto the parent, is moved
by the coarse edge (its affine pre-alignment and its CPD warp, then a polished subject's
polish step) and a short CPD warm-started there (:func:`_refine_edge`; its field fitted
with at most :data:`FINE_CONTROL_POINTS` of the model's points against every stored point
of the subject) puts it onto the full subject: one CPD per subject. The
result's warped points, correspondences, transforms and e are then those of the stored
shapes; the attempts, thresholds, similarity, confidence and quality checks keep the
working resolution's figures the decisions were taken on (``quality`` adds
``working_error``, the e decided on, and ``stored_min_jacobian``, the fold check of the
edge's warp on the stored points). The dynamic tree's subjects are then polished again on
the stored points, as the polish did at the working resolution but for the consensus
(:func:`_polish_stored`, ``quality["stored_polish"]``): its stages from where the stored
CPD left the model, every edge registered again from the parent as polished there (from
the root's own points at layer 2) and the two taken halfway, the finish from the root
model and the symmetric finish; their children's stored CPDs start from the
registrations before it. The confidence is the one the decisions were taken
with (the quality checks measure any shape at most :data:`registration._quality.
QUALITY_POINTS` points dense, the density their model was fitted at: before that, the 73
永 edge glyphs measured at their stored 1167-2244 points scored correct registrations near
0.05 and a tree run at the stored resolution left 71 of 72 subjects as leaves,
bench/RESULTS.md section 8).

Shapes at or below ``working_points`` are not subsampled; when no shape is above it,
nothing here runs and the methods behave exactly as without a coarse stage.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._cpd import CPDOptions, NonrigidTransform, cpd_nonrigid
from .._error import registration_error
from .._executor import Executor
from .._pointmap import PointTransform, composed_with_jacobian
from .._points import farthest_point_indices, mean_spacing2
from .._quality import fold_values
from .._result import CollectionResult, SubjectResult
from .._similarity import ProgressCallback
from .._transform import ChainTransform
from ._collection import _Collection
from ._polish import AtStored, _polish_subjects, affine_lead
from ._tasks import _map_tasks

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Points per shape the tree's decisions are taken at (None or 0: the stored resolution).
#: At 400 points the 73 永 edge glyphs (1167-2244 points) build their tree in a fraction
#: of the full-resolution time with e and correspondences close to a full-resolution run
#: (bench/bench_resolution.py, bench/RESULTS.md section 8; on 1200-point 永 edge chains
#: the ground-truth error is 1.16x the full-resolution tree's in a third of its CPU,
#: section 8.4).
DEFAULT_WORKING_POINTS = 400
#: Fewest points a working resolution may have.
MIN_WORKING_POINTS = 20
#: EM iterations of the warm-started CPD at the stored resolution (at most; it stops
#: earlier on CPD's own tolerance).
FINE_MAX_ITER = 20
#: Initial sigma^2 of the warm start, times half the e (eq. 10) of the warm-started model
#: (e is a mean squared 2-D distance, sigma^2 a per-coordinate variance). Started at 1x,
#: CPD's sigma grew back over its first iterations to 1.7-2.5x that (sigma^2 3-6x) on the
#: 永 glyphs, where its soft correspondences settle, rebuilding the truncated E-step's
#: neighbour list on the way; 3x starts near there (ground truth within 1 % either way on
#: six 永 families, bench/RESULTS.md section 8.1).
FINE_SIGMA2_FACTOR = 3.0
#: Most model points the warm-started CPD fits its field with (the root's farthest-point
#: subsample, chosen once; every stored point is then moved by that field and given its
#: correspondence). A CPD's E-step costs the model's points times the subject's, and at
#: this stage the start is already within the coarse registration's error: on eight 永
#: edge families at 1205-1800 points a shape (bench/RESULTS.md section 8.2) fitting with
#: 500 points gave the same ground-truth error as with every point (0.993x pooled, far
#: half 0.998x, every design within 2 %; 1000 and 700 points the same) in 0.63x the
#: stage's CPU time. The dynamic tree's polish at the stored resolution fits its CPDs with
#: the same points, and there they cost more: with that polish, 1.07x the every-point
#: error (far half 1.12x) in 0.23x the CPU; 800 points 1.05x in 0.40x, 1000 points 1.03x
#: in 0.49x (bench/RESULTS.md 7.32). Never fewer than the working resolution's points.
FINE_CONTROL_POINTS = 500
#: Most model points the stages of the dynamic tree's polish at the stored resolution
#: (:func:`_polish_stored`) fit their fields with; its other CPDs (the edge registered
#: again, the finish, the backward CPD) and its steps keep :data:`FINE_CONTROL_POINTS`.
#: The stages' mixture of centroids is where the control points cost the polish most:
#: with 1000 for the stages alone, eight 永 edge designs at 1200 points are at 1.03x the
#: every-point error (far half 1.06x; 500: 1.07x / 1.12x; 1000 for every CPD: 1.03x /
#: 1.06x in twice the stage's CPU); against plain CPD, dense glyph edges 0.419 -> 0.407,
#: skeletons 0.432 -> 0.417, MPEG-7 chains at 1200 points 0.287 -> 0.271, evenly sampled
#: outlines 0.543 -> 0.555, for 1.4x the polish's time (bench/RESULTS.md 7.32).
POLISH_STAGE_CONTROL_POINTS = 1000


def check_working_points(value: Any) -> int | None:
    """The working resolution as an int, or None for none; ValueError if invalid."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"working_points must be None, 0 or an integer >= "
                         f"{MIN_WORKING_POINTS}; got {value!r}")
    n = int(value)
    if n == 0:
        return None
    if n < MIN_WORKING_POINTS:
        raise ValueError(f"working_points must be None, 0 or an integer >= "
                         f"{MIN_WORKING_POINTS}; got {value!r}")
    return n


def coarse_collection(full: _Collection, working_points: int | None) -> _Collection:
    """The collection at the working resolution; `full` itself when no shape is above it.

    Coarse shapes keep the stored shapes' normalisation (their normalised points are a
    subset of the stored ones), so a transform fitted between coarse shapes applies to the
    stored points as it is.
    """
    if working_points is None or all(len(p) <= working_points for p in full.normed):
        return full
    normed = [p[farthest_point_indices(p, working_points)] for p in full.normed]
    return _Collection(normed=normed, norms=list(full.norms), names=list(full.names),
                       root=full.root, spacing2=[mean_spacing2(p) for p in normed])


@dataclass(frozen=True)
class _FineTask:
    subject: int
    q: FloatArray  # the full root model as warped onto the parent (parent's normalised coords)
    steps: tuple[PointTransform, ...]  # the coarse edge (affine, then CPD) or polish stages
    y: FloatArray  # the stored subject, normalised
    cpd: CPDOptions
    control: IntArray | None  # the model points the CPD is fitted with (None: all)
    # whether the outcome's correspondences are read (not for an edge run only for the
    # subject's children to start from); each is a pass over every stored pair
    correspondences: bool = True


@dataclass(frozen=True)
class _FineOutcome:
    subject: int
    warped: FloatArray
    error: float
    # None when none is read (`correspondences`)
    correspondence: IntArray | None
    probability: FloatArray | None
    step: NonrigidTransform
    min_jacobian: float  # of the edge's non-rigid warp (coarse then fine) on the stored model


def warm_start_sigma2(start: FloatArray, subject: FloatArray) -> float:
    """Initial CPD variance for a model already lying near the subject: half its e."""
    return max(FINE_SIGMA2_FACTOR * 0.5 * registration_error(start, subject), 1e-12)


def _refine_edge(task: _FineTask) -> _FineOutcome:
    """One edge at the stored resolution: the coarse edge's steps, then a short CPD.

    The warm-started CPD runs in the subject's normalised frame (``normalize=False``: both
    sets stay where the coarse edge put them) from a variance of
    :data:`FINE_SIGMA2_FACTOR` times half the remaining e, so it corrects locally instead of
    registering again from scratch. Its field is fitted with the task's ``control`` points
    of the model (see :data:`FINE_CONTROL_POINTS`) against every stored point of the
    subject, and moves every stored model point (``cpd_nonrigid(control=...)``). Its EM
    is accelerated, as for every warm start (``accelerate=True``): within the same
    :data:`FINE_MAX_ITER` iterations it gets nearer its fixed point (on six 1200-point 永
    edge chains, with the finish after it, ground truth 0.0289 -> 0.0283; skeletons a
    little lower too; bench/RESULTS.md 8.4). The fold check covers the edge's non-rigid
    steps and the fine one, on the stored points as the edge's affine pre-alignment
    leaves them.
    """
    lead = affine_lead(task.steps)
    pre = task.q
    for step in task.steps[:lead]:
        pre = step.apply(pre)
    # the edge's non-rigid steps, with their Jacobians for the fold check below
    both = composed_with_jacobian(task.steps[lead:], pre)
    assert both is not None, "every step of a tree edge gives its Jacobian"
    start, jac = both
    o = task.cpd
    res = cpd_nonrigid(start, task.y, **o.keywords(max_iter=min(o.max_iter, FINE_MAX_ITER)),
                       sigma2=warm_start_sigma2(start, task.y), normalize=False,
                       control=task.control, accelerate=True)
    warped = np.asarray(res.warped, dtype=np.float64)
    # chain rule: the fine step's Jacobians where the edge put the points, after the edge's
    # (one kernel product per step; taking the whole composition again cost twice that)
    jac = res.transform.apply_with_jacobian(start)[1] @ jac
    # a fold as the working resolution's check reads one (`_quality.fold_values`)
    det, _ = fold_values(pre, jac)
    own = task.correspondences
    return _FineOutcome(subject=task.subject, warped=warped,
                        error=registration_error(warped, task.y),
                        correspondence=np.asarray(res.correspondence, dtype=np.intp)
                        if own else None,
                        probability=np.asarray(res.probability, dtype=np.float64)
                        if own else None,
                        step=res.transform, min_jacobian=float(det.min()))


@dataclass
class _FineNode:
    q: FloatArray
    chain: ChainTransform


def _edge_steps(chain: ChainTransform, parent: ChainTransform) -> tuple[PointTransform, ...]:
    """The steps `chain` adds to its parent's."""
    if tuple(chain.path[:-1]) != tuple(parent.path):
        raise AssertionError(f"subject {chain.path[-1]}: its path {chain.path} does not "
                             f"extend its parent's {parent.path}")
    return chain.steps[len(parent.steps):]


def _polish_steps(res: SubjectResult) -> int:
    """How many CPD steps the polish (see :mod:`._polish`) added to `res`'s chain."""
    polish = (res.quality or {}).get("polish")
    return 0 if polish is None else int(polish.get("steps", 1))


def _edge_from_polished_parent(res: SubjectResult) -> bool:
    """Whether `res`'s edge was registered again from its parent's polished registration
    (its chain then extends the parent's whole chain, polish included)."""
    polish = (res.quality or {}).get("polish") or {}
    return bool((polish.get("from_parent") or {}).get("kept"))


def _as_built(res: SubjectResult) -> ChainTransform:
    """The chain `res` was attached with: a polished subject's chain ends in the polish's
    CPD steps, which its children were not built on."""
    assert res.transform is not None
    n = _polish_steps(res)
    if n == 0:
        return res.transform
    chain = res.transform
    return ChainTransform(source=chain.source, target=chain.target, steps=chain.steps[:-n],
                          path=chain.path)


def _refined_subjects(
    full: _Collection,
    subjects: list[SubjectResult],
    cpd: CPDOptions,
    control: IntArray | None,
    executor: Executor | None,
    progress: ProgressCallback | None,
    stage: str,
) -> tuple[list[SubjectResult], dict[int, tuple[PointTransform, ...]]]:
    """`subjects` (decided at the working resolution) with every registration redone at
    the stored resolution, a layer at a time from the root: one short CPD per subject,
    started from its parent's stored-resolution result as its children were built on, moved
    by the subject's coarse edge (and, for a polished subject, its coarse polish steps: see
    :mod:`._polish`). A child whose polish registered its edge again from the parent as
    polished starts from the parent's final stored-resolution result; a polished subject
    with children built on its chained registration (its edge's own, at the working
    resolution) gets one more CPD, of its edge alone, for those children to start from.

    The edge is a map of the plane fitted between the parent's shape and the subject's,
    so it carries the parent's refined correspondences over. On six 永 ground-truth
    families (bench/RESULTS.md section 8.1) one CPD for a polished subject (edge and polish
    together) gave the same correspondence error (0.99x) as redoing its edge and then its
    polish (two CPDs); one CPD per subject from its whole coarse chain was worse (1.04x).
    Children start from the result they were built on at the working resolution: started
    from a polished parent they had not been registered from, they inherit a polish that
    can move correspondences the wrong way while it lowers e (seen with the two-stage
    polish on one 永 design: 0.69x -> 0.88x of plain CPD); the polish registers a child's
    edge again from its polished parent only where that edge reaches no larger an e."""
    root = full.root
    # each member's stored-resolution registration: as built (what children attached on
    # its chained registration start from) and final (children whose edge was registered
    # again from its polished registration, see _polish.POLISH_FROM_PARENT_MIN_LAYER)
    fine = {root: _FineNode(q=full.normed[root], chain=full.root_chain())}
    fine_final = dict(fine)
    coarse_chain = {root: full.root_chain()}
    coarse_final = dict(coarse_chain)
    out = {s.index: s for s in subjects}
    pending = sorted((s for s in subjects if s.attached and s.parent is not None),
                     key=lambda s: (len(s.path), s.index))
    on_final = {s.index for s in pending if _edge_from_polished_parent(s)}
    needs_built = {s.parent for s in pending if s.index not in on_final}
    by_depth: dict[int, list[SubjectResult]] = {}
    for s in pending:
        by_depth.setdefault(len(s.path), []).append(s)
    total, done = len(pending), 0
    fine_outcome: dict[int, _FineOutcome] = {}
    final_chain: dict[int, ChainTransform] = {}
    # each subject's edge's affine pre-alignment (the polish at the stored resolution
    # registers the edge again from the parent as polished there, after the same steps)
    affines: dict[int, tuple[PointTransform, ...]] = {}
    for depth in sorted(by_depth):
        group = by_depth[depth]
        tasks, kinds, edges, steps, starts = [], [], {}, {}, {}
        for s in group:
            assert s.parent is not None and s.transform is not None
            built = _as_built(s)
            coarse_chain[s.index] = built
            coarse_final[s.index] = s.transform
            if s.index in on_final:
                edges[s.index] = _edge_steps(built, coarse_final[s.parent])
                starts[s.index] = fine_final[s.parent]
            else:
                edges[s.index] = _edge_steps(built, coarse_chain[s.parent])
                starts[s.index] = fine[s.parent]
            steps[s.index] = (*edges[s.index], *s.transform.steps[len(built.steps):])
            affines[s.index] = edges[s.index][:affine_lead(edges[s.index])]
            tasks.append(_FineTask(subject=s.index, q=starts[s.index].q,
                                   steps=steps[s.index], y=full.normed[s.index], cpd=cpd,
                                   control=control))
            kinds.append("final")
            if built is not s.transform and s.index in needs_built:
                tasks.append(_FineTask(subject=s.index, q=starts[s.index].q,
                                       steps=edges[s.index], y=full.normed[s.index], cpd=cpd,
                                       control=control, correspondences=False))
                kinds.append("built")
        counted = _counting(progress, stage, done, total, len(group) / len(tasks))
        for kind, res in zip(kinds, _map_tasks(_refine_edge, tasks, executor, counted, stage),
                             strict=True):
            s = out[res.subject]
            assert s.parent is not None
            own = steps[s.index] if kind == "final" else edges[s.index]
            chain = starts[s.index].chain.extended((*own, res.step), full.norms[s.index],
                                                   s.index)
            node = _FineNode(q=res.warped, chain=chain)
            if kind == "final":
                fine_outcome[s.index] = res
                final_chain[s.index] = chain
                fine_final[s.index] = node
            if kind == "built" or s.index not in fine:
                fine[s.index] = node
        done += len(group)
    for index, res in fine_outcome.items():
        s = out[index]
        s.quality = {**(s.quality or {}), "working_error": s.error,
                     "stored_min_jacobian": res.min_jacobian}
        s.error = res.error
        s.warped = full.norms[index].invert(res.warped)
        s.correspondence = res.correspondence
        s.probability = res.probability
        s.transform = final_chain[index]
    return [out[s.index] for s in subjects], affines


def _counting(progress: ProgressCallback | None, stage: str, offset: int,
              total: int, per_task: float = 1.0) -> ProgressCallback | None:
    """A progress callback that reports one layer's count within the whole stage's, in
    subjects (`per_task` of a subject a task)."""
    if progress is None:
        return None

    def report(_stage: str, done: int, _total: int) -> None:
        progress(stage, offset + int(done * per_task + 1e-9), total)

    return report


def at_stored_resolution(
    result: CollectionResult,
    full: _Collection,
    coarse: _Collection,
    cpd: CPDOptions,
    working_points: int | None,
    executor: Executor | None,
    progress: ProgressCallback | None,
    polish: bool = False,
) -> CollectionResult:
    """`result`, decided on `coarse`, with its registrations at the stored resolution;
    `polish`: its subjects (not direct CPD's) are then polished there
    (:func:`_polish_stored`; the dynamic tree with its polish).

    Unchanged (but for ``options["working_points"]``) when `coarse` is `full`.
    """
    result.options["working_points"] = working_points
    if coarse is full:
        return result
    # the root's control points, for every stored-resolution CPD of the tree and of direct
    n_control = max(FINE_CONTROL_POINTS, working_points or 0)
    root_points = full.normed[full.root]
    control = (farthest_point_indices(root_points, n_control)
               if len(root_points) > n_control else None)
    result.subjects, affines = _refined_subjects(full, result.subjects, cpd, control,
                                                 executor, progress, "full resolution")
    if polish:
        n_stage = max(POLISH_STAGE_CONTROL_POINTS, n_control)
        stage_control = (farthest_point_indices(root_points, n_stage)
                         if len(root_points) > n_stage else None)
        result.subjects = _polish_stored(full, result.subjects, cpd, control, affines,
                                         executor, progress, stage_control)
    if result.direct is not None:
        result.direct = _refined_subjects(full, result.direct, cpd, control, executor,
                                          progress, "direct full resolution")[0]
    return result


def _polish_stored(full: _Collection, subjects: list[SubjectResult], cpd: CPDOptions,
                   control: IntArray | None,
                   affines: dict[int, tuple[PointTransform, ...]],
                   executor: Executor | None, progress: ProgressCallback | None,
                   stage_control: IntArray | None = None) -> list[SubjectResult]:
    """`subjects`, registered at the stored resolution, polished there as the polish
    polished them at the working one (:func:`~registration._tree._polish._polish_subjects`:
    the stages from where the stored CPD left the model, the edge registered again from
    the parent as polished there (after `affines`, its affine pre-alignment), the finish
    from the root model and the symmetric finish; no consensus), every field through the
    model's points fitted with the `control` points (the backward CPD's with as many of
    the subject's), but the stages', which fit theirs with the `stage_control` points
    (:data:`POLISH_STAGE_CONTROL_POINTS`). Recorded in ``quality["stored_polish"]``; the
    confidence stays the one the decisions were taken with.

    A single edge whose polish the working resolution did not keep
    (``quality["polish_not_kept"]``) is not polished here either: it stays the stored
    CPD's (bench/RESULTS.md 7.54).

    Unlike the working resolution's polish, every subject registers its edge again (at
    layer 2 from the root's own points, deeper from the parent as polished here, whether
    or not the parent's polish moved it) and goes on to the halfway registration whatever
    that edge's e (kept there at up to ``CONSENSUS_MAX_E_RATIO`` times the lower e of the
    two, as always): the stored CPD only refines the coarse edge where it lies, so what
    the coarse stage could not fit (the stages' finer kernel on 400 points, a slide the
    coarse sampling allowed) is left to this stage, and a full CPD at the stored points
    can leave a slide of its own; halfway, the two err differently. Alone, the full CPD
    in place of the stored one breaks glyphs.

    Ground truth, tree / plain CPD over all subjects (bench/RESULTS.md 7.31, where the
    variants measured on the way are): glyph edges and skeletons rendered at 512 px and
    chained at 1200 points, 0.459 / 0.581 with the stored finishes alone -> 0.419 /
    0.432 (every far half at most 0.6x); at 1200 points a shape, MPEG-7 0.496 -> 0.287,
    evenly sampled outlines 0.963 -> 0.543, random subsets 0.891 -> 0.604; the 73
    full-size 永 glyphs' HTTP job 13.5 -> 22.8 s. Its cheaper variants (fewer stages
    before the halfway step, an accelerated edge, fewer subject points) lose or save
    little (7.32)."""
    results = {s.index: s for s in subjects}
    _polish_subjects(full, results, cpd, executor, progress,
                     stored=AtStored(control=control, edge_affines=affines,
                                     stage_control=stage_control))
    return [results[s.index] for s in subjects]

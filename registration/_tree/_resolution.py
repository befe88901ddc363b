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
edge's warp on the stored points). The dynamic tree's subjects are then finished at the
stored resolution as the polish finished them at the working one (:func:`_stored_finish`
and :func:`_stored_symmetric`, in the same task as the subject's CPD;
``quality["stored_finish"]`` and ``quality["stored_symmetric"]``); their children start
from the registration before those. The confidence is the one the decisions were taken
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
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._cpd import CPDOptions, NonrigidTransform, cpd_nonrigid
from .._cpd._estep import _posterior_max
from .._error import registration_error
from .._executor import Executor
from .._pointmap import PointTransform, composed_with_jacobian
from .._points import farthest_point_indices, mean_spacing2
from .._result import CollectionResult, SubjectResult
from .._similarity import ProgressCallback
from .._transform import AffineTransform, ChainTransform
from ._collection import _Collection
from ._polish import (
    FINISH_MAX_E_RATIO,
    _cpd_from_root,
    _halfway_back,
    _step_onto,
)
from ._symmetric import NoHalfway
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
#: stage's CPU time. Never fewer than the working resolution's points.
FINE_CONTROL_POINTS = 500
#: EM iterations of the symmetric finish's backward CPD at the stored resolution (at most;
#: see `_stored_symmetric`). Started from the finished registration, it took 70 on
#: average (120 at the 90th percentile) on 40 of the 永 edge glyphs at full resolution;
#: stopped at 20, as the stored CPD, six 1200-point 永 edge chains gave the same ground
#: truth (0.0272 against 0.0271) and the 73 glyphs' stored-resolution stage over HTTP took
#: 11.6 s instead of 13.4-14.0 (bench/RESULTS.md 7.16).
STORED_SYMMETRIC_MAX_ITER = 20


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
    # the stored root model (normalised), when the subject is finished at the stored
    # resolution after its CPD (see `_stored_finish`); None: not finished
    model: FloatArray | None = None
    spacing2: float = 0.0  # the stored subject's h^2 (the collection's), for the finish
    # whether the outcome's correspondences are read (not for an edge run only for the
    # subject's children to start from); each is a pass over every stored pair
    correspondences: bool = True


@dataclass(frozen=True)
class _StoredFinish:
    """What the finish at the stored resolution found (see :func:`_stored_finish`): its
    record, and when kept the step that extends the subject's chain and where it puts the
    model."""

    info: dict[str, Any]
    step: PointTransform | None = None
    warped: FloatArray | None = None
    error: float | None = None
    # when kept: the correspondences and their probabilities, read from `posterior` (in
    # the task, only for the last finish kept: see `_last_kept`)
    correspondence: IntArray | None = None
    probability: FloatArray | None = None
    posterior: Callable[[], tuple[NDArray[Any], NDArray[Any]]] | None = field(
        default=None, repr=False, compare=False)


@dataclass(frozen=True)
class _FineOutcome:
    subject: int
    warped: FloatArray
    error: float
    # None when a stored finish kept supplies them or none is read (`correspondences`)
    correspondence: IntArray | None
    probability: FloatArray | None
    step: NonrigidTransform
    min_jacobian: float  # of the edge's non-rigid warp (coarse then fine) on the stored model
    finish: _StoredFinish | None = None  # when the task asked for it
    symmetric: _StoredFinish | None = None  # the symmetric finish, with the finish


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
    lead = 0
    while lead < len(task.steps) - 1 and isinstance(task.steps[lead], AffineTransform):
        lead += 1
    pre = task.q
    for step in task.steps[:lead]:
        pre = step.apply(pre)
    # the edge's non-rigid steps, with their Jacobians for the fold check below
    both = composed_with_jacobian(task.steps[lead:], pre)
    assert both is not None, "every step of a tree edge gives its Jacobian"
    start, jac = both
    o = task.cpd
    res = cpd_nonrigid(start, task.y, beta=o.beta, lmbda=o.lmbda, w=o.w, tol=o.tol,
                       max_iter=min(o.max_iter, FINE_MAX_ITER), dtype=o.dtype,
                       sigma2=warm_start_sigma2(start, task.y), normalize=False,
                       control=task.control, accelerate=True)
    warped = np.asarray(res.warped, dtype=np.float64)
    # chain rule: the fine step's Jacobians where the edge put the points, after the edge's
    # (one kernel product per step; taking the whole composition again cost twice that)
    jac = res.transform.apply_with_jacobian(start)[1] @ jac
    det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
    error = registration_error(warped, task.y)
    finish = symmetric = None
    if task.model is not None:
        finish = _stored_finish(task.model, warped, error, task.y, task.spacing2, o,
                                task.control)
        at, e_at = warped, error
        if finish.warped is not None and finish.error is not None:  # the finish was kept
            at, e_at = finish.warped, finish.error
        symmetric = _stored_symmetric(task.model, at, e_at, task.y, task.spacing2, o,
                                      task.control)
        finish, symmetric = _last_kept(finish, symmetric)
    kept = any(f is not None and f.step is not None for f in (finish, symmetric))
    own = task.correspondences and not kept
    return _FineOutcome(subject=task.subject, warped=warped, error=error,
                        correspondence=np.asarray(res.correspondence, dtype=np.intp)
                        if own else None,
                        probability=np.asarray(res.probability, dtype=np.float64)
                        if own else None,
                        step=res.transform, min_jacobian=float(det.min()), finish=finish,
                        symmetric=symmetric)


def _last_kept(finish: _StoredFinish, symmetric: _StoredFinish
               ) -> tuple[_StoredFinish, _StoredFinish]:
    """The two stored finishes with the correspondences of the last one kept read (the
    subject's), the other's dropped unread: the outcome goes to another process."""
    last = symmetric if symmetric.step is not None else finish
    out = []
    for fin in (finish, symmetric):
        if fin is last and fin.posterior is not None:
            corr, prob = fin.posterior()
            fin = replace(fin, correspondence=np.asarray(corr, dtype=np.intp),
                          probability=np.asarray(prob, dtype=np.float64), posterior=None)
        elif fin.posterior is not None:
            fin = replace(fin, posterior=None)
        out.append(fin)
    return out[0], out[1]


def _stored_finish(model: FloatArray, warped: FloatArray, error: float, y: FloatArray,
                   spacing2: float, o: CPDOptions, control: IntArray | None
                   ) -> _StoredFinish:
    """The polish's finish (:func:`registration._tree._polish._finish`: its CPD,
    :func:`~registration._tree._polish._cpd_from_root`, and its step,
    :func:`~registration._tree._polish._step_onto`) again at the
    stored resolution: one CPD of the stored root model itself onto the stored subject,
    started where the subject's stored-resolution CPD left it (``init_warped``) from a
    variance of half its e (at least `spacing2`, the subject's h^2, as the polish's), its
    kernel :data:`~registration._tree._polish.FINISH_BETA_FACTOR` of the tree's beta, its
    regulariser :data:`~registration._tree._polish.FINISH_LMBDA_FACTOR` times the tree's
    lambda, fitted with the `control` points as the stage's CPD.

    The short CPD before it is penalised from the parent's warped model, so it keeps the
    slides the working resolution settled into; the finish's field is penalised from the
    root, and at the stored resolution the subject's own sampling noise, which sets how
    close to the truth CPD can settle, is smaller than at the working resolution (on six
    1200-point 永 edge chains the tree's ground-truth error went 0.0337 -> 0.0289, against
    0.0250 for a tree run entirely at 1200 points: bench/RESULTS.md 8.4).

    The subject's chain gains CPD's field through the control points (all points without
    them) from where the stored CPD left them to where the finish puts them
    (:func:`~registration._cpd.interpolating_field` at the consensus's width, as the
    polish's finish); the step's image of every stored point is what is reported, so the
    chain still maps the root onto it. Kept when neither the finish's field from the root
    nor the step folds at any stored point and the e reached is at most
    :data:`~registration._tree._polish.FINISH_MAX_E_RATIO` times the stored CPD's (the
    polish's rule; its confidence check is not repeated: the quality model is the working
    resolution's)."""
    info: dict[str, Any] = {"kept": False, "error_before": error}
    res = _cpd_from_root(model, y, warped, max(0.5 * error, spacing2, 1e-12), o, control)
    if res is None:
        info["reason"] = "its field from the root folds"
        return _StoredFinish(info)
    found = _step_onto(warped, np.asarray(res.warped, dtype=np.float64), o, control)
    if found is None:
        info["reason"] = "the step to it folds"
        return _StoredFinish(info)
    step, moved = found
    return _stored_ruled(info, step, moved, y, error, "the stored CPD's",
                         lambda e: (res.correspondence, res.probability))


def _stored_ruled(info: dict[str, Any], step: PointTransform, moved: FloatArray,
                  y: FloatArray, error: float, whose: str,
                  correspondence: Callable[[float], tuple[NDArray[Any], NDArray[Any]]]
                  ) -> _StoredFinish:
    """The stored finishes' rule: `step` (to `moved`) kept when its e is at most
    :data:`~registration._tree._polish.FINISH_MAX_E_RATIO` times `error` (`whose`: whose e
    that is, for the reason; `correspondence(e)`: the correspondences and their
    probabilities then). `info` records the e and the reason."""
    e = registration_error(moved, y)
    info["error"] = e
    if not e <= FINISH_MAX_E_RATIO * error:
        info["reason"] = f"e above {FINISH_MAX_E_RATIO:g}x {whose}"
        return _StoredFinish(info)
    info["kept"] = True
    info["reason"] = f"e at most {FINISH_MAX_E_RATIO:g}x {whose}"
    return _StoredFinish(info, step=step, warped=moved, error=e,
                         posterior=lambda: correspondence(e))


def _stored_symmetric(model: FloatArray, warped: FloatArray, error: float, y: FloatArray,
                      spacing2: float, o: CPDOptions, control: IntArray | None
                      ) -> _StoredFinish:
    """The polish's symmetric finish (:func:`registration._tree._polish._symmetric`) again
    at the stored resolution, after :func:`_stored_finish`: the stored subject registered
    back onto the stored root model from `warped` (where the finish left it; the stored
    CPD's points when the finish was not kept), and `warped` moved halfway to where the
    inverse of that backward field puts the model's points
    (:func:`~registration._tree._polish._halfway_back`). The backward CPD's field is
    fitted with as many of the subject's points as the model's `control` points (its
    farthest-point subsample), the fields through the model's points with those (so the
    backward field is inverted at those 500 root points alone). Kept, as the finish, when
    the inverse is found (at :data:`~registration._tree._symmetric.MIN_REACHED` of
    those points at least), the step does not fold and e is at most
    :data:`~registration._tree._polish.FINISH_MAX_E_RATIO` times `error`; without it the
    stored forward finish slides the points back (on six 1200-point 永 edge chains the
    working resolution's symmetric finish alone left the ground truth at 1.00x;
    bench/RESULTS.md 7.16)."""
    info: dict[str, Any] = {"kept": False, "error_before": error}
    subject_control = (None if control is None or len(y) <= len(control)
                       else farthest_point_indices(y, len(control)))
    found = _halfway_back(model, y, warped, error, spacing2, o, control, subject_control,
                          STORED_SYMMETRIC_MAX_ITER)
    info["without_inverse"] = found.without_inverse
    if isinstance(found, NoHalfway):
        info["reason"] = found.reason
        return _StoredFinish(info)
    step, moved = found.step, found.moved
    return _stored_ruled(info, step, moved, y, error, "the finished e",
                         lambda e: _posterior_max(moved, y, max(0.5 * e, spacing2), o.w))


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
    finish_model: FloatArray | None = None,
) -> list[SubjectResult]:
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
            tasks.append(_FineTask(subject=s.index, q=starts[s.index].q,
                                   steps=steps[s.index], y=full.normed[s.index], cpd=cpd,
                                   control=control, model=finish_model,
                                   spacing2=full.spacing2[s.index]))
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
        s.correspondence = res.correspondence  # None: a stored finish kept has them
        s.probability = res.probability
        s.transform = final_chain[index]
        for key, fin, said in (("stored_finish", res.finish, "finished again"),
                               ("stored_symmetric", res.symmetric, "made symmetric again")):
            if fin is None:
                continue
            s.quality[key] = fin.info
            if fin.step is None:
                continue
            assert fin.warped is not None and fin.error is not None
            s.error = fin.error
            s.warped = full.norms[index].invert(fin.warped)
            s.correspondence = fin.correspondence  # None: the symmetric one kept has them
            s.probability = fin.probability
            chain = s.transform
            s.transform = ChainTransform(source=chain.source, target=chain.target,
                                         steps=(*chain.steps, fin.step), path=chain.path)
            s.reason = f"{s.reason}; {said} at the stored resolution"
        assert s.correspondence is not None and s.probability is not None
    return [out[s.index] for s in subjects]


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
    finish: bool = False,
) -> CollectionResult:
    """`result`, decided on `coarse`, with its registrations at the stored resolution;
    `finish`: each of its subjects (not direct CPD's) is also finished there
    (:func:`_stored_finish`; the dynamic tree with its polish).

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
    result.subjects = _refined_subjects(full, result.subjects, cpd, control, executor,
                                        progress, "full resolution",
                                        root_points if finish else None)
    if result.direct is not None:
        result.direct = _refined_subjects(full, result.direct, cpd, control, executor,
                                          progress, "direct full resolution")
    return result

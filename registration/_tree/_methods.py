"""The three methods: the dynamic tree (Du et al. 2016), the static tree (Du et al. 2015)
and direct CPD from the root."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from typing import Any, Unpack

import numpy as np
from numpy.typing import ArrayLike

from .._error import part_of_model
from .._executor import Executor
from .._pose import PoseSpec
from .._result import Attempt, CollectionResult, SubjectResult
from .._similarity import ProgressCallback, Similarity
from . import _tasks
from ._collection import (
    _attempt,
    _Collection,
    _ensure_frontier,
    _subject_from_outcome,
    _TreeStart,
)
from ._options import MethodOptions, TreeOptions, takes_options
from ._passes import _again_from_root, _attach_leaves, _refine_parents
from ._polish import POLISH_MIN_LAYER, _polish_subjects, consensus_partner
from ._resolution import (
    at_stored_resolution,
    check_working_points,
    coarse_collection,
)
from ._rules import (
    AGAIN_E_FACTOR,
    BRIDGE_TASKS_PER_SUBJECT,
    ERROR_FACTOR,
    SPACING_FACTOR,
    _auto_error_threshold,
    _check_threshold,
    _error_limit,
    _lower_quartile_error,
    _rejection,
    _similarity_report,
    _SimilarityRule,
    _spacing_floor,
)
from ._tasks import (
    CPDOptions,
    _lowest_error,
    _options_dict,
    _owns_executor,
    _RegOutcome,
    _RegTask,
    _run_tasks,
    _starts,
    _turns_wait,
)


@takes_options(TreeOptions)
@_owns_executor
def build_dynamic_tree(
    shapes: Sequence[ArrayLike],
    root: int = 0,
    *,
    max_candidates: int = 3,
    fold_check: bool = True,
    refine: bool = True,
    polish: bool = True,
    **options: Unpack[TreeOptions],
) -> CollectionResult:
    """Register the root model to every shape through a dynamic tree (Du et al. 2016).

    Each edge of the tree is CPD's registration of the member's warped model onto the
    subject, made symmetric when both shapes have at least 150 points and the tree is
    decided at the stored resolution (no shape above `working_points`): moved halfway to
    where the subject, registered back onto that model, puts its points (CPD's slides
    along the outline fall differently the two ways round, so part of each cancels; the
    subject's ``quality["symmetric_edge"]`` says whether it was, and
    ``quality["symmetric_edge_reason"]`` why not). Between shapes of at least 150 points
    each edge's CPD runs from two starts, annealed from the spread of all pairs (the
    paper's) and held (the member's warped model where it lies, sigma^2 from its
    residual), and the registration with the lower e is kept: annealing can settle a group
    of parallel strokes one stroke off (``quality["edge_start"]`` says which start was
    kept, ``quality["edge_start_errors"]`` the e of each). Direct CPD and the static tree
    keep the paper's one-way CPD from its one start.

    Parameters
    ----------
    max_candidates : int
        When several members are similar to a waiting subject, the `max_candidates`
        most similar (smallest D) members not yet tried for it are tried in one layer
        and the accepted registration with the smallest e is kept. Where every turn may
        be tried (``pose="rotation"`` or ``"affine"``), a kept registration from another
        member whose e is above twice the lower quartile of the first layer's e (and
        above the subject's sampling floor) is registered from the root too, and the
        root's is kept instead when accepted at below 0.7x its e: an edge that missed
        the turn between a member and a subject fits the wrong pose at 2-3x the e right
        ones reach, under the error threshold (bench/RESULTS.md 7.50). In a collection
        that grows as given (at least twice as many subjects joined keeping their
        member's pose as turning it), a kept registration that turned its member's pose
        (``quality["pose"] == "rotated"``) waits while other subjects of its layer join
        as given: its subject is tried from the next layers' members too, and joins
        turned only when no registration that keeps the pose comes within the margin a
        turn must earn, or when a layer adds no subject as given (its ``reason`` then
        says it waited; bench/RESULTS.md 7.63).
    fold_check : bool
        Also reject registrations whose displacement field folds the model (Jacobian
        determinant <= 0 at a model point): e can be small while correspondences are wrong.
    refine : bool
        After the tree stops growing, a subject without children may move to a member
        that joined the tree after it and is more similar to it than its parent, when
        the registration from there is better (higher confidence, or as confident with a
        lower e). No cycles: a subject never moves below itself.
    polish : bool
        Finally, every attached subject is registered again by CPD from the root model
        where its chain (at layer 2: its one edge) left it, in two stages, the edges'
        kernel width beta then half of it; a stage is kept when it does not fold, lowers
        e and keeps a confidence >= 0.2, and a rejected stage is skipped (see
        :mod:`._polish`): the slide a chain accumulates link by link can relax, then the
        finer deformation the edges' smooth kernel leaves out is fitted. Two links or
        more from the root, the subject is also registered from a partner (the member
        nearest it by D that was polished before it, not its parent; the root itself,
        directly, when none is nearer or the subject has fewer than 150 points), and
        halfway between the two (polished again) replaces the chain's registration when
        its e is at most 1.1x the chain's: the two registrations' errors partly cancel.
        Subjects are polished parents first, and two links or more from the root a
        subject's edge is also registered again from its parent as polished; when its e
        is no larger than the chain's, both are polished and halfway between the two
        (polished again) is taken (the subject's transform then extends the parent's
        polished one). Up to two more CPD per subject; two links or more from the root,
        up to twelve (thirteen when the partner's registration also tries a rotated
        pose). On the
        ground-truth chains of bench/bench_groundtruth.py it lowered the correspondence
        error on every family but randomly subsampled outlines (bench/RESULTS.md, 0.4,
        0.5, 0.6 and 0.9); False: the tree as built.

    Returns
    -------
    CollectionResult

    Raises
    ------
    ValueError
        On invalid shapes, root, names or thresholds.
    """
    error_threshold = options["error_threshold"]
    _check_threshold("error_threshold", error_threshold)
    if max_candidates < 1:
        raise ValueError(f"max_candidates must be at least 1; got {max_candidates}")
    run = _Run.prepare(shapes, root, options, mixture="sampling")
    start = run.tree_start(options)
    cpd, executor, progress = run.cpd, run.executor, run.progress
    coll, sim, allowed, sim_rule = start.coll, start.sim, start.allowed, start.rule
    edge = partial(run.edge, sim)
    subjects_idx, nodes, results = start.subjects, start.nodes, start.results
    tau_err = error_threshold
    floors = {s: _spacing_floor(coll.spacing2[s]) for s in subjects_idx}
    waiting = set(subjects_idx)
    tried: set[tuple[int, int]] = set()
    rejected: dict[int, list[_RegOutcome]] = {}
    parts: set[int] = set()  # subjects that are part of the model
    e_ref: float | None = None  # the lower quartile of the first round's e
    frontier = [root]
    # turned registrations waiting while the tree still grows as given (`_turns_wait`)
    held: dict[int, _RegOutcome] = {}
    joined = [0, 0]  # how many subjects joined keeping their member's pose, and turned
    waited: dict[int, tuple[int, int]] = {}  # subject -> round it first waited, the turn's member
    # the round of growth: each tries the waiting subjects from the last round's new
    # members (from every member after a stall's bridges; a subject's layer is its depth,
    # one below its parent's, whichever round it joined in); progress names it "round N"
    # (N = grown - 1), not "layer N": bridges let a later round attach subjects higher up
    grown = 1
    runs = 0  # registrations so far; bridging stops at a budget (BRIDGE_TASKS_PER_SUBJECT)

    def bridge() -> bool:
        if runs >= BRIDGE_TASKS_PER_SUBJECT * len(subjects_idx):
            return False
        return bool(sim_rule.bridge(sim, nodes, waiting, tried))

    while waiting and (frontier or held):
        grown += 1
        _ensure_frontier(sim, frontier, waiting, allowed, executor, progress,
                         f"similarity round {grown - 1}")
        tasks: list[_RegTask] = []
        for _ in range(2):  # once more after new bridges when nothing is left to try
            for s in sorted(waiting):
                cands = sorted(
                    (float(sim.D[m, s]), m)
                    for m in start.members_for(s)
                    if (m, s) not in tried and sim_rule.similar(sim, m, s)
                )[:max_candidates]
                for _, m in cands:
                    tried.add((m, s))
                    tasks.append(edge(m, s, nodes[m].layer + 1, nodes[m].q))
            if tasks or held or not bridge():
                break
        if not tasks and not held:
            break
        runs += len(tasks)
        outcomes = _run_tasks(tasks, executor, progress, f"round {grown - 1}") if tasks else []
        if e_ref is None:  # the first round's: the root's registrations of its nearest
            e_ref = _lower_quartile_error(outcomes)
        if tau_err is None:
            tau_err = _auto_error_threshold(e_ref)
        accepted: dict[int, list[_RegOutcome]] = {}
        limits = {s: _error_limit(tau_err, error_threshold is not None, floors[s])
                  for s in {out.subject for out in outcomes} | held.keys()}
        # a subject is part of the model by the root's registration of it, the one the
        # chain's links cannot have squeezed (`_rules._rejection`)
        parts.update(out.subject for out in outcomes if out.member == root and part_of_model(
            out.warped, coll.normed[out.subject], coll.spacing2[out.subject]))
        for out in outcomes:
            limit = limits[out.subject]
            rejection = _rejection(out, limit, fold_check, part=out.subject in parts)
            ok = rejection is None
            reason = rejection or "accepted candidate"
            if not ok:
                rejected.setdefault(out.subject, []).append(out)
            results[out.subject].attempts.append(_attempt(out, limit, reason))
            if ok:
                accepted.setdefault(out.subject, []).append(out)
        for s, out in held.items():
            accepted.setdefault(s, []).append(out)
        best = {s: _lowest_error(outs) for s, outs in accepted.items()}
        if run.prealign and run.pose.any_rotation:  # an edge can miss a turn only there
            runs += _again_from_root(
                coll, results, best, tried,
                {s: max(AGAIN_E_FACTOR * e_ref, floors[s]) for s in best}, limits,
                fold_check, edge, nodes[root].q, executor, progress, f"round {grown - 1}")
        held = _turns_wait(best, joined)
        for s, out in held.items():
            waited.setdefault(s, (grown, out.member))
        new_frontier = []
        for s, out in sorted(best.items()):
            res, node = _subject_from_outcome(coll, out, nodes[out.member], joined=grown)
            res.attempts = [
                Attempt(**{**asdict(a), "accepted": a.member == out.member})
                for a in results[s].attempts
            ]
            res.reason = f"registered from {coll.names[out.member]} (layer {out.layer - 1})"
            if s in waited:  # say why it joined later than its turn was found
                first, turn = waited.pop(s)
                rounds = f"{grown - first} round{'s' if grown - first > 1 else ''}"
                res.reason += (f"; turned, after waiting {rounds} while the tree grew as given"
                               if out.pose == "rotated" else
                               f"; as given, after a turn from {coll.names[turn]} waited "
                               f"{rounds}")
            results[s] = res
            nodes[s] = node
            waiting.discard(s)
            new_frontier.append(s)
            joined[out.pose == "rotated"] += 1
        if not new_frontier and waiting and bridge():
            new_frontier = list(nodes)  # stalled: the next nearest bridges, from any member
        frontier = new_frontier
    # leaves first: they may reuse registrations made while the tree grew, which start
    # from their member's warped model as it was then; refinement then moves no member
    # that has a child, leaves included, so every chain stays the one it was built on
    if waiting:
        _attach_leaves(coll, sim, nodes, results, waiting, rejected, tried, allowed, edge,
                       max_candidates, executor, progress)
    if refine:
        _refine_parents(coll, sim, sim_rule, nodes, results, tried, tau_err, floors,
                        error_threshold is not None, fold_check, edge, executor, progress)
    known: dict[int, _RegOutcome] | None = None
    if polish:
        if options["compare_direct"]:  # run once, for the comparison and the consensus
            known = run.direct_outcomes(sim)

        def partner(s: int) -> _RegTask | _RegOutcome:
            """Subject `s` registered from its consensus partner (run once polished)."""
            m = consensus_partner(sim.D[:, s], results, nodes, s, root, len(coll.normed[s]))
            if m == root:
                # the partner's registration is an edge of the tree's own kind: direct
                # CPD's (compare_direct) serves only when the edges are one-way and
                # annealed too
                if (known is not None and not run.symmetric_edges
                        and not _tasks.HELD_START_EDGES):
                    return known[s]
                return edge(root, s, 2, coll.normed[root])
            r = results[m]
            assert r.warped is not None and r.layer is not None
            return edge(m, s, r.layer + 1, coll.norms[m].apply(r.warped))

        # the step towards plain CPD at the resolution the result is reported at
        _polish_subjects(coll, results, cpd, executor, progress, partner=partner,
                         along_plain=run.coll is run.full)
    return run.finish(
        "dynamic_tree", [results[s] for s in subjects_idx], sim, sim_rule,
        compare_direct=options["compare_direct"],
        thresholds={
            "error": tau_err,
            "error_rule": "explicit" if error_threshold is not None
            else f"auto: max({ERROR_FACTOR} x lower quartile of layer-2 e, "
            f"{SPACING_FACTOR} x the subject's squared point spacing)",
            "fold_check": fold_check,
            "polish": f"layer >= {POLISH_MIN_LAYER}" if polish else "off",
        },
        max_candidates=max_candidates, direct_outcomes=known, finish=polish,
    )


@takes_options(TreeOptions, ignored={
    "error_threshold": "Ignored (the static tree rejects nothing); accepted for a uniform "
                       "interface.",
})
@_owns_executor
def build_static_tree(
    shapes: Sequence[ArrayLike],
    root: int = 0,
    **options: Unpack[TreeOptions],
) -> CollectionResult:
    """The static (heuristic) tree of Du et al. 2015: built once, no rejection.

    The tree grows layer by layer over the similarity graph (``D <= similarity
    threshold``, automatic as in :func:`build_dynamic_tree`); each subject joins the
    most similar member of the previous layer. Then CPD runs along its edges, each edge
    starting from the root model as warped onto the parent. `error_threshold` is accepted
    for a uniform interface and ignored: no registration is rejected. Subjects the
    similarity graph does not reach from the root are reported unattached (with the
    automatic rule, only those without any computed path from the root).

    Returns
    -------
    CollectionResult
        ``method == "static_tree"``; every attempt is accepted.

    Raises
    ------
    ValueError
        On invalid shapes, root, names or thresholds.
    """
    run = _Run.prepare(shapes, root, options)
    start = run.tree_start(options)
    executor, progress = run.executor, run.progress
    coll, sim, sim_rule, nodes, results = (start.coll, start.sim, start.rule, start.nodes,
                                           start.results)
    # 1. the tree, from the similarity alone
    parent: dict[int, int] = {}
    layers: list[list[int]] = [[root]]
    waiting = set(start.subjects)
    while waiting and layers[-1]:
        frontier = layers[-1]
        _ensure_frontier(sim, frontier, waiting, start.allowed, executor, progress,
                         f"similarity layer {len(layers) + 1}")
        new = []
        for s in sorted(waiting):
            cands = [(float(sim.D[m, s]), m) for m in frontier if sim_rule.similar(sim, m, s)]
            if cands:
                parent[s] = min(cands)[1]
                new.append(s)
        waiting -= set(new)
        layers.append(new)
    # 2. CPD along the edges, a layer at a time
    for depth, members in enumerate(layers[1:], start=2):
        tasks = [run.task(sim, parent[s], s, depth, nodes[parent[s]].q) for s in members]
        for out in _run_tasks(tasks, executor, progress, f"layer {depth}"):
            res, node = _subject_from_outcome(coll, out, nodes[out.member], joined=depth)
            res.reason = f"static edge from {coll.names[out.member]}"
            results[out.subject] = res
            nodes[out.subject] = node
    for s in waiting:
        results[s].reason = "not reached: no similar shape on a path from the root"
    return run.finish(
        "static_tree", [results[s] for s in start.subjects], sim, sim_rule,
        compare_direct=options["compare_direct"],
        thresholds={"error": None, "error_rule": "none: the static tree does not reject"},
    )


def _collection_result(
    method: str,
    coll: _Collection,
    sim: Similarity,
    subjects: list[SubjectResult],
    direct: list[SubjectResult] | None,
    rule: _SimilarityRule | None,
    *,
    thresholds: dict[str, Any],
    options: dict[str, Any],
) -> CollectionResult:
    """A method's result: its subjects (and direct CPD's), with the collection's names, the
    similarity it computed and its thresholds, the similarity rule's first when it had one."""
    report = _similarity_report(rule) if rule is not None else {}
    return CollectionResult(
        method=method,
        root=coll.root,
        names=coll.names,
        subjects=subjects,
        thresholds={**report, **thresholds},
        options=options,
        direct=direct,
        similarity_pairs=sim.computed,
        similarity=sim.D,
    )


@dataclass(frozen=True)
class _Run:
    """One method call's arguments that every method shares, checked: the collection at
    the stored (`full`) and the working (`coll`) resolution, CPD's options, the pose rule
    and where the registrations run."""

    full: _Collection
    coll: _Collection
    working_points: int | None
    cpd: CPDOptions
    prealign: bool
    pose: PoseSpec
    executor: Executor | None
    progress: ProgressCallback | None

    @classmethod
    def prepare(cls, shapes: Sequence[ArrayLike], root: int, options: MethodOptions,
                mixture: str = "uniform") -> _Run:
        """Check the arguments (ValueError) and prepare the collection; `options` holds
        every option (:func:`takes_options` gives the defaults); `mixture`, the method's
        own CPD mixture (:attr:`CPDOptions.mixture_weights`), for options that leave it to the
        method."""
        working_points = check_working_points(options["working_points"])
        full = _Collection.prepare(shapes, root, options["names"])
        spec = PoseSpec.resolve(options["pose"], options["max_rotation"])
        cpd = options["cpd"] if options["cpd"] is not None else CPDOptions()
        if cpd.mixture_weights is None:
            cpd = replace(cpd, mixture_weights=mixture)
        return cls(full=full, coll=coarse_collection(full, working_points),
                   working_points=working_points, cpd=cpd,
                   prealign=options["prealign"], pose=spec, executor=options["executor"],
                   progress=options["progress"])

    @property
    def symmetric_edges(self) -> bool:
        """Whether the dynamic tree's edges are made symmetric: when the collection is
        registered at its stored resolution (no coarse stage). At the stored resolution
        every edge of a coarse tree is registered again by a short one-way CPD, which keeps
        little of the gain (1200-point 永 chains: edges 0.0296 -> 0.0292, skeletons 0.0413
        -> 0.0411) for 1.4x the HTTP job's time (bench/RESULTS.md 7.29)."""
        return _tasks.SYMMETRIC_LINKS and self.coll is self.full

    def tree_start(self, options: TreeOptions) -> _TreeStart:
        """What a tree method starts from (ValueError on an invalid threshold)."""
        _check_threshold("similarity_threshold", options["similarity_threshold"])
        return _TreeStart.prepare(self.coll, options["similarity_threshold"],
                                  options["candidates"], self.pose, self.executor,
                                  self.progress)

    def task(self, sim: Similarity, member: int, subject: int, layer: int,
             q: np.ndarray, symmetric: bool = False, held: bool = False) -> _RegTask:
        """The registration of the model as warped onto `member` (`q`) to `subject`
        (made symmetric when `symmetric`, CPD also run from the held start when `held`:
        the dynamic tree's edges)."""
        return _RegTask(
            subject=subject, member=member, layer=layer,
            similarity=float(sim.D[member, subject]), q=q, y=self.coll.normed[subject],
            starts=_starts(sim, member, subject), cpd=self.cpd,
            prealign=self.prealign, pose=self.pose, spacing2=self.coll.spacing2[subject],
            root_shape=None if member == self.coll.root else sim.shape(self.coll.root),
            symmetric=symmetric, held=held,
        )

    def edge(self, sim: Similarity, member: int, subject: int, layer: int,
             q: np.ndarray) -> _RegTask:
        """The dynamic tree's edge from `member` (the model warped onto it, `q`) to
        `subject`: :meth:`task`, symmetric at the stored resolution and with CPD also run
        from the held start. Every pass of the tree (growth, leaves, refinement, the
        consensus's partner) registers its edges through this one builder."""
        return self.task(sim, member, subject, layer, q, self.symmetric_edges,
                         _tasks.HELD_START_EDGES)

    def direct_outcomes(self, sim: Similarity) -> dict[int, _RegOutcome]:
        """The root registered directly onto every subject, as a layer-2 edge (pose
        handling included), by subject."""
        coll, r = self.coll, self.coll.root
        subjects_idx = [k for k in range(coll.n) if k != r]
        if self.prealign:
            sim.ensure([(r, s) for s in subjects_idx], executor=self.executor,
                       progress=self.progress, stage="similarity direct")
        tasks = [self.task(sim, r, s, 2, coll.normed[r]) for s in subjects_idx]
        return {out.subject: out
                for out in _run_tasks(tasks, self.executor, self.progress, "direct")}

    def direct(self, sim: Similarity, compare: bool = True,
               outcomes: dict[int, _RegOutcome] | None = None) -> list[SubjectResult] | None:
        """Direct CPD from the root to every subject (None unless ``compare``); from
        `outcomes` (:meth:`direct_outcomes`) when they were already run."""
        if not compare:
            return None
        if outcomes is None:
            outcomes = self.direct_outcomes(sim)
        root_node = self.coll.root_node()
        subjects = []
        for _, out in sorted(outcomes.items()):
            res, _ = _subject_from_outcome(self.coll, out, root_node, joined=2)
            res.reason = "direct CPD from the root"
            subjects.append(res)
        return subjects

    def finish(
        self,
        method: str,
        subjects: list[SubjectResult],
        sim: Similarity,
        rule: _SimilarityRule | None,
        *,
        compare_direct: bool,
        thresholds: dict[str, Any],
        max_candidates: int = 1,
        direct_outcomes: dict[int, _RegOutcome] | None = None,
        finish: bool = False,
    ) -> CollectionResult:
        """The method's result (with direct CPD's when ``compare_direct``: from
        `direct_outcomes` when they were already run), at the stored resolution (its
        subjects polished there when `finish`: see :func:`._resolution._polish_stored`)."""
        direct = self.direct(sim, compare_direct, direct_outcomes)
        result = _collection_result(
            method, self.coll, sim, subjects, direct, rule,
            thresholds=thresholds,
            options=_options_dict(self.cpd, self.prealign, max_candidates, self.pose),
        )
        return at_stored_resolution(result, self.full, self.coll, self.cpd,
                                    self.working_points, self.executor, self.progress,
                                    polish=finish)


@takes_options(MethodOptions, ignored=dict.fromkeys(
    ("similarity_threshold", "error_threshold", "compare_direct"),
    "Ignored; accepted so that the three methods take the same arguments.",
))
@_owns_executor
def register_direct(
    shapes: Sequence[ArrayLike],
    root: int = 0,
    **options: Unpack[MethodOptions],
) -> CollectionResult:
    """Direct CPD from the root model to every subject (the paper's baseline).

    With `prealign` (default) the pose handling of :func:`build_dynamic_tree` applies (CPD
    from the pose as given, and from a clearly better other pose when ICP finds one); the
    paper's plain CPD is ``prealign=False``: no pose search of any kind.
    Every subject is at layer 2 with the root as parent.

    Returns
    -------
    CollectionResult
        ``method == "direct"``.

    Raises
    ------
    ValueError
        On invalid shapes, root or names.
    """
    run = _Run.prepare(shapes, root, options)
    sim = Similarity.empty(run.coll.normed, pose=run.pose)
    subjects = run.direct(sim)
    assert subjects is not None
    return run.finish("direct", subjects, sim, None, compare_direct=False,
                      thresholds={"similarity": None, "error": None, "error_rule": "none"})

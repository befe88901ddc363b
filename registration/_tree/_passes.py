"""The dynamic tree's passes beside its growth: a round's registrations far above the
collection's e tried again from the root; when the tree stops growing, every waiting
subject attached as a leaf through its best registration, then childless subjects moved
to better parents."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from .._error import part_of_model
from .._executor import Executor
from .._points import rms_distance
from .._result import SubjectResult
from .._similarity import ProgressCallback, Similarity
from ._collection import _attempt, _Collection, _Node, _subject_from_outcome
from ._rules import (
    REFINE_MAX_D_RATIO,
    REFINE_TIE,
    _error_limit,
    _rejection,
    _scattered,
    _SimilarityRule,
)
from ._tasks import (
    POSE_DISTINCT_DEG,
    POSE_MARGIN,
    _lowest_error,
    _RegOutcome,
    _RegTask,
    _run_tasks,
    _subject_half,
)

#: How far apart (RMS, in the subject's RMS radius) two registrations of a subject put the
#: model's points when they differ by a turn of ``POSE_DISTINCT_DEG``: the distance a
#: refinement among near ties by D must move it (`_refine_parents`).
REFINE_APART = 2.0 * math.sin(math.radians(POSE_DISTINCT_DEG) / 2.0)

# the dynamic tree's edge builder, `_Run.edge` bound to the similarity: (member, subject,
# layer, the model as warped onto the member) -> the registration task
EdgeTask = Callable[[int, int, int, np.ndarray], _RegTask]


def _again_from_root(
    coll: _Collection,
    results: dict[int, SubjectResult],
    best: dict[int, _RegOutcome],
    tried: set[tuple[int, int]],
    above: dict[int, float],
    limits: dict[int, float],
    fold_check: bool,
    edge: EdgeTask,
    root_model: np.ndarray,
    executor: Executor | None,
    progress: ProgressCallback | None,
    stage: str,
) -> int:
    """Register again from the root every subject `s` of a round whose best accepted
    registration (`best`, from another member) has an e above `above[s]`
    (``AGAIN_E_FACTOR`` times the lower quartile of the first round's e, or the subject's
    sampling floor when that is higher: below it e cannot show a closer fit), and keep
    the root's in its place when the tree's rule accepts it (e below `limits[s]`, no
    fold, the confidence) and its e is below ``POSE_MARGIN`` times the member's. Updates
    `best`, the subjects' attempts in `results` and `tried`; returns how many
    registrations it ran.

    An edge can miss the turn between a member and a subject: on a glyph of parallel
    strokes affine and rigid ICP rank several turns about alike, and none of those a
    member offers need be the true one. The edge then fits the wrong pose as well as a
    wrong pose fits, at 2-3x the e right registrations reach in the collection but under
    the error threshold (``ERROR_FACTOR``, 3x), and the subjects registered from it
    afterwards follow it. The root offers other turns, and its registration carries no
    link. It must be clearly better, by the margin a turned start must earn against the
    pose as given: over the larger difference the root bridges, a lower e can be a
    slide. Ground truth: bench/RESULTS.md 7.50 (書 in a serif font turned at random,
    seed 1: an edge at 0.0085, the quartile 0.0031, and four subjects after it wrong;
    from the root 0.0036 and all of them right)."""
    root = coll.root
    tasks = [edge(root, s, 2, root_model) for s, out in sorted(best.items())
             if out.member != root and (root, s) not in tried and out.error > above[s]]
    for out in _run_tasks(tasks, executor, progress, f"{stage}, again from the root"):
        s = out.subject
        tried.add((root, s))
        member, e_member = coll.names[best[s].member], best[s].error
        why = _rejection(out, limits[s], fold_check)
        if why is None and not out.error < POSE_MARGIN * e_member:
            why = (f"e={out.error:.4g} not below {POSE_MARGIN:g}x the e of the registration "
                   f"from {member} ({e_member:.4g})")
        results[s].attempts.append(_attempt(
            out, limits[s], why or (f"accepted candidate: the registration from {member} "
                                    f"reached e={e_member:.4g}, above {above[s]:.4g}, and "
                                    f"this one is below {POSE_MARGIN:g}x its e")))
        if why is None:
            best[s] = out
    return len(tasks)


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
    edge: EdgeTask,
    executor: Executor | None,
    progress: ProgressCallback | None,
) -> None:
    """Move childless subjects to a later, more similar member when that registers better.

    The layers fix a subject's parent at the first layer with an acceptable
    registration; a member that joined later can be more similar to it (a smaller D:
    a smaller deformation for CPD to bridge). For every subject without children, the
    most similar such member not yet tried (and not the subject itself or below it) is
    tried; the subject moves when the new registration passes the tree's rule and is
    better: a higher path confidence, or one within ``REFINE_TIE`` with a lower e. A
    member whose D is above ``REFINE_MAX_D_RATIO`` times the parent's is a near tie by
    D: the subject moves there only when the new registration puts the model in another
    pose than the one it had (the two further apart than a turn of ``POSE_DISTINCT_DEG``
    moves the points): then one of the two is wrong, and the rule above picks the other.
    Otherwise the two agree, and the move would only add a link.
    """
    parents = {r.parent for r in results.values() if r.parent is not None}
    tasks: list[_RegTask] = []
    for s, r in sorted(results.items()):
        if s in parents or r.parent is None or r.leaf or r.layer is None:
            continue
        d_parent = float(sim.D[r.parent, s])
        later = sorted(
            (float(sim.D[m, s]), m) for m, node in nodes.items()
            if m != s and node.joined >= nodes[s].joined and (m, s) not in tried
            and s not in node.chain.path and np.isfinite(sim.D[m, s])
            and sim.D[m, s] < d_parent and sim_rule.similar(sim, m, s)
        )
        if not later:
            continue
        _, m = later[0]
        tried.add((m, s))
        tasks.append(edge(m, s, nodes[m].layer + 1, nodes[m].q))
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
        if out.pose == "rotated" and (old.quality or {}).get("pose") != "rotated":
            # a turn earns its place by the margin, as across members (`_lowest_error`)
            better = better and out.error < POSE_MARGIN * old.error
        why = "refinement not taken: not better than the registration it had"
        assert old.parent is not None
        d_member, d_parent = float(sim.D[out.member, s]), float(sim.D[old.parent, s])
        if ok and better and not d_member <= REFINE_MAX_D_RATIO * d_parent:
            apart = rms_distance(out.warped, nodes[s].q)
            if apart < REFINE_APART:
                better = False
                why = (f"refinement not taken: D {d_member:.3g}, above "
                       f"{REFINE_MAX_D_RATIO:g}x the parent's ({d_parent:.3g}), and the "
                       f"registration {apart:.2g} of the subject's size from the one it "
                       f"had, the same pose")
        accepted = ok and better
        old.attempts.append(_attempt(
            out, limit, "refined: moved here, more similar and a better registration"
            if accepted else why, accepted=accepted))
        if not accepted:
            continue
        res, node = _subject_from_outcome(coll, out, parent, joined=nodes[s].joined)
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
    edge: EdgeTask,
    max_candidates: int,
    executor: Executor | None,
    progress: ProgressCallback | None,
) -> None:
    """Give every subject the tree could not take its best registration, as a leaf.

    When the tree stops growing, each waiting subject is registered from the root and
    from its most similar members not yet tried (up to `max_candidates`); with the
    registrations rejected while the tree grew, the one with the lowest e is kept. All
    candidates register the same subject, so their e values compare like with like; on
    26 leaves with ground truth (glyph chains, Chui fish and Chinese) the lowest e gave a
    lower correspondence error than preferring unfolded registrations by confidence in
    every family (bench/RESULTS.md). A warp that folds locally is kept when its e is the
    lowest (a leaf is never a parent, so the fold does not spread), reporting confidence
    0. Two kinds of subject e cannot compare registrations of (bench/RESULTS.md 7.59,
    7.60; ``quality["leaf_compared_by"]``: "e", "root" or "subject"):

    - with scattered points without counterpart (outliers): e falls most where the model
      is pulled over them; the root's own registration is kept ("root");
    - part of the model (occluded, cut off: the root's registration leaves part of the
      model without counterpart, and the subject lies on the model,
      :func:`~registration._error.part_of_model`): e falls most where the whole model is
      squeezed onto the part; the registration that covers the subject's points closest
      is kept (`_subject_half`, as the poses of one task are compared; "subject"), and
      the polish, whose every stage is kept by e, is not run on it.

    The subject is attached as a leaf: never a parent, its confidence and the reason
    it was not accepted reported. It stays unattached only when no registration could be
    run.
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
            tasks.append(edge(m, s, nodes[m].layer + 1, nodes[m].q))
    for out in _run_tasks(tasks, executor, progress, "leaves"):
        rejected.setdefault(out.subject, []).append(out)
    for s in sorted(waiting):
        pool = rejected.get(s, [])
        usable = [o for o in pool if o.min_jacobian > 0]
        r = results[s]
        if not pool:
            r.reason = "unattached: no registration could be tried"
            continue
        # the lowest e: every candidate registers the same subject, so e compares like
        # with like; a local fold does not disqualify (a leaf is never a parent)
        best = _lowest_error(pool, key=lambda o: (o.error, -nodes[o.member].confidence))
        chosen_by = f"the lowest e of {len(pool)} registrations"
        compared_by = "e"
        direct = [o for o in pool if o.member == coll.root]
        if _scattered(best) and direct:
            # e cannot compare registrations onto scattered points (it falls most where
            # the model is pulled over them): the fewest links, the root's own
            best = _lowest_error(direct)
            chosen_by, compared_by = "the root's own registration (scattered points)", "root"
        elif direct and part_of_model(_lowest_error(direct).warped, coll.normed[s],
                                      coll.spacing2[s]):
            # the subject is part of the model: e falls most where the whole model is
            # squeezed onto the part, so the registrations are compared by how closely
            # each covers the subject's points, as the poses of one task are (`_pose_term`)
            term = _subject_half(coll.normed[s])
            best = _lowest_error(pool, key=lambda o: (term(o), o.error))
            chosen_by = (f"of {len(pool)} registrations, the one closest to every point of "
                         "the subject (it is part of the model: the root's registration "
                         "leaves part of the model without counterpart)")
            compared_by = "subject"
        parent = nodes[best.member]
        res, _ = _subject_from_outcome(coll, best, parent, joined=parent.joined, leaf=True)
        why = next((a.reason for a in reversed(r.attempts) if a.member == best.member), None)
        if not best.min_jacobian > 0:
            why = (f"its warp folds the model locally (min Jacobian determinant "
                   f"{best.min_jacobian:.3g}): confidence 0; {len(usable)} of the {len(pool)} "
                   "registrations tried do not fold")
        res.attempts = r.attempts
        res.quality = {**(res.quality or {}), "leaf_compared_by": compared_by}
        res.reason = (
            f"low-confidence leaf: {chosen_by}, from "
            f"{coll.names[best.member]}; not accepted into the tree"
            + (f" ({why})" if why else " (the tree stopped growing before reaching it)")
        )
        results[s] = res

"""The tree's threshold rules: which pairs are similar, the automatic error threshold and
its sampling floor, and the one acceptance rule for a registration."""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._error import SCATTER_MIN
from .._similarity import Similarity
from ._tasks import SPACING_FACTOR, _RegOutcome

FloatArray = NDArray[np.float64]

# Automatic thresholds (see `_SimilarityRule` and `_auto_error_threshold`).
CAPTURE_D = 0.01
SIMILAR_NEIGHBOURS = 4
ERROR_FACTOR = 3.0
# A round's registration from another member whose e is above this many times the lower
# quartile of the first round's e (the base of ERROR_FACTOR; and above the subject's
# sampling floor) is registered again from the root, where any turn may be tried
# (`_passes._again_from_root`). An edge that missed the turn between a member and a
# subject lies at 2-3x (書 in a serif font turned at random: 0.0069-0.0085 against
# 0.0024-0.0045 for right ones, the quartile 0.0031), under the error threshold. Right
# edges lie there too, on collections of large differences (MPEG-7: 7 of 1037 growth
# registrations tried again, none taken) and on glyphs turned apart (書 in Noto Sans: right
# ones up to 1.6x, wrong ones from 1.6x; 36 of 434 tried again, 1 taken): the root,
# bridging the whole difference, then rarely reaches the 0.7x margin (the default bench:
# 206 of 208 runs identical; bench/RESULTS.md 7.50).
AGAIN_E_FACTOR = 2.0
# A stalled tree opens bridges (`_SimilarityRule.bridge`) only while it has run fewer than
# this many registrations per subject in all: a tree as the paper builds it runs about 2
# (163 for the 72 subjects of the 永 edge glyphs), and shapes no member registers well
# (a blot from a bad scan) must not cost a CPD from every member each.
BRIDGE_TASKS_PER_SUBJECT = 8


# A registration is accepted into the tree only with at least this confidence (the
# calibrated probability that its correspondences are right; `_quality`). Measured in
# bench/calibrate_thresholds.py: 5.1% of the registrations scored below 0.2 were good
# (355 of 3140, mostly turned, mirrored and slid ones that e alone accepts), 31% of those
# scored 0.2-0.5.
MIN_CONFIDENCE = 0.2
# Refinement moves a subject when the new path confidence is higher by more than this, or
# within it and with a lower e.
REFINE_TIE = 0.02
# Refinement moves a subject to a later member only when it is clearly more similar to the
# subject than its parent, D at most this fraction of the parent's (the margin the polish's
# finer stages must earn on e), or when the new registration is in another pose
# (`_passes.REFINE_APART`). The move adds a link, whose error the subject inherits; a
# member barely more similar leaves CPD about the same deformation to bridge. Among prints
# of one type (each an independent small warp from the root) the sibling nearest by D is
# a pick by noise: 50 of the 57 moves on the bench's one-type family had D at 0.8-1.0x
# the root's, and their correspondences went 1.3-1.4x worse; on the chain families the
# moves above 0.8x were no better than staying. On subjects turned at random, two such
# moves had put a subject in a wrong pose right (bench/RESULTS.md 7.54).
REFINE_MAX_D_RATIO = 0.8


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
      and is registered from it, which is the point of the tree;
    - every subject can be reached from the root through similar pairs: a collection of
      tight groups (an archive with several impressions of each design) has a k-nearest
      graph that falls apart into its groups, and the tree would never leave the root's.
      A subject the rule's graph does not reach from the root has its ``into`` limit
      raised to its bottleneck distance from the root (:func:`_bridge_limits`): the
      smallest value that gives it a path of similar pairs, so the nearest pairs between
      groups count as similar and nothing else changes. A collection whose graph is
      already connected keeps its rule exactly. When the dynamic tree stalls with
      subjects waiting (its bridges rejected), :meth:`bridge` opens the next nearest
      untried pairs the same way, from the tree's members.
    """

    explicit: float | None
    into: dict[int, float]  # subject -> D from its k-th nearest shape, or its bridge limit
    out_of: dict[int, float]  # member -> D to its k-th nearest shape
    bridged: dict[int, float] = field(default_factory=dict)  # subject -> its raised limit

    @classmethod
    def build(cls, sim: Similarity, explicit: float | None, root: int = 0) -> _SimilarityRule:
        if explicit is not None:
            return cls(explicit=explicit, into={}, out_of={})
        n = sim.D.shape[0]
        off = ~np.eye(n, dtype=bool)

        def kth(values: FloatArray) -> float:
            v = np.sort(values[np.isfinite(values)])
            return float(v[min(SIMILAR_NEIGHBOURS, v.size) - 1]) if v.size else 0.0

        into = np.array([kth(sim.D[:, s][off[:, s]]) for s in range(n)])
        out_of = np.array([kth(sim.D[m, :][off[m, :]]) for m in range(n)])
        bridged = _bridge_limits(sim.D, into, out_of, [root])
        for s, b in bridged.items():
            into[s] = b
        return cls(
            explicit=None,
            into={s: float(into[s]) for s in range(n)},
            out_of={m: float(out_of[m]) for m in range(n)},
            bridged=bridged,
        )

    def bridge(self, sim: Similarity, members: Iterable[int], waiting: Iterable[int],
               tried: Iterable[tuple[int, int]]) -> int:
        """When the dynamic tree stalls (its bridge registrations rejected): raise the
        limit of the waiting subjects to their bottleneck D from the tree's members over
        the pairs not yet tried, so the next nearest pairs into them count as similar.
        Returns how many limits were raised (0: nothing left to try, or explicit)."""
        if self.explicit is not None:
            return 0
        n = sim.D.shape[0]
        into = np.array([self.into[k] for k in range(n)])
        out_of = np.array([self.out_of[k] for k in range(n)])
        raised = _bridge_limits(sim.D, into, out_of, list(members), tried)
        count = 0
        for s in waiting:
            if s in raised and raised[s] > self.into[s]:
                self.into[s] = self.bridged[s] = raised[s]
                count += 1
        return count

    def limit(self, member: int, subject: int) -> float:
        if self.explicit is not None:
            return self.explicit
        return max(CAPTURE_D, self.into[subject], self.out_of[member])

    def similar(self, sim: Similarity, member: int, subject: int) -> bool:
        d = sim.D[member, subject]
        return bool(np.isfinite(d) and d <= self.limit(member, subject))


def _similarity_report(rule: _SimilarityRule) -> dict[str, Any]:
    values = list(rule.into.values())
    report: dict[str, Any] = {
        "similarity": rule.explicit if rule.explicit is not None
        else max(CAPTURE_D, float(np.median(values))) if values else None,
        "similarity_rule": "explicit" if rule.explicit is not None
        else f"auto, per pair: max({CAPTURE_D}, D from the subject's {SIMILAR_NEIGHBOURS}th "
        f"nearest shape, D to the member's {SIMILAR_NEIGHBOURS}th nearest shape); a subject "
        "no path of such pairs reaches from the root takes instead its bottleneck D from "
        "the root, and when the tree stalls from its members over the pairs not yet tried "
        "('bridged': how many subjects); 'similarity' is the median over subjects",
    }
    if rule.explicit is None:
        report["bridged"] = len(rule.bridged)
    return report


def _bridge_limits(
    D: FloatArray, into: FloatArray, out_of: FloatArray, sources: Sequence[int],
    tried: Iterable[tuple[int, int]] = (),
) -> dict[int, float]:
    """The raised ``into`` limit of each shape the rule leaves unreachable from `sources`.

    Edges are the computed pairs ``member -> subject`` (``D[member, subject]`` finite, in
    the direction the tree uses them) not in `tried`; a pair the rule already counts
    similar costs 0, any other its D. A shape's bridge limit is its bottleneck (minimax)
    distance from the sources over these edges: the smallest largest-cost along a path.
    Raising the limit of every unreachable shape to it makes every shape with a finite
    path reachable (on the minimax path each shape's predecessor edge costs at most its
    limit), and changes nothing where the rule's graph already reaches everything.
    """
    n = D.shape[0]
    finite = np.isfinite(D)
    np.fill_diagonal(finite, False)
    for m, s in tried:
        finite[m, s] = False
    limit = np.maximum(CAPTURE_D, np.maximum(into[None, :], out_of[:, None]))
    d = np.where(finite, D, np.inf)
    cost = np.where(d <= limit, 0.0, d)
    best = np.full(n, np.inf)
    done = np.zeros(n, dtype=bool)
    best[list(sources)] = 0.0
    heap = [(0.0, int(k)) for k in sources]
    while heap:
        b, m = heapq.heappop(heap)
        if done[m]:
            continue
        done[m] = True
        via = np.maximum(b, cost[m])
        better = np.flatnonzero((via < best) & ~done)
        best[better] = via[better]
        for k in better:
            heapq.heappush(heap, (float(via[k]), int(k)))
    raise_to = np.maximum(into, best)  # never below the k-nearest limit
    return {int(k): float(raise_to[k]) for k in np.flatnonzero((best > 0) & np.isfinite(best))}


def _auto_error_threshold(lower_quartile: float) -> float:
    """``ERROR_FACTOR`` times `lower_quartile`, the lower quartile of the second layer's
    e (:func:`_lower_quartile_error` of the first round's registrations).

    Those are registrations of the root to the subjects similar to it. The best of them
    measure what "registered" means for this collection (its point density, noise and
    genuine shape variation); failed registrations sit an order of magnitude above
    (generated families: 2e-4 to 5e-4 against about 5e-3). The lower quartile rather
    than the median, because every shape's few nearest shapes count as similar, so the
    root's similar subjects can include far ones that fail. Applied per subject together
    with a floor from the subject's own sampling (:func:`_spacing_floor`).
    """
    return ERROR_FACTOR * lower_quartile


def _lower_quartile_error(outcomes: Sequence[_RegOutcome]) -> float:
    """The lower quartile of the finite e of `outcomes` (infinite when there is none)."""
    errs = [o.error for o in outcomes if math.isfinite(o.error)]
    if not errs:
        return math.inf
    return float(np.percentile(errs, 25))


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


def _check_threshold(name: str, value: float | None) -> None:
    if value is not None and not (value > 0 and math.isfinite(value)):
        raise ValueError(f"{name} must be a positive finite number or None; got {value}")


def _error_limit(tau_err: float, explicit: bool, floor: float) -> float:
    """The e a subject's registration must stay below: the explicit threshold, or the
    automatic one raised to the subject's sampling floor."""
    return tau_err if explicit else max(tau_err, floor)


def _scattered(out: _RegOutcome) -> bool:
    """Whether the subject's points without counterpart on the registration `out` are
    scattered (:func:`~registration._error.scattered_extra` above
    :data:`~registration._error.SCATTER_MIN`: outliers, specks), so that its e, which
    falls most where the model is pulled over them, does not tell a good registration
    from a bad one."""
    return out.scattered is not None and out.scattered > SCATTER_MIN


def _rejection(out: _RegOutcome, limit: float, fold_check: bool,
               part: bool = False) -> str | None:
    """Why the tree's rule refuses a registration (None: it accepts it): a fold, e at or
    above `limit`, a confidence below ``MIN_CONFIDENCE``, scattered points on the
    subject without counterpart (`_scattered`), or a subject that is part of the model
    (`part`: the root's registration of it reads
    :func:`~registration._error.part_of_model`), checked in that order. Such subjects
    are so attached as leaves, never parents: each child of a subject with outliers
    would inherit a registration pulled over them (bench/RESULTS.md 7.59), and e, which
    counts the model's points without counterpart, accepts from a member the
    registration that squeezes the whole model onto the part (7.60)."""
    if fold_check and not out.min_jacobian > 0:
        return "folded (Jacobian determinant <= 0)"
    if not out.error < limit:
        return f"e={out.error:.4g} >= error threshold {limit:.4g}"
    if not out.quality.confidence >= MIN_CONFIDENCE:
        return f"confidence {out.quality.confidence:.2f} < {MIN_CONFIDENCE}"
    if _scattered(out):
        assert out.scattered is not None
        return (f"the subject has points scattered off the registered model (outliers; "
                f"scatter {out.scattered:.2f} > {SCATTER_MIN:g}), which its e pulls the "
                "model over")
    if part:
        return ("the subject is part of the model (occluded or cut off: the root's "
                "registration leaves a piece of the model without counterpart), which e "
                "would squeeze the whole model onto")
    return None

"""A collection prepared for registration (normalised shapes, names, spacing), the tree's
nodes, and the similarity store each method starts from."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._candidates import candidate_pairs
from .._executor import Executor
from .._points import Normalization, mean_spacing2, normalise
from .._pose import PoseSpec
from .._result import Attempt, SubjectResult
from .._similarity import ProgressCallback, Similarity
from .._transform import ChainTransform
from ._rules import _SimilarityRule
from ._tasks import _RegOutcome

FloatArray = NDArray[np.float64]

MAX_EXHAUSTIVE_SHAPES = 64
DEFAULT_CANDIDATES = 12


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
                   spacing2=[mean_spacing2(p) for p in normed])

    @property
    def n(self) -> int:
        return len(self.normed)

    def root_chain(self) -> ChainTransform:
        r = self.root
        return ChainTransform(source=self.norms[r], target=self.norms[r], steps=(), path=(r,))

    def root_node(self) -> _Node:
        return _Node(q=self.normed[self.root], chain=self.root_chain(), layer=1)


@dataclass
class _Node:
    q: FloatArray  # root model warped onto this member (normalised coords of the member)
    chain: ChainTransform
    layer: int  # its depth in the tree: the root 1, a child one more than its parent
    confidence: float = 1.0  # the weakest registration on the path from the root
    # the round of the tree's growth in which it joined (the root 1): the layer it would
    # have if every round grew from the one before, which a stalled tree's bridges do not
    joined: int = 1


def _attempt(out: _RegOutcome, limit: float, reason: str, accepted: bool = False) -> Attempt:
    """The record of the registration `out` among a subject's attempts, held to `limit`."""
    return Attempt(member=out.member, layer=out.layer, similarity=out.similarity,
                   error=out.error, limit=limit, min_jacobian=out.min_jacobian,
                   accepted=accepted, reason=reason)


def _subject_from_outcome(
    coll: _Collection, out: _RegOutcome, parent: _Node, *, joined: int, leaf: bool = False,
) -> tuple[SubjectResult, _Node]:
    """The subject registered by `out` from `parent`, and its node (joined in round
    `joined` of the tree's growth): one layer below its parent."""
    s = out.subject
    chain = parent.chain.extended(out.steps, coll.norms[s], s)
    layer = parent.layer + 1
    confidence = min(parent.confidence, out.quality.confidence)
    # the dynamic tree's edges: whether the edge was made symmetric, and why not; which
    # of CPD's starts it kept (annealed or held), with the e each reached
    edge: dict[str, Any] = (
        {"symmetric_edge": out.symmetric, "symmetric_edge_reason": out.symmetric_reason}
        if out.symmetric or out.symmetric_reason else {})
    if out.cpd_start:
        edge.update(edge_start=out.cpd_start, edge_start_errors=out.cpd_start_errors)
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
                 "pose_errors": dict(out.pose_errors), "pose_margin": out.pose_margin,
                 "pose_compared_by": out.pose_compared_by, **edge},
    )
    return res, _Node(q=out.warped, chain=chain, layer=layer, confidence=confidence,
                      joined=joined)


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
    stage: str,
) -> None:
    """Compute D from the newest members to the waiting subjects (lazily: only the pairs
    that can give a subject its next candidate), reported to `progress` as `stage`."""
    if allowed is not None and len(frontier) * len(waiting) > len(allowed):
        # a large collection: its allowed pairs (O(n k)) are fewer than frontier x waiting
        members = set(frontier)
        pairs = sorted(p for p in allowed if p[0] in members and p[1] in waiting)
    else:
        pairs = [(m, s) for m in frontier for s in sorted(waiting)]
        if allowed is not None:
            pairs = [p for p in pairs if p in allowed]
    sim.ensure(pairs, executor=executor, progress=progress, stage=stage)


@dataclass
class _TreeStart:
    """What both tree methods start from: the prepared collection, the similarity store
    with the pairs it may hold, the similarity rule, the root's node and a blank result
    for every subject (the CPD options and the pose rule are the caller's: see
    ``_Run`` in ``_methods``)."""

    coll: _Collection
    sim: Similarity
    allowed: set[tuple[int, int]] | None
    rule: _SimilarityRule
    subjects: list[int]
    nodes: dict[int, _Node]
    results: dict[int, SubjectResult]
    sources: dict[int, list[int]] | None = None  # subject -> the members allowed for it

    def members_for(self, subject: int) -> Iterable[int]:
        """The tree's members whose D to `subject` may be known: all of them, or for a
        large collection only its allowed candidates (O(k) instead of O(n) a subject)."""
        if self.sources is None:
            return self.nodes
        return [m for m in self.sources.get(subject, ()) if m in self.nodes]

    @classmethod
    def prepare(
        cls,
        coll: _Collection,
        similarity_threshold: float | None,
        candidates: int | None,
        pose: PoseSpec,
        executor: Executor | None,
        progress: ProgressCallback | None,
    ) -> _TreeStart:
        root = coll.root
        sim, allowed = _prepare_similarity(
            coll, similarity_threshold, candidates, executor, progress, pose
        )
        subjects = [k for k in range(coll.n) if k != root]
        sources: dict[int, list[int]] | None = None
        if allowed is not None:
            sources = {}
            for m, s in sorted(allowed):
                sources.setdefault(s, []).append(m)
        return cls(
            sources=sources, coll=coll, sim=sim, allowed=allowed,
            rule=_SimilarityRule.build(sim, similarity_threshold, root), subjects=subjects,
            nodes={root: coll.root_node()},
            results={s: SubjectResult(index=s, name=coll.names[s]) for s in subjects},
        )

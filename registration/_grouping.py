"""Which impressions came from the same mould: grouping glyph instances (issue 11).

:func:`group_instances` computes the mould distance of :mod:`._mould_distance` for the pairs
that can matter, cuts a single-linkage tree at a threshold, and checks every group against
its representative so that a chain of near pairs never pulls two moulds together.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

from ._executor import Executor
from ._mould_distance import Impression, impression_descriptor, local_discrepancy
from ._mould_distance import prepare_impression as _prepare
from ._points import normalise
from ._similarity import ProgressCallback, similarity_matrix

FloatArray = NDArray[np.float64]

__all__ = ["GroupingResult", "MouldGroup", "group_instances"]

#: Automatic threshold = NOISE_FACTOR x the median nearest-instance distance, kept within
#: [THRESHOLD_MIN, THRESHOLD_MAX] (units: the shapes' RMS radius). Measured in bench/
#: bench_grouping.py on several settings (see bench/RESULTS.md, section 6).
NOISE_FACTOR = 2.0
THRESHOLD_MIN = 0.06
THRESHOLD_MAX = 0.12
_MAX_ROUNDS = 8


@dataclass(frozen=True)
class MouldGroup:
    """Instances attributed to one mould.

    Attributes
    ----------
    label : int
        The group's number (``GroupingResult.labels`` holds it for every member).
    members : list of int
        Input positions, ascending.
    representative : int
        The medoid: the member with the smallest largest distance to the others.
    spread : float
        Largest distance of a member to the representative.
    """

    label: int
    members: list[int]
    representative: int
    spread: float

    def to_dict(self) -> dict[str, object]:
        return {"label": self.label, "members": list(self.members),
                "representative": self.representative, "spread": self.spread}


@dataclass(frozen=True)
class GroupingResult:
    """Result of :func:`group_instances`.

    Attributes
    ----------
    labels : ndarray of int, shape (n,)
        Group of every input shape, in input order; groups are numbered by decreasing
        size, then by first member.
    groups : list of MouldGroup
        ``groups[g].label == g``.
    confidence : ndarray, shape (n,)
        Silhouette of each instance in [0, 1]: ``(b - a) / max(a, b)`` with ``a`` its
        distance to its group's representative (for the representative, the median
        distance to its members) and ``b`` its distance to the nearest instance of
        another group; 0 for an instance alone in its group (nothing supports it) and
        when ``b <= a``.
    distances : ndarray, shape (n, n)
        Symmetric mould distances (units: RMS radius of the shapes); NaN where a pair was
        not computed (pruned by the descriptor, or never needed).
    threshold : float
        The cut: instances farther apart than this are never in one group.
    threshold_source : {"given", "automatic"}
    noise_level : float
        Median over instances of the distance to the nearest other instance.
    linkage : ndarray, shape (n - 1, 4)
        Single-linkage tree (scipy's format) over the computed distances, for a
        dendrogram; pairs not computed count as ``uncomputed_distance``.
    uncomputed_distance : float
    pairs_computed : int
        Registrations run.
    dropped_points : list of int
        Points removed from each shape as ink specks.
    """

    labels: NDArray[np.intp]
    groups: list[MouldGroup]
    confidence: FloatArray
    distances: FloatArray
    threshold: float
    threshold_source: str
    noise_level: float
    linkage: FloatArray
    uncomputed_distance: float
    pairs_computed: int
    dropped_points: list[int] = field(default_factory=list)

    @property
    def n_groups(self) -> int:
        return len(self.groups)

    def __repr__(self) -> str:
        single = sum(len(g.members) == 1 for g in self.groups)
        return (f"GroupingResult({len(self.labels)} instances, {self.n_groups} groups, "
                f"{single} singletons, threshold={self.threshold:.4g} "
                f"({self.threshold_source}))")

    def to_dict(self) -> dict[str, object]:
        """A JSON-serialisable summary (NaN distances as None)."""
        return {
            "labels": [int(v) for v in self.labels],
            "groups": [g.to_dict() for g in self.groups],
            "confidence": [float(v) for v in self.confidence],
            "distances": [[None if np.isnan(v) else float(v) for v in row]
                          for row in self.distances],
            "threshold": self.threshold,
            "threshold_source": self.threshold_source,
            "noise_level": self.noise_level,
            "linkage": [[float(v) for v in row] for row in self.linkage],
            "uncomputed_distance": self.uncomputed_distance,
            "pairs_computed": self.pairs_computed,
            "dropped_points": list(self.dropped_points),
        }


class _Distances:
    """The mould distance, computed lazily and symmetrically for the pairs asked for."""

    def __init__(self, imps: list[Impression], pose: str, max_rotation: float | None,
                 executor: Executor | None, progress: ProgressCallback | None) -> None:
        self.imps = imps
        n = len(imps)
        self.D = np.full((n, n), np.nan)
        np.fill_diagonal(self.D, 0.0)
        self.pose, self.max_rotation = pose, max_rotation
        self.executor, self.progress = executor, progress
        self.computed = 0
        # ICP runs on the coarse subsets, normalised again by similarity_matrix: keep the
        # maps between those frames and the full shapes' frames.
        self.frames = [normalise(imp.coarse)[1] for imp in imps]

    def ensure(self, pairs: Sequence[tuple[int, int]], stage: str) -> None:
        todo = sorted({(min(i, j), max(i, j)) for i, j in pairs
                       if i != j and np.isnan(self.D[i, j])})
        if not todo:
            return
        sim = similarity_matrix(
            [imp.coarse for imp in self.imps], pairs=todo, pose=self.pose,
            max_rotation=self.max_rotation, executor=self.executor,
            progress=(None if self.progress is None
                      else lambda _s, d, t: self.progress(stage, d, t)),  # type: ignore[misc]
        )
        for i, j in todo:
            fi, fj = self.frames[i], self.frames[j]
            # y = s_j (A (x - c_i) / s_i + t) + c_j  on the full normalised shapes
            A = sim.A[i, j] * (fj.scale / fi.scale)
            t = fj.scale * sim.t[i, j] + np.asarray(fj.center) - A @ np.asarray(fi.center)
            d = local_discrepancy(self.imps[i], self.imps[j], A, t)
            self.D[i, j] = self.D[j, i] = d
        self.computed += len(todo)


def _check_options(shapes: Sequence[ArrayLike], threshold: float | None, neighbours: int,
                   max_rotation: float | None) -> None:
    if len(shapes) == 0:
        raise ValueError("shapes is empty: need at least one instance to group")
    if threshold is not None and not (
            isinstance(threshold, int | float) and np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number (units: RMS radius); "
                         f"got {threshold!r}")
    if isinstance(neighbours, bool) or not isinstance(neighbours, int | np.integer) \
            or neighbours < 1:
        raise ValueError(f"neighbours must be an integer >= 1; got {neighbours!r}")
    if max_rotation is not None and not (
            isinstance(max_rotation, int | float) and 0 < max_rotation <= 180):
        raise ValueError(f"max_rotation must be in (0, 180] degrees; got {max_rotation!r}")


def group_instances(
    shapes: Sequence[ArrayLike],
    *,
    threshold: float | None = None,
    neighbours: int = 6,
    max_rotation: float | None = None,
    executor: Executor | None = None,
    progress: ProgressCallback | None = None,
) -> GroupingResult:
    """Group instances of one character by the mould (type, block) that printed them.

    Two instances are from one mould when, after an affine map, no stretch of either
    outline sits farther than `threshold` from the other (see
    :mod:`registration._mould_distance`): printing noise moves outlines a little
    everywhere, another mould moves them a lot somewhere.

    Parameters
    ----------
    shapes : sequence of array_like, shape (n_i, 2)
        The instances' points (contours, edges or skeletons, all of one kind), in any
        coordinates; y may point down. Instances must be upright to within a few degrees
        unless `max_rotation` is given.
    threshold : float, optional
        Largest mould distance within a group, in units of the shapes' RMS radius.
        Default: automatic, ``2 x`` the median distance of an instance to its nearest
        other instance, kept within [0.06, 0.12] (measured, bench/RESULTS.md).
    neighbours : int
        Registrations per instance before the group checks: its nearest instances by a
        cheap density descriptor. Every group is then checked in full against its
        representative, so this bounds cost, not group size.
    max_rotation : float, optional
        Also try rotations up to this many degrees (the affine ICP's "upright" pose);
        default: the pose as given only.
    executor : Executor, optional
        Where the affine ICP runs (see :func:`similarity_matrix`).
    progress : callable(stage, done, total), optional

    Returns
    -------
    GroupingResult

    Raises
    ------
    ValueError
        On an empty collection, an invalid shape (the message names it) or option.
    """
    _check_options(shapes, threshold, neighbours, max_rotation)
    imps = [_prepare(s, name=f"shapes[{k}]") for k, s in enumerate(shapes)]
    n = len(imps)
    pose = "as_given" if max_rotation is None else "upright"
    dist = _Distances(imps, pose, max_rotation, executor, progress)
    if n == 1:
        return _result(dist, np.zeros(1, dtype=np.intp), threshold or THRESHOLD_MIN,
                       "given" if threshold else "automatic", 0.0)
    desc = np.stack([impression_descriptor(imp) for imp in imps])
    dd = ((desc[:, None, :] - desc[None, :, :]) ** 2).sum(axis=2)
    np.fill_diagonal(dd, np.inf)
    k = min(neighbours, n - 1)
    near = np.argsort(dd, axis=1, kind="stable")[:, :k]
    dist.ensure([(i, int(j)) for i in range(n) for j in near[i]], "candidates")
    nearest = np.nanmin(np.where(np.eye(n, dtype=bool), np.nan, dist.D), axis=1)
    noise = float(np.median(nearest))
    if threshold is None:
        thr = float(np.clip(NOISE_FACTOR * noise, THRESHOLD_MIN, THRESHOLD_MAX))
        source = "automatic"
    else:
        thr, source = float(threshold), "given"
    labels = _cut(dist, thr)
    # Confidence needs each instance's nearest instance outside its group.
    for _ in range(_MAX_ROUNDS):
        ask = []
        for i in range(n):
            outside = np.flatnonzero(labels != labels[i])
            if len(outside) and np.isnan(dist.D[i, outside]).all():
                ask.append((i, int(outside[np.argmin(dd[i, outside])])))
        if not ask:
            break
        dist.ensure(ask, "separation")
        new = _cut(dist, thr)
        if np.array_equal(new, labels):
            break
        labels = new
    return _result(dist, labels, thr, source, noise)


def _single_linkage(D: FloatArray) -> tuple[FloatArray, float]:
    known = D[~np.isnan(D)]
    far = float(2.0 * max(float(known.max()) if known.size else 1.0, 1.0))
    W = np.where(np.isnan(D), far, D)
    np.fill_diagonal(W, 0.0)
    return linkage(squareform(W, checks=False), method="single"), far


def _cut(dist: _Distances, thr: float) -> NDArray[np.intp]:
    """Single-linkage groups at `thr`, each checked in full against its medoid: members
    farther than `thr` from it are grouped again among themselves."""
    n = len(dist.imps)
    labels = np.full(n, -1, dtype=np.intp)
    pending = [np.arange(n)]
    next_label = 0
    for _ in range(4 * n):
        if not pending:
            break
        idx = pending.pop()
        if len(idx) == 1:
            labels[idx] = next_label
            next_label += 1
            continue
        sub = dist.D[np.ix_(idx, idx)]
        Z, _ = _single_linkage(sub)
        for c in np.unique(fcluster(Z, thr, criterion="distance")):
            members = idx[fcluster(Z, thr, criterion="distance") == c]
            if len(members) == 1:
                labels[members] = next_label
                next_label += 1
                continue
            med = _medoid(dist.D, members)
            dist.ensure([(med, int(j)) for j in members], "group check")
            close = dist.D[med, members] <= thr
            labels[members[close]] = next_label
            next_label += 1
            if (~close).any():
                pending.append(members[~close])
    return labels


def _medoid(D: FloatArray, members: NDArray[np.intp]) -> int:
    sub = D[np.ix_(members, members)]
    worst = np.where(np.isnan(sub), np.inf, sub).max(axis=1)
    typical = np.nanmedian(np.where(np.eye(len(members), dtype=bool), np.nan, sub), axis=1)
    # fully measured members first, then the smallest largest distance, then median
    order = np.lexsort((members, np.nan_to_num(typical, nan=np.inf), worst))
    return int(members[order[0]])


def _result(dist: _Distances, raw: NDArray[np.intp], thr: float, source: str,
            noise: float) -> GroupingResult:
    n = len(raw)
    D = dist.D
    blocks = [np.flatnonzero(raw == c) for c in np.unique(raw)]
    blocks.sort(key=lambda m: (-len(m), int(m[0])))
    labels = np.empty(n, dtype=np.intp)
    groups: list[MouldGroup] = []
    conf = np.zeros(n)
    for g, members in enumerate(blocks):
        labels[members] = g
        rep = _medoid(D, members) if len(members) > 1 else int(members[0])
        spread = float(np.nanmax(D[rep, members])) if len(members) > 1 else 0.0
        groups.append(MouldGroup(label=g, members=[int(m) for m in members],
                                 representative=rep, spread=spread))
    for grp in groups:
        members = np.asarray(grp.members)
        if len(members) == 1:
            continue
        others = np.setdiff1d(np.arange(n), members)
        for i in members:
            own = D[grp.representative, members[members != i]] if i == grp.representative \
                else D[i, [grp.representative]]
            a = float(np.nanmedian(own))
            b = float(np.nanmin(D[i, others])) if len(others) and \
                not np.isnan(D[i, others]).all() else np.inf
            conf[i] = 0.0 if b <= a else (1.0 if not np.isfinite(b) else (b - a) / b)
    if n > 1:
        Z, far = _single_linkage(D)
    else:
        Z, far = np.zeros((0, 4)), 0.0
    return GroupingResult(
        labels=labels, groups=groups, confidence=conf, distances=D.copy(), threshold=thr,
        threshold_source=source, noise_level=noise, linkage=np.asarray(Z, dtype=np.float64),
        uncomputed_distance=far, pairs_computed=dist.computed,
        dropped_points=[imp.dropped for imp in dist.imps])

"""Which impressions came from the same mould: grouping glyph instances (issue 11).

:func:`group_instances` computes the outline-field distance of :mod:`._outline_field`
(every instance aligned to the collection's median field, near pairs once more to each
other) and cuts an average-linkage tree at a threshold: average linkage, unlike single
linkage, does not let a chain of near pairs pull two moulds together. An instance left
alone by the cut then joins its nearest group of three or more when it is within 1.5 x
the threshold of it on average: a printing accident (a thin tip eroded, a narrow gap
closed) hits one print, a different mould every print it made, so a lone print far from
a group is more likely a damaged print of it than a mould of its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

from ._executor import Executor, owned_executor
from ._mould_distance import prepare_impression as _prepare
from ._outline_field import (
    INK_WEIGHT,
    align_fields,
    common_frame,
    field_distance,
    grid_centres,
    local_difference,
    outline_field,
    pair_distances,
    screen,
    warp,
)
from ._similarity import ProgressCallback

FloatArray = NDArray[np.float64]

__all__ = ["GroupingResult", "InstanceComparison", "MouldGroup", "compare_instances",
           "group_instances"]

#: Automatic threshold = NOISE_FACTOR x the median nearest-instance distance, kept within
#: [THRESHOLD_MIN, THRESHOLD_MAX] (units: the shapes' RMS radius). Measured in bench/
#: bench_grouping.py on several settings (see bench/RESULTS.md, sections 6.1 and 6.2).
NOISE_FACTOR = 2.0
THRESHOLD_MIN = 0.04
THRESHOLD_MAX = 0.15
#: A lone instance (a group of one at the cut) joins the group it is nearest to on average
#: when that group has at least ATTACH_MIN_SIZE members and the mean distance is at most
#: ATTACH_FACTOR x the threshold: a printing accident (an eroded tip, a closed gap) hits
#: one print, while another mould shows in all of its prints (bench/RESULTS.md 6.2).
ATTACH_FACTOR = 1.5
ATTACH_MIN_SIZE = 3
_CHUNK = 32


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
        The medoid: the member with the smallest mean distance to the others.
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
        Silhouette of each instance in [0, 1]: ``(b - a) / b`` with ``a`` its mean
        distance to the other members of its group and ``b`` the smallest mean distance
        to the members of another group; 0 for an instance alone in its group (nothing
        supports it) and when ``b <= a``.
    distances : ndarray, shape (n, n)
        Symmetric mould distances (units: RMS radius of the shapes); pairs that were not
        aligned to each other (far by the screen) hold the screen's estimate.
    threshold : float
        The cut of the average-linkage tree: two groups whose members are farther apart
        than this on average are not merged (but an instance alone at the cut joins its
        nearest group of three or more within ``1.5 x`` this on average).
    threshold_source : {"given", "automatic"}
    noise_level : float
        Median over instances of the distance to the nearest other instance.
    linkage : ndarray, shape (n - 1, 4)
        Average-linkage tree (scipy's format) over `distances`, for a dendrogram.
    pairs_computed : int
        Pairs aligned to each other.
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
        """A JSON-serialisable summary."""
        return {
            "labels": [int(v) for v in self.labels],
            "groups": [g.to_dict() for g in self.groups],
            "confidence": [float(v) for v in self.confidence],
            "distances": [[float(v) for v in row] for row in self.distances],
            "threshold": self.threshold,
            "threshold_source": self.threshold_source,
            "noise_level": self.noise_level,
            "linkage": [[float(v) for v in row] for row in self.linkage],
            "pairs_computed": self.pairs_computed,
            "dropped_points": list(self.dropped_points),
        }


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


def _refine_chunk(chunk: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]]
                  ) -> list[float]:
    """Each pair (own field a, own field b, a and b in the common frame): the smaller of
    the distance in the common frame and after aligning a's own field onto b's (the
    common frame can distort an instance: the median of unlike shapes is a blob)."""
    own = pair_distances([f for fs in chunk for f in fs[:2]],
                         [(2 * k, 2 * k + 1) for k in range(len(chunk))])
    return [min(float(d), field_distance(fs[2], fs[3])) for d, fs in zip(own, chunk, strict=True)]


def group_instances(
    shapes: Sequence[ArrayLike],
    *,
    threshold: float | None = None,
    neighbours: int = 10,
    max_rotation: float | None = None,
    executor: Executor | None = None,
    progress: ProgressCallback | None = None,
) -> GroupingResult:
    """Group instances of one character by the mould (type, block) that printed them.

    Two instances are from one mould when their outlines, aligned by an affine map and
    with a uniform ink spread or starvation counted once rather than in every place,
    differ nowhere by much (see :mod:`registration._outline_field`): printing noise
    moves outlines a little everywhere, another mould moves them a lot somewhere.
    Groups: average-linkage hierarchical clustering cut at `threshold`; then every
    instance alone in its group joins the group of at least three members it is nearest
    to on average, if within ``1.5 x threshold`` (a damaged print rather than a mould of
    its own).

    Parameters
    ----------
    shapes : sequence of array_like, shape (n_i, 2)
        The instances' points (outlines from scans, preferably: the inside of the ink is
        found from them), in any coordinates; y may point down. Instances must be upright
        to within a few degrees unless `max_rotation` is given.
    threshold : float, optional
        Cut of the average-linkage tree, in units of the shapes' RMS radius. Default:
        automatic, ``2 x`` the median distance of an instance to its nearest other
        instance, kept within [0.04, 0.15] (measured, bench/RESULTS.md section 6.2).
    neighbours : int
        Pairs aligned to each other per instance: its nearest by a cheap field
        difference, in the common frame and on its own field (up to twice this many);
        the distances of farther pairs are estimated from that difference. Bounds cost,
        not group size.
    max_rotation : float, optional
        Also try starting rotations up to this many degrees (10 degree steps) when
        aligning every instance to the collection's median; default: as given only.
    executor : Executor, optional
        Where the pairwise alignments run (default: serial for few pairs, else a local
        process pool closed afterwards).
    progress : callable(stage, done, total), optional
        Stages, in order, each counting from 0 to its total: ``"fields"`` (instances),
        ``"alignment"`` (alignments to the median field, two rounds of every instance),
        ``"pairs"`` (pairs aligned to each other).

    Returns
    -------
    GroupingResult

    Raises
    ------
    ValueError
        On an empty collection, an invalid shape (the message names it) or option.
    """
    _check_options(shapes, threshold, neighbours, max_rotation)
    n = len(shapes)
    report = progress or (lambda _s, _d, _t: None)
    # each instance prepared (normalised, despeckled) and its field made in one step of
    # "fields": the preparation is a third of the stage's time (bench/RESULTS.md 5.3)
    report("fields", 0, n)
    fields, dropped = [], []
    for k, s in enumerate(shapes):
        imp = _prepare(s, name=f"shapes[{k}]")
        fields.append(outline_field(imp.points).field)
        dropped.append(imp.dropped)
        report("fields", k + 1, n)
    if n == 1:
        return _result(np.zeros((1, 1)), np.zeros(1, dtype=np.intp),
                       threshold or THRESHOLD_MIN, "given" if threshold else "automatic",
                       0.0, 0, dropped)
    aligned = common_frame(fields, max_rotation=max_rotation,
                           progress=lambda d, t: report("alignment", d, t))
    D, pairs = _distances(fields, aligned, neighbours, executor, report)
    noise = float(np.median(np.where(np.eye(n, dtype=bool), np.inf, D).min(axis=1)))
    if threshold is None:
        thr = float(np.clip(NOISE_FACTOR * noise, THRESHOLD_MIN, THRESHOLD_MAX))
        source = "automatic"
    else:
        thr, source = float(threshold), "given"
    Z = linkage(squareform(D, checks=False), method="average")
    labels = _attach_lone(D, np.asarray(fcluster(Z, thr, criterion="distance") - 1,
                                        dtype=np.intp), ATTACH_FACTOR * thr)
    return _result(D, labels, thr, source, noise, pairs, dropped, Z)


def _distances(fields: list[FloatArray], aligned: list[FloatArray], neighbours: int,
               executor: Executor | None, report: ProgressCallback
               ) -> tuple[FloatArray, int]:
    """All-pairs mould distances: each instance's nearest by either screen (in the common
    frame and on its own field; the common frame can distort an instance unlike the
    median) measured, the others estimated from the screen; and the pairs measured."""
    n = len(fields)
    S_common, S_own = screen(aligned), screen(fields)
    pairs_set: set[tuple[int, int]] = set()
    k = min(neighbours, n - 1)
    for S in (S_common, S_own):
        np.fill_diagonal(S, np.inf)
        near = np.argsort(S, axis=1, kind="stable")[:, :k]
        pairs_set |= {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in near[i]}
    S = np.minimum(S_common, S_own)
    pairs = sorted(pairs_set)
    D = np.full((n, n), np.nan)
    np.fill_diagonal(D, 0.0)
    chunks = [pairs[c:c + _CHUNK] for c in range(0, len(pairs), _CHUNK)]
    done = 0
    report("pairs", 0, len(pairs))
    with owned_executor(executor, len(pairs) // _CHUNK * 4) as ex:
        for c, ds in ex.map_unordered(
                _refine_chunk, [[(fields[i], fields[j], aligned[i], aligned[j])
                                 for i, j in ch] for ch in chunks]):
            for (i, j), d in zip(chunks[c], ds, strict=True):
                D[i, j] = D[j, i] = d
            done += len(chunks[c])
            report("pairs", done, len(pairs))
    known = ~np.isnan(D) & ~np.eye(n, dtype=bool)
    # farther pairs: the screen scaled as the measured pairs scale it (they are far)
    ratio = float(np.median(D[known] / np.maximum(S[known], 1e-12)))
    D = np.where(np.isnan(D), ratio * S, D)
    np.fill_diagonal(D, 0.0)
    return (D + D.T) / 2, len(pairs)


def _attach_lone(D: FloatArray, labels: NDArray[np.intp], reach: float) -> NDArray[np.intp]:
    """Every instance alone in its group joins the group of at least ATTACH_MIN_SIZE
    members it is nearest to on average, when that mean distance is within `reach`
    (lone instances do not join each other: two of them are no evidence of a mould)."""
    out = labels.copy()
    counts = np.bincount(labels)
    hosts = np.flatnonzero(counts >= ATTACH_MIN_SIZE)
    if hosts.size == 0:
        return out
    for i in np.flatnonzero(counts[labels] == 1):
        means = np.array([D[i, labels == h].mean() for h in hosts])
        best = int(np.argmin(means))
        if means[best] <= reach:
            out[i] = hosts[best]
    return out


def _medoid(D: FloatArray, members: NDArray[np.intp]) -> int:
    """The member with the smallest mean distance to the others (then the first)."""
    mean = D[np.ix_(members, members)].mean(axis=1)
    return int(members[int(np.argmin(mean))])


def _result(D: FloatArray, labels_raw: NDArray[np.intp], thr: float, source: str,
            noise: float, pairs: int, dropped: list[int],
            Z: FloatArray | None = None) -> GroupingResult:
    n = len(labels_raw)
    blocks = [np.flatnonzero(labels_raw == c) for c in np.unique(labels_raw)]
    blocks.sort(key=lambda m: (-len(m), int(m[0])))
    labels = np.empty(n, dtype=np.intp)
    groups: list[MouldGroup] = []
    for g, members in enumerate(blocks):
        labels[members] = g
        rep = _medoid(D, members) if len(members) > 1 else int(members[0])
        spread = float(np.max(D[rep, members])) if len(members) > 1 else 0.0
        groups.append(MouldGroup(label=g, members=[int(m) for m in members],
                                 representative=rep, spread=spread))
    conf = np.zeros(n)
    for grp in groups:
        members = np.asarray(grp.members)
        if len(members) == 1:
            continue
        for i in members:
            a = float(D[i, members[members != i]].mean())
            b = min((float(D[i, o.members].mean()) for o in groups if o.label != grp.label),
                    default=np.inf)
            conf[i] = 0.0 if b <= a else (1.0 if not np.isfinite(b) else (b - a) / b)
    return GroupingResult(
        labels=labels, groups=groups, confidence=conf, distances=D.copy(), threshold=thr,
        threshold_source=source, noise_level=noise,
        linkage=np.zeros((0, 4)) if Z is None else np.asarray(Z, dtype=np.float64),
        pairs_computed=pairs, dropped_points=dropped)


@dataclass(frozen=True)
class InstanceComparison:
    """Where an instance differs from another (its group's representative, say).

    Attributes
    ----------
    instance, reference : ndarray, shape (n, 2)
        Both point sets normalised (centroid 0, unit RMS radius), the instance mapped onto
        the reference by the fitted affine map.
    difference : ndarray, shape (g, g)
        Local outline difference, the uniform ink shift taken out, on a grid (rows = y)
        in the reference's normalised frame; ``grid`` holds the cell centres along
        either axis.
    grid : ndarray, shape (g,)
    distance : float
        The mould distance of the pair, as :func:`group_instances` measures it.
    ink_offset : float
        The uniform outline shift taken out (positive: the reference's ink is heavier).
    worst : tuple of float
        (x, y) of the largest local difference.
    """

    instance: FloatArray
    reference: FloatArray
    difference: FloatArray
    grid: FloatArray
    distance: float
    ink_offset: float
    worst: tuple[float, float]


def compare_instances(instance: ArrayLike, reference: ArrayLike) -> InstanceComparison:
    """Align `instance` onto `reference` as :func:`group_instances` does and say where their
    outlines differ (for a picture of why two instances are, or are not, one mould).

    Parameters
    ----------
    instance, reference : array_like, shape (n_i, 2)
        The two instances' points (outlines, as for :func:`group_instances`).

    Returns
    -------
    InstanceComparison

    Raises
    ------
    ValueError
        On an invalid shape (named ``instance`` or ``reference``).
    """
    a = _prepare(instance, name="instance")
    b = _prepare(reference, name="reference")
    fa, fb = outline_field(a.points).field, outline_field(b.points).field
    p = align_fields(fa, fb)
    local, c = local_difference(warp(fa, p), fb)
    A, t = p[:4].reshape(2, 2), p[4:]
    # a(A x + t) ~ b(x): a's point y sits at x = A^-1 (y - t) in b's frame
    moved = np.asarray(np.linalg.solve(A, (a.points - t).T).T, dtype=np.float64)
    g = grid_centres()
    iy, ix = np.unravel_index(int(np.argmax(local)), local.shape)
    return InstanceComparison(
        instance=moved, reference=b.points, difference=local, grid=g,
        distance=float(local.max() + abs(c) / INK_WEIGHT), ink_offset=c,
        worst=(float(g[ix]), float(g[iy])))

"""Cut rules for ``group_instances``' distances, compared on the same distances (issue 11).

Used by ``bench_grouping.py --rules``: every rule is a function of the distance matrix alone
(no truth), scored by the adjusted Rand index on the full setting and on subsets with fewer
impressions per mould (the first 2 or 3 of each, or 1-5 drawn per mould): a rule must not
rely on every mould having five prints. Subsets are submatrices of the same distances (the
pairs a run on the subset would measure are measured here too, near enough).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

from registration._grouping import ATTACH_FACTOR, _attach_lone

Rule = Callable[[np.ndarray], np.ndarray]


def noise_level(D: np.ndarray) -> float:
    return float(np.median(np.where(np.eye(len(D), dtype=bool), np.inf, D).min(axis=1)))


def _tree(D: np.ndarray, method: str = "average") -> np.ndarray:
    return np.asarray(linkage(squareform(D, checks=False), method=method))


def cut(factor: float, method: str = "average", attach: bool = False) -> Rule:
    def rule(D: np.ndarray) -> np.ndarray:
        thr = factor * noise_level(D)
        labels = np.asarray(fcluster(_tree(D, method), thr, "distance") - 1, dtype=np.intp)
        return _attach_lone(D, labels, ATTACH_FACTOR * thr) if attach else labels
    return rule


def mad_cut(k: float) -> Rule:
    """Average linkage cut at median + k x 1.4826 MAD of the nearest-instance distances
    (a fitted same-mould noise distribution)."""
    def rule(D: np.ndarray) -> np.ndarray:
        d1 = np.where(np.eye(len(D), dtype=bool), np.inf, D).min(axis=1)
        med = float(np.median(d1))
        thr = med + k * 1.4826 * float(np.median(np.abs(d1 - med)))
        return np.asarray(fcluster(_tree(D), thr, "distance"))
    return rule


def inconsistent(t: float, depth: int = 3) -> Rule:
    def rule(D: np.ndarray) -> np.ndarray:
        return np.asarray(fcluster(_tree(D), t, "inconsistent", depth=depth))
    return rule


def largest_gap(lo: float = 1.5, hi: float = 4.0) -> Rule:
    """Cut in the largest ratio between consecutive merge heights within [lo, hi] x the
    noise level (a gap statistic on the tree)."""
    def rule(D: np.ndarray) -> np.ndarray:
        Z = _tree(D)
        noise = noise_level(D)
        h = np.sort(Z[:, 2])
        h = h[(h >= lo * noise) & (h <= hi * noise)]
        if len(h) < 2:
            return np.asarray(fcluster(Z, 2 * noise, "distance"))
        k = int(np.argmax(np.log(h[1:] / h[:-1])))
        return np.asarray(fcluster(Z, (h[k] + h[k + 1]) / 2, "distance"))
    return rule


def small_joins(lo: float, hi: float, small: int) -> Rule:
    """Merges up to lo x noise; from lo to hi x noise only when one side has fewer than
    `small` members (bottom-up on the average-linkage tree)."""
    def rule(D: np.ndarray) -> np.ndarray:
        n = len(D)
        Z = _tree(D)
        noise = noise_level(D)
        size = [1] * n + [0] * (n - 1)
        ok = [True] * n + [False] * (n - 1)
        for k, (a, b, h, _) in enumerate(Z):
            a, b = int(a), int(b)
            size[n + k] = size[a] + size[b]
            ok[n + k] = ok[a] and ok[b] and (
                h <= lo * noise or (h <= hi * noise and min(size[a], size[b]) < small))
        labels = np.arange(n)
        for k in range(n - 2, -1, -1):  # top down: an accepted node is one group
            if ok[n + k]:
                members = _leaves(Z, n + k, n)
                labels[members] = labels[members].min()
        return labels
    return rule


def _leaves(Z: np.ndarray, node: int, n: int) -> list[int]:
    out, stack = [], [node]
    while stack:
        v = stack.pop()
        if v < n:
            out.append(v)
        else:
            stack += [int(Z[v - n, 0]), int(Z[v - n, 1])]
    return out


RULES: dict[str, Rule] = {
    "average 2x": cut(2.0),
    "average 2.5x (default before)": cut(2.5),
    "average 3x": cut(3.0),
    "average 2x + lone join 3+ (default)": cut(2.0, attach=True),
    "average 2.5x + lone join 3+": cut(2.5, attach=True),
    "complete 2.5x": cut(2.5, "complete"),
    "complete 3x": cut(3.0, "complete"),
    "median + 5 MAD of nearest": mad_cut(5.0),
    "inconsistency 1.5 (depth 3)": inconsistent(1.5),
    "largest gap in [1.5x, 4x]": largest_gap(),
    "tree: 1-2 join to 3x": small_joins(2.0, 3.0, 3),
    "tree: 1 joins to 3x": small_joins(2.0, 3.0, 2),
}


def subsets(truth: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """Index sets: all, the first 2 and 3 impressions of each mould, 1-5 drawn per mould."""
    moulds = np.unique(truth)
    draw = np.random.default_rng(seed).integers(1, 6, len(moulds))
    first = {m: np.flatnonzero(truth == m) for m in moulds}
    return {
        "all": np.arange(len(truth)),
        "2 each": np.concatenate([first[m][:2] for m in moulds]),
        "3 each": np.concatenate([first[m][:3] for m in moulds]),
        "1-5 each": np.concatenate([first[m][:k] for m, k in zip(moulds, draw, strict=True)]),
    }


def rule_table(D: np.ndarray, truth: np.ndarray,
               ari: Callable[[np.ndarray, np.ndarray], float]) -> dict[str, dict[str, float]]:
    """ARI of every rule on every subset: {rule: {subset: ari}}."""
    subs = subsets(truth)
    return {name: {s: ari(rule(D[np.ix_(idx, idx)]), truth[idx]) for s, idx in subs.items()}
            for name, rule in RULES.items()}

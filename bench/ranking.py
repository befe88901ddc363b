"""Rank statistics the benchmarks share: how well a score orders registrations.

Ties count half, as in the Mann-Whitney U statistic: confidences tie (every low-confidence
leaf at 0) and so does coverage (1.0 wherever every subject point is reached), and an AUC
that broke such ties by input order would read the order the rows were gathered in.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import rankdata


def auc(score: np.ndarray, positive: np.ndarray) -> float:
    """The probability that a random positive scores above a random negative, ties half
    (NaN when either class is empty). `positive`: a boolean mask, or 0/1 labels."""
    s = np.asarray(score, dtype=np.float64)
    pos = np.asarray(positive).astype(bool)
    n_pos, n_neg = int(pos.sum()), int((~pos).sum())
    if not n_pos or not n_neg:
        return float("nan")
    ranks = rankdata(s)  # average ranks for ties
    u = ranks[pos].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation (average ranks for ties)."""
    return float(np.corrcoef(rankdata(a), rankdata(b))[0, 1])

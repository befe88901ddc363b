"""The benchmarks' rank statistics (``bench/ranking.py``): the AUC counts ties half.

calibrate_thresholds and bench_groundtruth print AUCs of scores that tie often (every
low-confidence leaf at confidence 0, coverage at 1.0); an AUC that broke ties by input
order read the order the rows were gathered in.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest


@pytest.fixture()
def ranking(bench_module) -> ModuleType:  # bench/ranking.py
    return bench_module("ranking")


def test_auc_counts_ties_half_and_ignores_the_rows_order(ranking) -> None:
    rng = np.random.default_rng(4)
    score = rng.integers(0, 4, 300).astype(float)  # few values: many ties
    positive = rng.random(300) < 0.3
    pos, neg = score[positive], score[~positive]
    pairwise = (pos[:, None] > neg[None, :]).mean() + 0.5 * (pos[:, None] == neg[None, :]).mean()
    assert ranking.auc(score, positive) == pytest.approx(pairwise, abs=1e-12)
    order = rng.permutation(300)
    assert ranking.auc(score[order], positive[order]) == pytest.approx(pairwise, abs=1e-12)
    # 0/1 labels read as the mask; all tied is chance; one class alone has no AUC
    assert ranking.auc(score, positive.astype(int)) == pytest.approx(pairwise, abs=1e-12)
    assert ranking.auc(np.ones(10), np.arange(10) < 4) == 0.5
    assert np.isnan(ranking.auc(score, np.ones(300, dtype=bool)))


def test_auc_and_spearman_at_their_extremes(ranking) -> None:
    score = np.arange(10.0)
    assert ranking.auc(score, score >= 6) == 1.0
    assert ranking.auc(-score, score >= 6) == 0.0
    assert ranking.spearman(score, score**3) == pytest.approx(1.0)
    assert ranking.spearman(score, -score) == pytest.approx(-1.0)

"""error_statistics (registration/_result.py) against hand computations."""

from __future__ import annotations

import pytest

from registration import error_statistics


def test_mean_and_linearly_interpolated_95th_percentile() -> None:
    # 1..20: mean 10.5; the 95th percentile sits at rank 0.95 * 19 = 18.05 (0-based),
    # between 19 and 20: 19 + 0.05 * (20 - 19) = 19.05
    stats = error_statistics([float(v) for v in range(20, 0, -1)])
    assert stats == {"count": 20, "mean": pytest.approx(10.5), "p95": pytest.approx(19.05)}


def test_small_lists() -> None:
    # two values: rank 0.95 -> 0.1 + 0.95 * (0.3 - 0.1) = 0.29
    stats = error_statistics([0.3, 0.1])
    assert stats["count"] == 2
    assert stats["mean"] == pytest.approx(0.2)
    assert stats["p95"] == pytest.approx(0.29)
    one = error_statistics([0.004])
    assert one == {"count": 1, "mean": pytest.approx(0.004), "p95": pytest.approx(0.004)}
    assert isinstance(one["mean"], float) and isinstance(one["p95"], float)


def test_empty_list_has_no_mean() -> None:
    assert error_statistics([]) == {"count": 0, "mean": None, "p95": None}

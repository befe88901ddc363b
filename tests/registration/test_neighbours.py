"""The cell-list pair search of the truncated E-step against a brute-force search."""

from __future__ import annotations

import numpy as np
import pytest

from registration._cpd import _neighbours
from registration._cpd._neighbours import near_pairs


def brute(t: np.ndarray, x: np.ndarray, r: float) -> set[tuple[int, int]]:
    d = np.linalg.norm(t[:, None, :] - x[None, :, :], axis=2)
    i, j = np.nonzero(d <= r)
    return set(zip(i.tolist(), j.tolist(), strict=True))


def contour(k: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = np.sort(rng.uniform(0.0, 2 * np.pi, k))
    rad = 1.0 + 0.3 * np.cos(3 * a)
    return np.column_stack([np.cos(a) * rad, np.sin(a) * rad]) + rng.normal(0, 0.01, (k, 2))


def check(t: np.ndarray, x: np.ndarray, r: float) -> None:
    found = near_pairs(t, x, r)
    assert found is not None and found.dist is not None
    i = found.i
    got = set(zip(i.tolist(), found.j.tolist(), strict=True))
    assert got == brute(t, x, r)
    assert len(got) == len(found.j)  # no pair twice
    assert np.all(np.diff(i) >= 0)  # grouped by centroid, in centroid order
    assert found.counts.sum() == len(found.j)
    np.testing.assert_array_equal(found.xj, x[found.j].T)
    np.testing.assert_allclose(found.dist, np.linalg.norm(t[i] - x[found.j], axis=1),
                               rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("r", [1e-3, 0.02, 0.1, 0.45, 3.0, 50.0])
def test_matches_brute_force_on_contours(r: float) -> None:
    x = contour(700, 1)
    t = contour(500, 2) * 1.05 + 0.03  # partly outside the subject's bounding box
    check(t, x, r)


def test_centroids_far_outside_and_degenerate_subjects() -> None:
    rng = np.random.default_rng(3)
    t = rng.normal(0.0, 5.0, (200, 2))
    check(t, rng.normal(0.0, 1.0, (300, 2)), 0.7)
    check(t, np.zeros((40, 2)), 6.0)  # every subject point in one cell
    check(t, np.column_stack([np.linspace(-3, 3, 90), np.zeros(90)]), 0.5)  # a segment
    check(np.zeros((1, 2)), np.zeros((1, 2)), 1e-9)
    ones = np.ones((3, 2))
    check(np.zeros((0, 2)), ones, 1.0)
    check(ones, np.zeros((0, 2)), 1.0)


def test_points_on_cell_boundaries() -> None:
    # a lattice whose spacing is the cell side (r / 2): points on every cell edge, and
    # centroids exactly r from some of them
    g = np.arange(-5, 6) * 0.05
    x = np.array([(a, b) for a in g for b in g])
    check(x[::3] + 0.0, x, 0.1)
    check(x[::2] + np.array([0.1, 0.0]), x, 0.1)


def test_tiny_radius_keeps_cell_numbers_finite() -> None:
    x = contour(300, 4) * 1e3
    check(x[:50] + 1e-9, x, 1e-8)


def test_cap_stops_the_search(monkeypatch: pytest.MonkeyPatch) -> None:
    x = contour(2000, 5)
    t = contour(2000, 6)
    full = near_pairs(t, x, 0.3, distances=False)
    assert full is not None and full.dist is None
    monkeypatch.setattr(_neighbours, "CANDIDATE_BLOCK", 1000)  # many blocks
    assert near_pairs(t, x, 0.3, cap=len(full.j) - 1) is None
    again = near_pairs(t, x, 0.3, cap=len(full.j), distances=False)
    assert again is not None
    np.testing.assert_array_equal(again.j, full.j)
    np.testing.assert_array_equal(again.counts, full.counts)


@pytest.mark.parametrize("r", [0.0, -1.0, float("nan"), float("inf")])
def test_rejects_a_radius_that_is_not_positive_and_finite(r: float) -> None:
    with pytest.raises(ValueError, match="radius must be positive and finite"):
        near_pairs(np.zeros((2, 2)), np.zeros((2, 2)), r)

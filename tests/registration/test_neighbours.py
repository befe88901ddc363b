"""The cell-list pair search of the truncated E-step against a brute-force search, with
its scan compiled (``_ckernel``) and with numpy's."""

from __future__ import annotations

import os

import numpy as np
import pytest

from registration._cpd import _neighbours, _switch
from registration._cpd._neighbours import near_pairs

COMPILED = _switch.CKERNEL


@pytest.fixture(autouse=True, params=["compiled", "numpy"])
def engine(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    if request.param == "compiled":
        if COMPILED is None:
            if os.environ.get("REGTREE_REQUIRE_CKERNEL") == "1":
                pytest.fail("REGTREE_REQUIRE_CKERNEL=1 but _ckernel is not importable")
            pytest.skip("registration._cpd._ckernel not built")
        monkeypatch.setattr(_switch, "CKERNEL", COMPILED)
    else:
        monkeypatch.setattr(_switch, "CKERNEL", None)
    return str(request.param)


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


def test_both_scans_list_the_same_pairs_in_the_same_order(
        engine: str, monkeypatch: pytest.MonkeyPatch) -> None:
    if engine == "numpy" or COMPILED is None:
        pytest.skip("compares the compiled scan with numpy's (run once, as 'compiled')")
    x = contour(1500, 7)
    t = contour(1200, 8) * 1.02
    for r in (0.01, 0.08, 0.4):
        got = near_pairs(t, x, r)
        monkeypatch.setattr(_switch, "CKERNEL", None)
        want = near_pairs(t, x, r)
        monkeypatch.setattr(_switch, "CKERNEL", COMPILED)
        assert got is not None and want is not None
        for a, b in ((got.counts, want.counts), (got.j, want.j), (got.xj, want.xj),
                     (got.dist, want.dist)):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == b.dtype  # type: ignore[union-attr]


def test_the_compiled_scan_checks_its_runs(engine: str) -> None:
    if engine == "numpy" or COMPILED is None:
        pytest.skip("the compiled scan's own checks")
    t, xs = np.zeros((2, 2)), np.zeros(4)
    counts = np.empty(2, dtype=np.int64)
    lens = np.ones((2, 5), dtype=np.int64)
    assert COMPILED.pair_counts(t, xs, xs, np.zeros((2, 5), dtype=np.int64), lens, 1.0, -1,
                                counts) == 10
    with pytest.raises(ValueError, match="a run lies outside the points"):
        COMPILED.pair_counts(t, xs, xs, np.full((2, 5), 4, dtype=np.int64), lens, 1.0, -1,
                             counts)
    with pytest.raises(ValueError, match="whole rows"):
        COMPILED.pair_counts(t, xs, xs, np.zeros(3, dtype=np.int64), lens, 1.0, -1, counts)
    with pytest.raises(ValueError, match="the output does not hold the pairs"):
        COMPILED.pair_fill(t, xs, xs, np.arange(4), np.zeros((2, 5), dtype=np.int64), lens,
                           1.0, np.empty(9, dtype=np.int64), np.empty((2, 9)), None)

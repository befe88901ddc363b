"""similarity_matrix (registration/_similarity.py): D of eq. 9 between the shapes of a
collection."""

from __future__ import annotations

import numpy as np
import pytest

from registration import similarity_matrix
from registration.synthetic import chained_family


def _shapes() -> list[np.ndarray]:
    return list(chained_family(n_chains=2, chain_length=2, n_points=50, seed=3).shapes)


def _rigid(points: np.ndarray, degrees: float, shift: tuple[float, float]) -> np.ndarray:
    a = np.radians(degrees)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return points @ R.T + np.asarray(shift)


def test_every_ordered_pair_with_zero_diagonal() -> None:
    shapes = _shapes()
    sim = similarity_matrix(shapes)
    n = len(shapes)
    assert sim.D.shape == (n, n)
    np.testing.assert_array_equal(np.diag(sim.D), 0.0)
    off = sim.D[~np.eye(n, dtype=bool)]
    assert np.isfinite(off).all() and (off > 0).all()
    assert sim.computed == n * (n - 1)
    # D is directed (the model moves onto the subject), yet both directions of a pair agree
    # on which shapes are alike: each shape's nearest is the same either way round
    assert (np.argsort(sim.D + np.diag([np.inf] * n), axis=1)[:, 0]
            == np.argsort(sim.D.T + np.diag([np.inf] * n), axis=1)[:, 0]).all()


def test_a_similar_copy_is_at_distance_zero_both_ways() -> None:
    base, other = _shapes()[0], _shapes()[3]
    copy = 2.5 * _rigid(base, -40.0, (5.0, -2.0))
    sim = similarity_matrix([base, copy, other])
    assert sim.D[0, 1] < 1e-6 and sim.D[1, 0] < 1e-6
    assert min(sim.D[0, 2], sim.D[2, 0], sim.D[1, 2]) > 1e-3
    # a sheared copy is nearer than any other shape, both ways
    sheared = base @ np.array([[1.3, 0.4], [-0.2, 0.8]]).T
    sim = similarity_matrix([base, sheared, other])
    assert max(sim.D[0, 1], sim.D[1, 0]) < min(sim.D[0, 2], sim.D[1, 2], sim.D[2, 0])


def test_invariant_to_a_rigid_motion_of_one_shape() -> None:
    shapes = _shapes()
    moved = list(shapes)
    moved[2] = _rigid(shapes[2], 70.0, (10.0, -4.0))
    before = similarity_matrix(shapes).D
    after = similarity_matrix(moved).D
    np.testing.assert_allclose(after, before, rtol=0.05, atol=1e-4)


def test_pairs_and_candidates_limit_what_is_computed() -> None:
    shapes = _shapes()
    sim = similarity_matrix(shapes, pairs=[(0, 1), (2, 3)])
    assert sim.computed == 2
    known = ~np.isnan(sim.D)
    assert known.sum() == len(shapes) + 2
    assert known[0, 1] and known[2, 3] and not known[1, 0]
    few = similarity_matrix(shapes, candidates=1)
    nan = np.isnan(few.D)
    assert (nan == nan.T).all()  # both directions of every chosen pair
    assert few.computed == int((~nan).sum()) - len(shapes) < len(shapes) * (len(shapes) - 1)


def test_progress_reports_every_pair() -> None:
    calls: list[tuple[str, int, int]] = []
    similarity_matrix(_shapes()[:3], progress=lambda *a: calls.append(a))
    assert calls[0] == ("similarity", 0, 6)
    assert calls[-1] == ("similarity", 6, 6)
    assert [c[1] for c in calls] == sorted(c[1] for c in calls)


def test_bad_input_is_refused() -> None:
    shapes = _shapes()
    with pytest.raises(ValueError, match="at least 2 shapes"):
        similarity_matrix(shapes[:1])
    with pytest.raises(ValueError, match=r"pair \(0, 9\) is out of range for 5 shapes"):
        similarity_matrix(shapes, pairs=[(0, 9)])
    with pytest.raises(ValueError, match="candidates must be at least 1"):
        similarity_matrix(shapes, candidates=0)
    with pytest.raises(ValueError, match=r"shapes\[1\]"):
        similarity_matrix([shapes[0], [[0.0, 0.0, 0.0]]])

import numpy as np
import pytest

from registration import registration_error


def test_eq10_hand_computed():
    q = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    y = np.array([[0.0, 1.0], [2.0, 0.5]])
    # forward: q0->y0 (1), q1->y0 or y1: d2 = 2 vs 1.25 -> 1.25, q2->y1: 0.25
    # backward: y0->q0: 1, y1->q2: 0.25
    expected = (1.0 + 1.25 + 0.25 + 1.0 + 0.25) / 5
    assert registration_error(q, y) == pytest.approx(expected)


def test_eq10_zero_for_identical_sets_and_symmetric():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(30, 2))
    b = rng.normal(size=(20, 2))
    assert registration_error(a, a) == 0.0
    assert registration_error(a, b) == pytest.approx(registration_error(b, a))
    assert isinstance(registration_error(a, b), float)


def test_eq10_rejects_bad_input():
    with pytest.raises(ValueError, match="q has a non-finite"):
        registration_error([[0, 0], [np.nan, 1]], [[0, 0]])
    with pytest.raises(ValueError, match=r"y must have shape \(n, 2\)"):
        registration_error([[0, 0]], [[0, 0, 0]])

import numpy as np
import pytest

from registration import as_points, normalise, resample


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ([[0, 0], [1, 1]], "at least 3 points; got 2"),
        (np.zeros((4, 3)), r"shape \(n, 2\); got \(4, 3\)"),
        (np.zeros(6), r"shape \(n, 2\); got \(6,\)"),
        ([[0, 0], [1, np.nan], [2, 2]], "non-finite coordinate at point 1"),
        ([[0, 0], [1, np.inf], [2, 2]], "non-finite coordinate at point 1"),
        ([["a", "b"], ["c", "d"], ["e", "f"]], "numeric array"),
    ],
)
def test_as_points_rejects_bad_input(value, message):
    with pytest.raises(ValueError, match=message):
        as_points(value, name="points")


def test_normalise_centres_and_scales_and_inverts():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 2)) * 37.0 + [400.0, -20.0]
    q, norm = normalise(p)
    np.testing.assert_allclose(q.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.sqrt((q**2).sum(axis=1).mean()), 1.0)
    np.testing.assert_allclose(norm.invert(q), p)
    np.testing.assert_allclose(norm.apply(p), q)


def test_normalise_rejects_coincident_points():
    with pytest.raises(ValueError, match="zero size"):
        normalise(np.ones((5, 2)))


def test_resample_keeps_evenly_spaced_points():
    p = np.c_[np.arange(100.0), np.zeros(100)]
    r = resample(p, 10)
    assert r.shape == (10, 2)
    np.testing.assert_allclose(np.diff(r[:, 0]), 10.0)
    assert resample(p, 200) is not None and resample(p, 200).shape == (100, 2)
    with pytest.raises(ValueError, match="at least 3"):
        resample(p, 2)


def test_sampling_irregularity_tells_even_from_random_sampling():
    from registration._points import sampling_irregularity

    rng = np.random.default_rng(4)

    def ellipse(t):
        return np.c_[np.cos(t), 0.5 * np.sin(t)]

    even = ellipse(np.linspace(0, 2 * np.pi, 400, endpoint=False))
    assert sampling_irregularity(even) < 1e-3
    # an even sampling stretched by a smooth map: the spacing varies, but only slowly
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    assert sampling_irregularity(ellipse(t + 0.4 * np.sin(t))) < 0.02
    # independent uniform points: about 1 at any number of points and any size
    for n in (100, 400):
        values = [sampling_irregularity(7.0 * ellipse(np.sort(rng.uniform(0, 2 * np.pi, n))))
                  for _ in range(100)]
        assert 0.85 < float(np.mean(values)) < 1.1
    # clustered: more than random
    clustered = ellipse(np.sort(2 * np.pi * rng.beta(0.3, 0.3, 400)))
    assert sampling_irregularity(clustered) > 1.0
    assert sampling_irregularity(even[:3]) == 0.0

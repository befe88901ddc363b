"""Tests of registration._cpd (non-rigid CPD)."""

from __future__ import annotations

import itertools
import json
from typing import Any

import numpy as np
import pytest

from registration._cpd import CPDResult, NonrigidTransform, cpd_nonrigid


# ----------------------------------------------------------------------------------------
# synthetic data
# ----------------------------------------------------------------------------------------
def fish_curve(k: int) -> np.ndarray:
    """A lobed closed contour (~100 x 70 units), sampled unevenly in arc length."""
    t = np.linspace(0.0, 2 * np.pi, k, endpoint=False)
    r = 1.0 + 0.2 * np.cos(3 * t) + 0.1 * np.sin(5 * t + 0.3)
    pts = np.column_stack([np.cos(t) * r * 50.0, np.sin(t) * r * 35.0])
    return pts + np.array([300.0, 200.0])


def smooth_warp(p: np.ndarray) -> np.ndarray:
    """Known smooth field: translation, mild symmetric affine, two broad Gaussian bumps."""
    c = np.array([300.0, 200.0])
    z = (p - c) / 50.0
    a = np.array([[1.06, 0.04], [0.04, 0.95]])
    out = z @ a.T
    out += np.exp(-np.sum((z - [0.8, 0.2]) ** 2, axis=1))[:, None] * [0.10, -0.15]
    out += np.exp(-np.sum((z + np.array([0.7, 0.1])) ** 2, axis=1))[:, None] * [-0.08, 0.12]
    return out * 50.0 + c + np.array([6.0, -4.0])


def rms_radius(p: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, axis=1))))


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    model = fish_curve(200)
    truth = smooth_warp(model)
    perm = rng.permutation(len(truth))
    subject = truth[perm] + 0.05 * rng.standard_normal(truth.shape)
    return model, subject, truth, perm


@pytest.fixture(scope="module")
def big_pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    model = fish_curve(600)
    subject = smooth_warp(fish_curve(650)) + 0.05 * rng.standard_normal((650, 2))
    return model, subject


@pytest.fixture(scope="module")
def dense_big(big_pair: tuple[np.ndarray, np.ndarray]) -> CPDResult:
    model, subject = big_pair
    return cpd_nonrigid(model, subject, tol=0.0, max_iter=80, low_rank=False, truncate=False,
                        gauss_grid=False)


# ----------------------------------------------------------------------------------------
# accuracy
# ----------------------------------------------------------------------------------------
def test_recovers_known_smooth_warp(pair: tuple[np.ndarray, ...]) -> None:
    model, subject, truth, perm = pair
    res = cpd_nonrigid(model, subject)
    assert res.warped.shape == model.shape
    err = np.linalg.norm(res.warped - truth, axis=1)
    scale = rms_radius(truth)  # ~47 units; mean point spacing ~1.5 units
    before = np.linalg.norm(model - truth, axis=1).mean()  # ~13% of scale
    # Bound: CPD with the MATLAB defaults is biased even for the identity on this unevenly
    # sampled curve (points slide ~1% of the RMS radius along it; pycpd does the same), and
    # the warp adds ~1% more (measured 0.85 units = 1.8%).  4% is about one point spacing
    # on average; a wrong registration (flipped, collapsed, stuck) errs by > 10%.
    assert err.mean() < 0.04 * scale, err.mean() / scale
    assert err.mean() < 0.2 * before
    assert err.max() < 0.10 * scale
    # correspondence: model point i should pick the subject row holding the true image of
    # a point at most 3 contour neighbours away from i
    k = len(model)
    true_index = perm[res.correspondence]  # subject row j is the image of model perm[j]
    gap = np.abs(true_index - np.arange(k))
    gap = np.minimum(gap, k - gap)
    assert np.mean(gap <= 3) > 0.95
    assert res.correspondence.dtype.kind == "i"
    assert np.all((res.probability >= 0) & (res.probability <= 1))
    assert res.converged and 1 <= res.iterations <= 150
    assert res.sigma2 > 0


def test_matches_pycpd(pair: tuple[np.ndarray, ...]) -> None:
    model, subject, _, _ = pair
    opts: dict[str, Any] = dict(beta=2.0, lmbda=3.0, w=0.1, tol=0.0, max_iter=40)
    ours = cpd_nonrigid(model, subject, low_rank=False, truncate=False, **opts)
    ref = cpd_nonrigid(model, subject, backend="pycpd", **opts)
    assert ours.iterations == ref.iterations == 40
    # same data, same normalisation, same EM: agreement is limited by rounding only
    # (measured ~1e-12 of the RMS radius)
    scale = rms_radius(subject)
    assert np.max(np.abs(ours.warped - ref.warped)) < 1e-8 * scale
    assert ours.sigma2 == pytest.approx(ref.sigma2, rel=1e-6)
    np.testing.assert_allclose(ref.transform.apply(model), ref.warped, atol=1e-8 * scale)


# ----------------------------------------------------------------------------------------
# the transform
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("low_rank", [False, True])
def test_transform_consistent(pair: tuple[np.ndarray, ...], low_rank: bool) -> None:
    model, subject, truth, _ = pair
    res = cpd_nonrigid(model, subject, low_rank=low_rank)
    tr = res.transform
    scale = rms_radius(subject)
    np.testing.assert_allclose(tr.apply(model), res.warped, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(tr(model), res.warped, rtol=0, atol=1e-8 * scale)
    # midpoints between consecutive model points land near the midpoints of their images
    mid = 0.5 * (model + np.roll(model, -1, axis=0))
    wmid = tr.apply(mid)
    interp = 0.5 * (res.warped + np.roll(res.warped, -1, axis=0))
    assert np.max(np.linalg.norm(wmid - interp, axis=1)) < 0.05
    # ... and the field generalises: midpoints are as accurate as the fitted points
    err_fit = np.linalg.norm(res.warped - truth, axis=1).mean()
    assert np.mean(np.linalg.norm(wmid - smooth_warp(mid), axis=1)) < 1.2 * err_fit + 0.05
    assert tr.apply(np.empty((0, 2))).shape == (0, 2)


def test_transform_round_trip(pair: tuple[np.ndarray, ...]) -> None:
    model, subject, _, _ = pair
    res = cpd_nonrigid(model, subject, max_iter=20)
    d = json.loads(json.dumps(res.transform.to_dict()))
    back = NonrigidTransform.from_dict(d)
    pts = np.random.default_rng(3).uniform(200, 400, size=(50, 2))
    np.testing.assert_array_equal(back.apply(pts), res.transform.apply(pts))
    with pytest.raises(ValueError, match="not a serialised NonrigidTransform"):
        NonrigidTransform.from_dict({"kind": "affine"})
    with pytest.raises(ValueError, match=r"points must have shape \(k, 2\)"):
        back.apply(np.zeros((3, 3)))


def test_result_is_read_only(pair: tuple[np.ndarray, ...]) -> None:
    model, subject, _, _ = pair
    res = cpd_nonrigid(model, subject, max_iter=5)
    with pytest.raises(ValueError):
        res.warped[0, 0] = 1.0
    with pytest.raises(AttributeError):
        res.iterations = 3  # type: ignore[misc]


# ----------------------------------------------------------------------------------------
# accelerations agree with the dense float64 computation
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("opts", "rel_tol"),
    [
        (dict(low_rank=True, truncate=False), 1e-6),
        (dict(low_rank=False, truncate=True), 1e-6),
        (dict(), 1e-6),  # auto: both on for this size
        (dict(dtype="float32", low_rank=False, truncate=False, gauss_grid=False), 1e-4),
        (dict(dtype="float32"), 1e-4),
    ],
)
def test_fast_paths_match_dense(big_pair: tuple[np.ndarray, np.ndarray], dense_big: CPDResult,
                                opts: dict[str, Any], rel_tol: float) -> None:
    model, subject = big_pair
    res = cpd_nonrigid(model, subject, tol=0.0, max_iter=80, **opts)
    scale = rms_radius(subject)
    assert res.iterations == dense_big.iterations
    assert np.max(np.abs(res.warped - dense_big.warped)) < rel_tol * scale
    np.testing.assert_allclose(res.transform.apply(model), res.warped, rtol=0,
                               atol=1e-8 * scale)


def test_fixed_num_eig_is_approximate_but_close(big_pair: tuple[np.ndarray, np.ndarray],
                                                 dense_big: CPDResult) -> None:
    model, subject = big_pair
    res = cpd_nonrigid(model, subject, tol=0.0, max_iter=80, low_rank=True, num_eig=10)
    scale = rms_radius(subject)
    assert np.max(np.abs(res.warped - dense_big.warped)) < 0.05 * scale


# ----------------------------------------------------------------------------------------
# robustness
# ----------------------------------------------------------------------------------------
def test_callback_called_and_exception_propagates(pair: tuple[np.ndarray, ...]) -> None:
    model, subject, _, _ = pair
    model_copy, subject_copy = model.copy(), subject.copy()
    seen: list[tuple[int, float, float]] = []

    class Stop(Exception):
        pass

    def cb(it: int, s2: float, obj: float) -> None:
        seen.append((it, s2, obj))
        if it == 3:
            raise Stop

    with pytest.raises(Stop):
        cpd_nonrigid(model, subject, callback=cb)
    assert [s[0] for s in seen] == [1, 2, 3]
    assert all(np.isfinite(s[1]) and s[1] > 0 and np.isfinite(s[2]) for s in seen)
    np.testing.assert_array_equal(model, model_copy)
    np.testing.assert_array_equal(subject, subject_copy)
    # the same call without the callback still works
    assert cpd_nonrigid(model, subject, max_iter=3).iterations == 3


def _assert_finite(res: CPDResult, m: int) -> None:
    assert res.warped.shape == (m, 2)
    assert np.isfinite(res.warped).all()
    assert np.isfinite(res.probability).all()
    assert np.isfinite(res.sigma2) and res.sigma2 > 0
    assert np.isfinite(res.transform.coefficients).all()


@pytest.mark.parametrize("w", [0.0, 0.1])
@pytest.mark.parametrize(
    "case", ["duplicates", "collinear", "three", "offset", "all_same", "tiny_scale"]
)
def test_degenerate_inputs_never_nan(case: str, w: float) -> None:
    rng = np.random.default_rng(5)
    base = fish_curve(40)
    if case == "duplicates":
        model = np.repeat(base[:10], 4, axis=0)
        subject = smooth_warp(np.repeat(base[::4], 3, axis=0))
    elif case == "collinear":
        t = np.linspace(0, 1, 30)
        model = np.column_stack([t, 2 * t])
        subject = np.column_stack([t ** 1.1, 2 * t + 0.1])
    elif case == "three":
        model = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        subject = np.array([[0.1, 0.0], [1.2, 0.1], [0.0, 0.9]])
    elif case == "offset":
        model = base + 1e6
        subject = smooth_warp(base) + np.array([1e6, -1e6])
    elif case == "all_same":
        model = np.ones((5, 2))
        subject = np.full((4, 2), 3.0)
    else:  # tiny_scale
        model = base * 1e-9
        subject = smooth_warp(base) * 1e-9 + rng.standard_normal(base.shape) * 1e-12
    all_opts: list[dict[str, Any]] = [
        {}, {"normalize": False}, {"truncate": True, "low_rank": True}]
    for opts in all_opts:
        res = cpd_nonrigid(model, subject, w=w, **opts)
        _assert_finite(res, len(model))


def test_identical_sets_hit_sigma2_floor() -> None:
    model = fish_curve(60)
    res = cpd_nonrigid(model, model.copy(), w=0.0, tol=0.0, max_iter=150)
    _assert_finite(res, 60)
    assert res.converged
    np.testing.assert_allclose(res.warped, model, atol=1e-3 * rms_radius(model))


def test_normalize_false_on_normalised_data_is_identity(pair: tuple[np.ndarray, ...]) -> None:
    model, subject, _, _ = pair

    def unit(p: np.ndarray) -> np.ndarray:
        q = p - p.mean(axis=0)
        return q / rms_radius(q)

    mn, sn = unit(model), unit(subject)
    a = cpd_nonrigid(mn, sn, normalize=False, low_rank=False, truncate=False, max_iter=40)
    b = cpd_nonrigid(mn, sn, normalize=True, low_rank=False, truncate=False, max_iter=40)
    assert a.iterations == b.iterations
    np.testing.assert_allclose(a.warped, b.warped, rtol=0, atol=1e-9)
    assert a.sigma2 == pytest.approx(b.sigma2, rel=1e-9)
    # in caller units beta=2 on a shape 100 units across is a very local kernel: still finite
    res = cpd_nonrigid(model, subject, normalize=False, max_iter=30)
    _assert_finite(res, len(model))


# ----------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------
GOOD = fish_curve(10)


@pytest.mark.parametrize(
    ("model", "subject", "match"),
    [
        (np.zeros((5, 3)), GOOD, r"model must have shape \(n, 2\); got \(5, 3\)"),
        (GOOD, np.zeros(6), r"subject must have shape \(n, 2\); got \(6,\)"),
        (GOOD[:2], GOOD, "model must have at least 3 points; got 2"),
        (GOOD, GOOD[:1], "subject must have at least 3 points; got 1"),
        (np.where(np.arange(20).reshape(10, 2) == 7, np.nan, GOOD), GOOD,
         "model must contain only finite values; row 3"),
        (GOOD, np.where(np.arange(20).reshape(10, 2) == 0, np.inf, GOOD),
         "subject must contain only finite values; row 0"),
        ([["a", "b"]] * 3, GOOD, "model must be a numeric array"),
    ],
)
def test_bad_points(model: object, subject: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        cpd_nonrigid(model, subject)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("opts", "match"),
    [
        (dict(beta=0.0), "beta must be > 0; got 0.0"),
        (dict(beta=float("nan")), "beta must be finite"),
        (dict(lmbda=-1.0), "lmbda must be > 0; got -1.0"),
        (dict(w=1.0), r"w must satisfy 0 <= w < 1; got 1.0"),
        (dict(w=-0.1), r"w must satisfy 0 <= w < 1"),
        (dict(tol=-1e-3), "tol must be >= 0"),
        (dict(max_iter=0), "max_iter must be an integer >= 1; got 0"),
        (dict(max_iter=2.5), "max_iter must be an integer >= 1; got 2.5"),
        (dict(sigma2=0.0), "sigma2 must be > 0 or None"),
        (dict(num_eig=0), r"num_eig must be None or an integer in \[1, 10\]"),
        (dict(num_eig=11), r"num_eig must be None or an integer in \[1, 10\]"),
        (dict(dtype="float16"), "dtype must be 'float64' or 'float32'; got 'float16'"),
        (dict(backend="matlab"), "backend must be 'native' or 'pycpd'"),
        (dict(low_rank="yes"), "low_rank must be True, False or None"),
        (dict(truncate=1), "truncate must be True, False or None"),
        (dict(callback=3), "callback must be callable or None"),
        (dict(beta="2"), "beta must be a real number"),
    ],
)
def test_bad_parameters(opts: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        cpd_nonrigid(GOOD, GOOD, **opts)


def test_pycpd_backend_transform_and_callback(pair: tuple[np.ndarray, ...]) -> None:
    model, subject, truth, _ = pair
    its: list[int] = []
    res = cpd_nonrigid(model, subject, backend="pycpd", tol=0.0, max_iter=30,
                       callback=lambda i, s, o: its.append(i))
    assert its == list(range(1, 31))
    assert res.iterations == 30
    assert np.linalg.norm(res.warped - truth, axis=1).mean() < 1.0


# ----------------------------------------------------------------------------------------
# warm start (init_warped)
# ----------------------------------------------------------------------------------------
def test_init_warped_starts_from_the_given_positions(pair: Any) -> None:
    model, subject, _, _ = pair
    first = cpd_nonrigid(model, subject)
    # started where a converged run ended, from a small sigma^2, CPD stays there: the
    # kernel and the regulariser are still the model's, the field still model -> subject
    again = cpd_nonrigid(model, subject, init_warped=first.warped, sigma2=first.sigma2)
    scale = rms_radius(subject)
    assert np.sqrt(np.mean(np.sum((again.warped - first.warped) ** 2, axis=1))) < 0.02 * scale
    assert np.allclose(again.transform.apply(model), again.warped, atol=1e-8 * scale)
    # with sigma^2 left to its default it is computed from the start, not from the model
    calls: list[float] = []
    cpd_nonrigid(model, subject, init_warped=first.warped, max_iter=1,
                 callback=lambda it, s2, obj: calls.append(s2))
    cold: list[float] = []
    cpd_nonrigid(model, subject, max_iter=1, callback=lambda it, s2, obj: cold.append(s2))
    assert calls[0] < cold[0]


# ----------------------------------------------------------------------------------------
# accelerated EM (accelerate)
# ----------------------------------------------------------------------------------------
def _warm(pair: Any) -> tuple[np.ndarray, np.ndarray, float]:
    """The subject, a start near it as the tree's polish has (a short run's end), and the
    variance it starts from (half the start's mean squared distance to the subject)."""
    model, subject, _, _ = pair
    start = cpd_nonrigid(model, subject, max_iter=12).warped
    near = np.argmin(((start[:, None] - subject[None]) ** 2).sum(-1), axis=1)
    return subject, start, 0.5 * float(np.mean(np.sum((start - subject[near]) ** 2, axis=1)))


def test_accelerate_reaches_the_same_fit_in_fewer_iterations(pair: Any) -> None:
    subject, start, s2 = _warm(pair)
    runs = {acc: cpd_nonrigid(start, subject, sigma2=s2, dtype="float64", accelerate=acc)
            for acc in (False, True)}
    plain, fast = runs[False], runs[True]
    scale = rms_radius(subject)
    assert fast.converged and plain.converged
    assert fast.iterations < 0.75 * plain.iterations
    # the same fixed point: at least as low an objective, the same points to 1e-3 of
    # the shape's size, the same correspondences almost everywhere
    assert fast.objective <= plain.objective + 1e-6 * abs(plain.objective)
    assert np.sqrt(np.mean(np.sum((fast.warped - plain.warped) ** 2, axis=1))) < 1e-3 * scale
    assert np.mean(fast.correspondence == plain.correspondence) > 0.97
    assert np.allclose(fast.transform.apply(start), fast.warped, atol=1e-8 * scale)


def test_accelerate_never_raises_the_objective(pair: Any,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    from registration._cpd import _nonrigid

    subject, start, s2 = _warm(pair)
    for step_max in (4.0, 1e4):  # the default, and steps so long that some are rejected
        monkeypatch.setattr(_nonrigid, "ACCEL_STEP_MAX", step_max)
        seen: list[float] = []

        def record(it: int, s: float, obj: float, seen: list[float] = seen) -> None:
            seen.append(obj)

        res = cpd_nonrigid(start, subject, sigma2=s2, dtype="float64", accelerate=True,
                           callback=record)
        # each accepted state's objective is no larger than the last: an extrapolation
        # that would raise it is dropped for EM's own iterate
        assert all(b <= a + 1e-9 * abs(a) for a, b in itertools.pairwise(seen))
        assert res.converged and np.isfinite(res.warped).all()
        if step_max > 4:  # rejected extrapolations cost an E-step each, and are counted
            assert res.iterations > len(seen)


def test_accelerate_does_not_stop_on_an_extrapolation_that_made_no_progress(
        pair: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    from registration._cpd import _nonrigid

    subject, start, s2 = _warm(pair)
    plain = cpd_nonrigid(start, subject, sigma2=s2, dtype="float64")
    # every extrapolation lands back on the state one EM step before: accepted (its
    # objective is the one it must not exceed), with no change against it; that is no
    # convergence, and EM goes on from there
    monkeypatch.setattr(_nonrigid, "_squarem", lambda s0, s1, s2_, step_max, floor: s1)
    stuck = cpd_nonrigid(start, subject, sigma2=s2, dtype="float64", accelerate=True)
    assert stuck.converged and stuck.iterations > 3
    scale = rms_radius(subject)
    assert np.sqrt(np.mean(np.sum((stuck.warped - plain.warped) ** 2, axis=1))) < 1e-3 * scale


def test_accelerate_stopped_by_max_iter_returns_an_em_iterate(pair: Any) -> None:
    subject, start, s2 = _warm(pair)
    # two EM steps, then an extrapolated state that no E-step has checked: not returned
    plain = cpd_nonrigid(start, subject, sigma2=s2, tol=0.0, max_iter=2)
    fast = cpd_nonrigid(start, subject, sigma2=s2, tol=0.0, max_iter=2, accelerate=True)
    assert np.array_equal(plain.warped, fast.warped)
    assert plain.sigma2 == fast.sigma2


def test_accelerate_is_validated(pair: Any) -> None:
    model, subject, _, _ = pair
    with pytest.raises(ValueError, match="accelerate must be True or False"):
        cpd_nonrigid(model, subject, accelerate="yes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="accelerate needs backend='native'"):
        cpd_nonrigid(model, subject, accelerate=True, backend="pycpd")


# ----------------------------------------------------------------------------------------
# control points (control)
# ----------------------------------------------------------------------------------------
def test_control_with_every_point_is_the_plain_run(pair: Any) -> None:
    model, subject, _, _ = pair
    plain = cpd_nonrigid(model, subject)
    every = cpd_nonrigid(model, subject, control=np.arange(len(model)))
    scale = rms_radius(subject)
    assert every.iterations == plain.iterations
    assert np.allclose(every.warped, plain.warped, atol=1e-9 * scale)
    assert np.array_equal(every.correspondence, plain.correspondence)


def test_control_points_fit_the_field_that_moves_every_point(pair: Any) -> None:
    model, subject, truth, perm = pair
    control = np.arange(0, len(model), 3)  # a third of the points, spread along the curve
    res = cpd_nonrigid(model, subject, control=control)
    scale = rms_radius(subject)
    assert res.warped.shape == model.shape
    assert res.correspondence.shape == res.probability.shape == (len(model),)
    # the field is the control points' (the mixture's centroids), and it moves every point
    assert np.array_equal(res.transform.control_points.shape, (len(control), 2))
    assert np.allclose(res.transform.apply(model), res.warped, atol=1e-8 * scale)
    # as close to the truth as the run on every point, points between controls included
    plain = cpd_nonrigid(model, subject)
    rms = {name: float(np.sqrt(np.mean(np.sum((r.warped - truth) ** 2, axis=1)))) / scale
           for name, r in (("control", res), ("plain", plain))}
    others = np.setdiff1d(np.arange(len(model)), control)
    between = float(np.sqrt(np.mean(np.sum((res.warped[others] - truth[others]) ** 2,
                                           axis=1)))) / scale
    assert rms["control"] < 1.2 * rms["plain"] and between < 1.2 * rms["plain"]
    # the correspondences of every model point come from the full posterior
    truth_index = np.argsort(perm)  # subject row of each model point's image
    hits = {name: float(np.mean(r.correspondence == truth_index))
            for name, r in (("control", res), ("plain", plain))}
    assert hits["control"] > 0.8 * hits["plain"]


def test_control_with_a_warm_start(pair: Any) -> None:
    model, subject, truth, _ = pair
    first = cpd_nonrigid(model, subject)
    control = np.arange(1, len(model), 4)
    again = cpd_nonrigid(model, subject, init_warped=first.warped, sigma2=first.sigma2,
                         control=control)
    scale = rms_radius(subject)

    def off(r: CPDResult) -> float:
        return float(np.sqrt(np.mean(np.sum((r.warped - truth) ** 2, axis=1)))) / scale

    # a quarter of the points, started where the run on every point ended, stay about there
    assert np.sqrt(np.mean(np.sum((again.warped - first.warped) ** 2, axis=1))) < 0.05 * scale
    assert off(again) < 1.2 * off(first)


@pytest.mark.parametrize(("control", "message"), [
    (np.array([0, 1]), "at least 3 model points"),
    (np.array([0, 1, 1, 2]), "distinct"),
    (np.array([0, 1, 200]), r"lie in \[0, 200\)"),
    (np.array([-1, 1, 2]), r"lie in \[0, 200\)"),
    (np.array([0.0, 1.0, 2.0]), "integer model indices"),
    (np.array([[0, 1, 2]]), "1-D array"),
])
def test_control_is_validated(pair: Any, control: np.ndarray, message: str) -> None:
    model, subject, _, _ = pair
    with pytest.raises(ValueError, match=message):
        cpd_nonrigid(model, subject, control=control)


def test_control_needs_the_native_backend(pair: Any) -> None:
    model, subject, _, _ = pair
    with pytest.raises(ValueError, match="control needs backend='native'"):
        cpd_nonrigid(model, subject, control=np.arange(10), backend="pycpd")


def test_init_warped_is_validated(pair: Any) -> None:
    model, subject, _, _ = pair
    with pytest.raises(ValueError, match="init_warped must have the model's shape"):
        cpd_nonrigid(model, subject, init_warped=model[:-1])
    with pytest.raises(ValueError, match="init_warped needs backend='native'"):
        cpd_nonrigid(model, subject, init_warped=model, backend="pycpd")
    with pytest.raises(ValueError, match="init_warped"):
        cpd_nonrigid(model, subject, init_warped=np.full_like(model, np.nan))


def test_correspondences_are_computed_when_first_read(monkeypatch: pytest.MonkeyPatch) -> None:
    """A run's final correspondences cost a pass over every pair: they are computed when
    first read (most of the tree's runs are intermediate steps whose correspondences nobody
    reads), once, with the values an eager pass gives; a result sent to another process
    carries them."""
    import pickle

    from registration._cpd import _nonrigid
    from registration._cpd._estep import _posterior_max

    calls = []

    def counting(*args: Any) -> Any:
        calls.append(args)
        return _posterior_max(*args)

    monkeypatch.setattr(_nonrigid, "_posterior_max", counting)
    t = np.linspace(0.0, 2.0 * np.pi, 60, endpoint=False)
    model = np.column_stack([np.cos(t), 0.6 * np.sin(t)])
    subject = model * 1.1 + 0.02 * np.sin(3 * t)[:, None]
    res = cpd_nonrigid(model, subject)
    assert calls == []
    corr, prob = res.correspondence, res.probability
    assert len(calls) == 1
    assert res.correspondence is corr and res.probability is prob and len(calls) == 1
    want = _posterior_max(*calls[0])
    np.testing.assert_array_equal(corr, want[0])
    np.testing.assert_array_equal(prob, want[1])
    assert not corr.flags.writeable and not prob.flags.writeable
    other = cpd_nonrigid(model, subject)
    sent = pickle.loads(pickle.dumps(other))
    assert len(calls) == 2  # computed where the run was made
    np.testing.assert_array_equal(sent.correspondence, corr)
    np.testing.assert_array_equal(sent.warped, res.warped)
    assert len(calls) == 2

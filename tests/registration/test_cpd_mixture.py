"""CPD with mixture weights (``cpd_nonrigid(mixture_weights=...)``): every E-step pass
against the sums written out from the whole weighted kernel matrix, whole runs through
every pass, the validation, and the sampling weights the dynamic tree runs with."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from registration import CPDOptions, build_dynamic_tree, cpd_nonrigid, register_direct
from registration._cpd import _estep, _switch
from registration._cpd._estep import _EStep, _MixtureWeights, _posterior_max_dense
from registration._points import sampling_irregularity, sampling_weights
from registration.synthetic import deformation_chains

from .test_ckernel import with_engine
from .test_cpd_fast import close, curve


def weighted_sums(t: np.ndarray, x: np.ndarray, s2: float, w: float,
                  pi: np.ndarray) -> _estep._EStepOut:
    """The E-step's sums from the whole kernel matrix, each centroid's row times its
    weight (mean 1), every exponent exact."""
    pi = pi / pi.mean()
    d2 = np.sum((t[:, None, :] - x[None, :, :]) ** 2, axis=2)
    k = pi[:, None] * np.exp(-d2 / (2.0 * s2))
    c = 2.0 * np.pi * s2 * w / (1.0 - w) * len(t) / len(x)
    colsum = k.sum(axis=0)
    den = np.maximum(colsum + c, 1e-300)
    return _estep._EStepOut(k @ (1.0 / den), colsum / den, k @ (x / den[:, None]),
                            -float(np.sum(np.log(den))) + len(x) * np.log(s2), k.size)


ENGINES = [None] + ([_switch.CKERNEL] if _switch.CKERNEL is not None else [])


@pytest.mark.parametrize("engine", ENGINES, ids=lambda e: "numpy" if e is None else "compiled")
@pytest.mark.parametrize(("sigma", "w"), [(0.3, 0.1), (0.03, 0.1), (0.03, 0.0), (0.01, 0.1)])
def test_every_estep_pass_sums_the_weighted_mixture(engine: Any, sigma: float,
                                                    w: float) -> None:
    x, t = curve(530, 1), curve(470, 2, wobble=0.05)
    pi = np.random.default_rng(3).uniform(0.3, 3.0, len(t))
    s2 = sigma * sigma
    want = weighted_sums(t, x, s2, w, pi)

    def run(method: str, dtype: str = "float64") -> _estep._EStepOut | None:
        est = _EStep(x, len(t), w, dtype, _MixtureWeights(pi / pi.mean()))
        if method == "truncated":
            est.force_truncate = True
            return est.truncated(t, s2, est.radius(t, s2))
        if method == "dense":
            return est.dense(t, s2)
        return getattr(est, method)(t, s2)

    close(with_engine(engine, lambda: run("dense")), want, 1e-10)
    close(with_engine(engine, lambda: run("dense", "float32")), want, 1e-5)
    if sigma >= 0.03:  # the whole-box grid's range (the cost rule keeps it there)
        close(with_engine(engine, lambda: run("grid")), want, 1e-8)
    if w > 0:  # the box transform needs the outlier constant (see _choose_estep)
        close(with_engine(engine, lambda: run("boxgrid")), want, 1e-8)
    if sigma <= 0.03:
        out = with_engine(engine, lambda: run("truncated"))
        assert out is not None and out.nnz < len(t) * len(x)
        close(out, want, 1e-8)


@pytest.mark.parametrize("engine", ENGINES, ids=lambda e: "numpy" if e is None else "compiled")
def test_weighted_correspondences(engine: Any) -> None:
    x, t = curve(400, 8), curve(380, 9, wobble=0.05)
    pi = np.random.default_rng(4).uniform(0.3, 3.0, len(t))
    s2 = 0.02**2
    arg, best = with_engine(engine, lambda: _posterior_max_dense(
        t, x, s2, 0.1, _MixtureWeights(pi / pi.mean())))
    d2 = np.sum((t[:, None, :] - x[None, :, :]) ** 2, axis=2)
    k = (pi / pi.mean())[:, None] * np.exp(-d2 / (2 * s2))
    post = k / (k.sum(axis=0) + 2 * np.pi * s2 * 0.1 / 0.9 * len(t) / len(x))
    np.testing.assert_array_equal(arg, np.argmax(post, axis=1))
    np.testing.assert_allclose(best, post.max(axis=1), rtol=1e-9)


def test_equal_weights_are_the_uniform_mixture() -> None:
    y, x = curve(300, 5), curve(260, 6, wobble=0.2)
    plain = cpd_nonrigid(y, x)
    same = cpd_nonrigid(y, x, mixture_weights=np.full(len(y), 7.0))
    named = cpd_nonrigid(y, x, mixture_weights="uniform")
    np.testing.assert_array_equal(named.warped, plain.warped)
    np.testing.assert_allclose(same.warped, plain.warped, atol=1e-12)
    assert same.objective == pytest.approx(plain.objective, rel=1e-12)
    np.testing.assert_array_equal(same.correspondence, plain.correspondence)


def test_weighted_runs_agree_through_every_pass() -> None:
    """Whole runs at 1200 x 1100 points (grid, box, truncated and dense E-steps by cost)
    and with each pass forced: the same fit, within the passes' stated tolerances."""
    y, x = curve(1200, 11), curve(1100, 12, wobble=0.15)
    pi = np.random.default_rng(5).uniform(0.3, 3.0, len(y))
    ref = cpd_nonrigid(y, x, mixture_weights=pi, truncate=False, gauss_grid=False)
    moved = np.max(np.abs(ref.warped - cpd_nonrigid(y, x, truncate=False,
                                                    gauss_grid=False).warped))
    assert moved > 1e-3  # the weights change the fit ...
    for kw in ({}, {"truncate": True}, {"gauss_grid": True, "truncate": False}):
        got = cpd_nonrigid(y, x, mixture_weights=pi, **kw)
        assert np.max(np.abs(got.warped - ref.warped)) < 1e-6  # ... the passes do not
    got32 = cpd_nonrigid(y, x, mixture_weights=pi, dtype="float32")
    assert np.max(np.abs(got32.warped - ref.warped)) < 1e-4


def test_sampling_weights_with_control_points() -> None:
    y, x = curve(600, 13), curve(500, 14, wobble=0.1)
    control = np.arange(0, 600, 3)
    res = cpd_nonrigid(y, x, mixture_weights="sampling", control=control)
    assert res.warped.shape == (600, 2) and res.correspondence.shape == (600,)
    # an array's entries at the control points weight the EM's centroids
    pi = np.random.default_rng(6).uniform(0.5, 2.0, 600)
    a = cpd_nonrigid(y, x, mixture_weights=pi, control=control)
    frame = (y.mean(axis=0), float(np.sqrt(np.mean(np.sum((y - y.mean(axis=0)) ** 2, axis=1)))))
    b = cpd_nonrigid(y[control], x, mixture_weights=pi[control], model_frame=frame)
    np.testing.assert_allclose(a.transform.apply(y[control]), b.warped, atol=1e-9)


@pytest.mark.parametrize(("weights", "message"), [
    ("even", "mixture_weights must be None, 'uniform', 'sampling' or an array"),
    (np.ones(5), r"one entry per model point, shape \(40,\); got shape \(5,\)"),
    (np.r_[np.ones(39), 0.0], "finite and > 0"),
    (np.r_[np.ones(39), np.nan], "finite and > 0"),
    (np.ones((40, 2)), "shape"),
    (object(), "mixture_weights must be None, 'uniform', 'sampling' or an array"),
])
def test_mixture_weights_are_validated(weights: Any, message: str) -> None:
    y, x = curve(40, 1), curve(40, 2)
    with pytest.raises(ValueError, match=message):
        cpd_nonrigid(y, x, mixture_weights=weights)


def test_mixture_weights_need_the_native_backend() -> None:
    with pytest.raises(ValueError, match="mixture_weights needs backend='native'"):
        cpd_nonrigid(curve(40, 1), curve(40, 2), mixture_weights="sampling",
                     backend="pycpd")


def test_cpd_options_mixture_is_validated() -> None:
    assert CPDOptions().mixture_weights is None
    assert CPDOptions(mixture_weights="uniform").mixture_weights == "uniform"
    with pytest.raises(ValueError, match="mixture_weights must be 'uniform', 'sampling' or None"):
        CPDOptions(mixture_weights="even")


def ellipse(t: np.ndarray) -> np.ndarray:
    return np.column_stack([1.5 * np.cos(t), np.sin(t)])


def test_sampling_weights_even_out_random_draws_only() -> None:
    rng = np.random.default_rng(0)
    # evenly spaced, also once stretched smoothly: every weight about 1
    even = ellipse(np.linspace(0, 2 * np.pi, 400, endpoint=False))
    stretched = ellipse(np.linspace(0, 2 * np.pi, 400, endpoint=False) ** 1.3
                        / (2 * np.pi) ** 0.3)
    for pts in (even, stretched):
        w = sampling_weights(pts)
        assert sampling_irregularity(pts) < 0.1
        assert np.all(w == 1.0)
    # drawn at random: a point in a cluster weighs less than one beside a gap
    t = np.sort(rng.uniform(0, 2 * np.pi, 400))
    drawn = ellipse(t)
    w = sampling_weights(drawn)
    assert w.mean() == pytest.approx(1.0) and w.min() > 0 and w.std() > 0.2
    gap = np.diff(np.r_[t, t[0] + 2 * np.pi])
    arc = 0.5 * (gap + np.roll(gap, 1))  # the parameter length each point stands for
    assert np.corrcoef(w, arc)[0, 1] > 0.6
    assert np.all(sampling_weights(drawn[:4]) == 1.0)  # too few points to compare


def _spy(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    import registration._tree._polish as polish
    import registration._tree._resolution as resolution
    import registration._tree._tasks as tasks

    seen: list[Any] = []

    def spy(*args: Any, **kwargs: Any) -> Any:
        seen.append(kwargs.get("mixture_weights"))
        return cpd_nonrigid(*args, **kwargs)

    for mod in (tasks, polish, resolution):
        monkeypatch.setattr(mod, "cpd_nonrigid", spy)
    return seen


def test_the_dynamic_tree_weights_its_mixtures_and_the_baselines_do_not(
        monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1)
    dense = ellipse(np.linspace(0, 2 * np.pi, 3000, endpoint=False))
    dense[:, 1] += 0.3 * np.sin(3 * np.linspace(0, 2 * np.pi, 3000, endpoint=False))
    fam = deformation_chains(dense, n_points=160, n_chains=2, chain_length=2, seed=2)
    shapes = [s[rng.permutation(len(s))] for s in fam.shapes]
    seen = _spy(monkeypatch)
    build_dynamic_tree(shapes, root=0, compare_direct=False)
    assert seen and set(seen) == {"sampling"}
    seen.clear()
    build_dynamic_tree(shapes, root=0, compare_direct=False,
                       cpd=CPDOptions(mixture_weights="uniform"))
    assert seen and set(seen) == {"uniform"}
    seen.clear()
    register_direct(shapes, root=0)
    register_direct(shapes, root=0, prealign=False)
    register_direct(shapes, root=0, cpd=CPDOptions(dtype="float64"))
    assert seen and set(seen) == {"uniform"}


def test_compiled_passes_check_the_log_weights() -> None:
    ck = _switch.CKERNEL
    if ck is None:
        pytest.skip("registration._cpd._ckernel not built")
    tt, x = np.zeros((2, 3)), np.zeros((4, 2))
    p1, px, pt1 = np.empty(3), np.empty((2, 3)), np.empty(4)
    ck.dense(tt, x, 1.0, 0.1, 1e-300, False, p1, px, pt1, np.zeros(3))
    with pytest.raises(ValueError, match="lw holds 16 bytes, expected 24"):
        ck.dense(tt, x, 1.0, 0.1, 1e-300, False, p1, px, pt1, np.zeros(2))
    with pytest.raises(ValueError, match="lw holds"):
        ck.posterior_max(tt, x, 1.0, 0.1, 1e-300, np.empty(3, dtype=np.int64), np.empty(3),
                         np.zeros(4))

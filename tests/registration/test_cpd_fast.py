"""CPD's near-linear paths (issue 9) against the dense computation they replace.

Stated tolerances (also in the docstrings of ``registration._cpd._fgt`` and ``_estep``):

* Chebyshev-grid Gauss transform, whole-box (``_fgt``) and box-wise (``_boxfgt``): every sum
  within ``1e-9 * sum_j |q_j|`` of the dense one; the E-step sums ``P1``, ``Pt1``, ``P X``
  within ``1e-8`` relative.
* Pivoted-Cholesky kernel: ``|G - L L^T| <= trace tolerance``; eigen form reproduces ``G``.
* Truncated E-step (sparse, CSR): sums within ``1e-8`` relative in float64, ``1e-5`` in float32.
* Sparse final correspondences: the same argmax and maximum as the dense pass.
* Whole runs: warped points within ``1e-6`` (float64) / ``1e-4`` (float32) of the subject's
  RMS radius of the dense float64 run.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from registration._cpd import _boxfgt, _estep, _switch, cpd_nonrigid
from registration._cpd._boxfgt import BOX_ABS_TOL, box_gauss_transform, box_rank
from registration._cpd._estep import _EStep, _posterior_max, _posterior_max_dense
from registration._cpd._fgt import _cheb_nodes, _interp_matrix, gauss_transform, pivoted_cholesky
from registration._cpd._field import _gauss_kernel
from registration._cpd._mstep import LOW_RANK_TRACE_TOL, _low_rank_factor


def curve(k: int, seed: int = 0, wobble: float = 0.0) -> np.ndarray:
    """A lobed closed contour normalised to zero mean and unit RMS radius."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, 2 * np.pi, k))
    r = 1.0 + 0.25 * np.cos(3 * t) + 0.1 * np.sin(5 * t + 0.3) + wobble * np.sin(7 * t)
    p = np.column_stack([np.cos(t) * r * 1.4, np.sin(t) * r])
    p -= p.mean(axis=0)
    return p / math.sqrt(float(np.mean(np.sum(p * p, axis=1))))


def dense_sums(t: np.ndarray, x: np.ndarray, s2: float, w: float) -> _estep._EStepOut:
    return _EStep(x, len(t), w, "float64").dense(t, s2)


def close(a: _estep._EStepOut, b: _estep._EStepOut, rel: float) -> None:
    for got, want in ((a.p1, b.p1), (a.pt1, b.pt1), (a.px, b.px)):
        assert np.max(np.abs(got - want)) <= rel * np.max(np.abs(want))
    assert abs(a.nll - b.nll) <= rel * abs(b.nll) + 1e-9


def naive_sums(t: np.ndarray, x: np.ndarray, s2: float, w: float) -> _estep._EStepOut:
    """The E-step's sums from the whole kernel matrix, every exponent exact."""
    d2 = np.sum((t[:, None, :] - x[None, :, :]) ** 2, axis=2)
    k = np.exp(-d2 / (2.0 * s2))
    c = 2.0 * np.pi * s2 * w / (1.0 - w) * len(t) / len(x)
    colsum = k.sum(axis=0)
    den = np.maximum(colsum + c, 1e-300)
    return _estep._EStepOut(k @ (1.0 / den), colsum / den, k @ (x / den[:, None]),
                            -float(np.sum(np.log(den))) + len(x) * np.log(s2), k.size)


@pytest.mark.parametrize("sigma", [0.3, 0.03, 0.01, 0.004])
@pytest.mark.parametrize("w", [0.1, 0.0])
def test_float64_dense_estep_clips_only_what_underflows(
        sigma: float, w: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """At a small sigma most exponents lie below -700, where numpy's float64 exp is slow:
    they are clipped and their kernel subtracted, and the sums stay those of the exact
    kernels (w = 0 too, where a subject point far from every centroid has only such
    kernels and its denominator stays at the floor)."""
    t = curve(300, 1)
    x = np.vstack([curve(250, 2, wobble=0.1) * 1.05, [[3.0, 3.0]]])  # one point far off
    s2 = sigma * sigma
    assert (_estep._max_exponent(t, x, s2) > -_estep._EXP_MIN) == (sigma < 0.3)
    got = dense_sums(t, x, s2, w)
    # the same E-step without the clip: the same sums to rounding
    monkeypatch.setattr(_estep, "_max_exponent", lambda *_: 0.0)
    close(got, dense_sums(t, x, s2, w), 1e-14)
    # and the exact kernels' sums, to the rounding of the exponent's expanded form
    # (|t|^2 - 2 t.x + |x|^2 loses about eps |t|^2 / sigma^2 to cancellation)
    close(got, naive_sums(t, x, s2, w), 1e-10)


@pytest.mark.parametrize("sigma", [2.0, 0.7, 0.3, 0.12, 0.05])
def test_gauss_transform_matches_dense(sigma: float) -> None:
    rng = np.random.default_rng(1)
    src, tgt = curve(300, 1), curve(250, 2, wobble=0.1) * 1.1
    q = rng.standard_normal((300, 3))
    got = gauss_transform(src, q, tgt, sigma)
    want = _gauss_kernel(tgt, src, sigma) @ q
    assert np.max(np.abs(got - want)) <= 1e-9 * float(np.max(np.sum(np.abs(q), axis=0)))


@pytest.mark.parametrize("sigma", [1.0, 0.4, 0.15])
@pytest.mark.parametrize("w", [0.1, 0.0])
def test_grid_estep_matches_dense(sigma: float, w: float) -> None:
    x, t = curve(400, 3), curve(350, 4, wobble=0.15)
    got = _EStep(x, len(t), w, "float64").grid(t, sigma * sigma)
    close(got, dense_sums(t, x, sigma * sigma, w), 1e-8)


def test_interpolation_weights_on_and_next_to_the_nodes() -> None:
    """Points on a node (or a denormal away) get that node's one-hot row; elsewhere the
    weights reproduce polynomials up to the degree the nodes carry."""
    p = 13
    nodes = _cheb_nodes(p)
    on = _interp_matrix(nodes, p)
    np.testing.assert_array_equal(on, np.eye(p))
    near = _interp_matrix(np.array([nodes[4] + 5e-324, nodes[7] - 5e-324]), p)
    np.testing.assert_array_equal(near, np.eye(p)[[4, 7]])
    u = np.r_[-1.0, np.linspace(-0.999, 0.999, 57), 1.0, nodes[2] + 1e-15]
    lmat = _interp_matrix(u, p)
    assert np.all(np.isfinite(lmat))
    for degree in (0, 1, 5, p - 1):
        np.testing.assert_allclose(lmat @ nodes**degree, u**degree, atol=1e-13)


@pytest.mark.parametrize("widths", [1.0, 2.0, 4.0, 7.0, 8.0])
def test_box_rank_interpolates_every_shift(widths: float) -> None:
    """Every 1-D kernel value between a box and any point (inside the box or up to 9
    sigma away) is interpolated within BOX_ABS_TOL on box_rank nodes (sigma = 1)."""
    p = box_rank(widths)
    u = np.linspace(0.0, widths, 601)
    nodes = (_cheb_nodes(p) + 1.0) * 0.5 * widths
    v = np.linspace(-9.0, widths + 9.0, 1201)
    lmat = _interp_matrix(u / widths * 2.0 - 1.0, p)
    exact = np.exp(-0.5 * (u[:, None] - v[None, :]) ** 2)
    approx = lmat @ np.exp(-0.5 * (nodes[:, None] - v[None, :]) ** 2)
    assert np.max(np.abs(approx - exact)) <= BOX_ABS_TOL


@pytest.mark.parametrize("sigma", [0.5, 0.12, 0.04, 0.01])
def test_box_gauss_transform_matches_dense(sigma: float) -> None:
    rng = np.random.default_rng(1)
    src, tgt = curve(600, 1), curve(500, 2, wobble=0.1) * 1.1
    src = np.vstack([src, [[3.0, 2.5]]])  # a lone source box far from every target
    q = rng.standard_normal((601, 3))
    got = box_gauss_transform(src, q, tgt, sigma)
    want = _gauss_kernel(tgt, src, sigma) @ q
    assert np.max(np.abs(got - want)) <= 1e-11 * float(np.max(np.sum(np.abs(q), axis=0)))


@pytest.mark.parametrize(("sigma", "w"), [(0.3, 0.0), (0.3, 0.1), (0.08, 0.1), (0.02, 0.1),
                                           (0.005, 0.1)])
def test_box_estep_matches_dense(sigma: float, w: float) -> None:
    """Down to small sigma with an outlier weight (every denominator >= its constant; the
    choice in run_estep uses the box E-step only then)."""
    x, t = curve(400, 3), curve(350, 4, wobble=0.15)
    got = _EStep(x, len(t), w, "float64").boxgrid(t, sigma * sigma)
    close(got, dense_sums(t, x, sigma * sigma, w), 1e-8)


def test_box_run_matches_dense(pair: tuple[np.ndarray, np.ndarray], dense_run: np.ndarray,
                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A whole run with the box-wise E-step on every iteration it applies to."""
    calls = []
    box = _EStep.boxgrid

    def counted(self: _EStep, t: np.ndarray, s2: float) -> _estep._EStepOut:
        calls.append(s2)
        return box(self, t, s2)

    monkeypatch.setattr(_EStep, "grid_cost", lambda self, t, s2: None)
    monkeypatch.setattr(_EStep, "boxgrid", counted)
    monkeypatch.setattr(_boxfgt, "BOX_MAX_OCCUPIED", 10**9)
    model, subject = pair
    res = cpd_nonrigid(model, subject, tol=0.0, max_iter=60, gauss_grid=True, truncate=False,
                       low_rank=False)
    assert len(calls) == 60
    scale = float(np.sqrt(np.mean(np.sum((subject - subject.mean(0)) ** 2, axis=1))))
    assert np.max(np.abs(res.warped - dense_run)) < 1e-6 * scale


@pytest.mark.parametrize(("dtype", "rel"), [("float64", 1e-8), ("float32", 1e-5)])
def test_truncated_estep_matches_dense(dtype: str, rel: float,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    x, t = curve(500, 5), curve(450, 6, wobble=0.05)
    s2 = 0.03**2
    est = _EStep(x, len(t), 0.1, dtype)
    est.force_truncate = True
    want = dense_sums(t, x, s2, 0.1)
    got = est.truncated(t, s2, est.radius(t, s2))
    assert got is not None and got.nnz < len(t) * len(x) // 4
    close(got, want, rel)
    # the list is reused while the centroids move little: still exact
    moved = t + 0.002
    got = est.truncated(moved, s2, est.radius(moved, s2))
    assert got is not None
    close(got, dense_sums(moved, x, s2, 0.1), rel)
    # sigma halves: the loose list is pruned to the new radius (no new search), still exact
    before = est._pj
    monkeypatch.setattr(_estep, "near_pairs", None)  # a search would fail
    got = est.truncated(moved, s2 / 4, est.radius(moved, s2 / 4))
    assert got is not None and est._pj is not None and before is not None
    assert len(est._pj) < len(before)
    close(got, dense_sums(moved, x, s2 / 4, 0.1), rel)


@pytest.mark.parametrize("w", [0.1, 0.0])
def test_float32_truncation_radius_follows_its_precision(w: float) -> None:
    """float32 runs truncate at TRUNCATION_EPS_F32 (their own rounding), float64 at
    TRUNCATION_EPS: a smaller radius, fewer pairs, still within the float32 tolerance."""
    x, t = curve(500, 5), curve(450, 6, wobble=0.05)
    s2 = 0.02**2
    e32, e64 = _EStep(x, len(t), w, "float32"), _EStep(x, len(t), w, "float64")
    r32, r64 = e32.radius(t, s2), e64.radius(t, s2)
    assert r32 < r64
    # r^2 = (a term without eps) - 2 sigma^2 log(eps), for w > 0 and w = 0 alike
    want = 2 * s2 * math.log(_estep.TRUNCATION_EPS / _estep.TRUNCATION_EPS_F32)
    assert r32**2 - r64**2 == pytest.approx(want, rel=1e-9)
    e32.force_truncate = e64.force_truncate = True
    got32, got64 = e32.truncated(t, s2, r32), e64.truncated(t, s2, r64)
    assert got32 is not None and got64 is not None and got32.nnz < got64.nnz
    close(got32, dense_sums(t, x, s2, w), 1e-5)


def test_estimated_choice_is_reused_while_sigma_stays_close(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A method chosen by the estimated costs runs again without new estimates while
    sigma^2 stays within ENGINE_REUSE_FACTOR of where it was chosen, and is chosen afresh
    beyond; either way the sums are the dense ones within the method's tolerance."""
    monkeypatch.setattr(_estep, "DENSE_ONLY_MAX_PAIRS", 0)  # small sets: always dense
    x, t = curve(500, 5), curve(450, 6, wobble=0.05)
    est = _EStep(x, len(t), 0.1, "float64")
    sample = np.unique(np.linspace(0, len(t) - 1, 64).astype(np.intp))
    s2 = 0.02**2
    close(_estep.run_estep(est, t, s2, None, None, sample), dense_sums(t, x, s2, 0.1), 1e-8)
    assert est.choice is not None and est.choice[0] == s2
    chosen = est.choice

    def no_estimate(*args: object) -> float:
        raise AssertionError("estimated again within the reuse factor")

    monkeypatch.setattr(_EStep, "density", no_estimate)
    monkeypatch.setattr(_EStep, "grid_cost", no_estimate)
    monkeypatch.setattr(_EStep, "box_cost", no_estimate)
    near = s2 * 0.9
    assert near >= s2 / _estep.ENGINE_REUSE_FACTOR
    close(_estep.run_estep(est, t, near, None, None, sample), dense_sums(t, x, near, 0.1), 1e-8)
    assert est.choice == chosen
    monkeypatch.undo()
    monkeypatch.setattr(_estep, "DENSE_ONLY_MAX_PAIRS", 0)
    far = s2 * 4 * _estep.ENGINE_REUSE_FACTOR
    close(_estep.run_estep(est, t, far, None, None, sample), dense_sums(t, x, far, 0.1), 1e-8)
    assert est.choice is not None and est.choice[0] == far
    # a method forced by the caller neither reuses nor records a choice
    forced = _EStep(x, len(t), 0.1, "float64")
    _estep.run_estep(forced, t, s2, False, False, sample)
    assert forced.choice is None


@pytest.mark.parametrize("beta", [2.0, 1.0])
def test_field_kernel_product_by_the_grid_matches_dense(
        beta: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """Many points: the field's kernel product (warp, Jacobian) goes through the Chebyshev
    grid, every sum within 1e-12 of sum_j |q_j| of the dense product; few points: dense."""
    from registration._cpd import _field
    from registration._cpd._field import NonrigidTransform, kernel_product

    cp, z = curve(1200, 3), curve(1100, 4, wobble=0.1) * 1.1
    q = np.random.default_rng(0).normal(size=(len(cp), 6)) * 50.0
    want = _gauss_kernel(z, cp, beta) @ q
    with monkeypatch.context() as mp:
        mp.setattr(_field, "_gauss_kernel", None)  # the dense product would fail
        got = kernel_product(z, cp, q, beta)
        field = NonrigidTransform(cp, q[:, :2], beta, np.zeros(2), 1.0, np.zeros(2), 1.0)
        warped, jac = field.apply_with_jacobian(z)
    assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(q).sum(axis=0))
    np.testing.assert_allclose(warped, z + want[:, :2], rtol=0, atol=1e-9)
    # the Jacobian against central differences of the warp
    h = 1e-6
    for axis in range(2):
        d = np.zeros(2)
        d[axis] = h
        fd = (field.apply(z + d) - field.apply(z - d)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, axis], fd, rtol=0, atol=1e-5)
    small = kernel_product(z[:50], cp[:60], q[:60], beta)  # below the grid's fixed cost
    np.testing.assert_allclose(small, _gauss_kernel(z[:50], cp[:60], beta) @ q[:60], rtol=0,
                               atol=1e-13 * np.max(np.abs(q[:60]).sum(axis=0)))
    # points at infinity, NaN or 1e233 leave no grid to build: dense, as the warp was
    far = np.vstack([z, [[np.inf, 0.0], [np.nan, 1.0], [1e233, 0.0]]])
    with np.errstate(all="ignore"):
        got_far, want_far = kernel_product(far, cp, q, beta), _gauss_kernel(far, cp, beta) @ q
    # (in row blocks: the same products up to BLAS's rounding of each block, which is
    # relative to the summed terms' magnitude, not to a sum that cancels: OpenBLAS 0.3.31
    # differs by 5e-13 relative on such sums)
    np.testing.assert_allclose(got_far, want_far, rtol=0,
                               atol=1e-13 * np.max(np.abs(q).sum(axis=0)))


@pytest.mark.parametrize("beta", [2.0, 0.5])
def test_pivoted_cholesky_and_eigen_form(beta: float) -> None:
    y = curve(300, 7)
    g = _gauss_kernel(y, y, beta)
    lmat = pivoted_cholesky(y, beta, None, LOW_RANK_TRACE_TOL)
    assert lmat.shape[1] < 300
    assert np.max(np.abs(g - lmat @ lmat.T)) <= LOW_RANK_TRACE_TOL * 300
    q, lam = _low_rank_factor(y, beta, None)
    np.testing.assert_allclose(q.T @ q, np.eye(len(lam)), atol=1e-10)
    assert np.max(np.abs(g - (q * lam) @ q.T)) <= 1e-9
    _, lam5 = _low_rank_factor(y, beta, 5)
    assert len(lam5) == 5
    # the same points again (another array): the factor made before, read-only
    again = _low_rank_factor(y.copy(), beta, None)
    assert again[0] is q and again[1] is lam
    assert not q.flags.writeable and not lam.flags.writeable
    moved = y.copy()
    moved[0, 0] += 1e-9
    assert _low_rank_factor(moved, beta, None)[0] is not q
    # more columns than the tolerance asks: pivots at rounding level, whose Gram-route
    # eigenvectors are not orthonormal; the QR route's are
    q250, lam250 = _low_rank_factor(y, beta, 250)
    assert len(lam250) > len(lam)
    np.testing.assert_allclose(q250.T @ q250, np.eye(len(lam250)), atol=1e-10)
    assert np.max(np.abs(g - (q250 * lam250) @ q250.T)) <= 1e-9


def test_small_problems_take_the_dense_estep_without_estimates(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Up to DENSE_ONLY_MAX_PAIRS pairs the E-step is dense at every sigma (estimating the
    other methods' costs would cost as much as the dense E-step); one pair more and the
    estimates run again."""
    x, t = curve(500, 5), curve(450, 6, wobble=0.05)
    sample = np.unique(np.linspace(0, len(t) - 1, 64).astype(np.intp))
    monkeypatch.setattr(_estep, "DENSE_ONLY_MAX_PAIRS", len(t) * len(x))
    est = _EStep(x, len(t), 0.1, "float32")
    with monkeypatch.context() as mp:
        def no_estimate(*args: object) -> float:
            raise AssertionError("estimated a small problem's E-step")

        for name in ("density", "grid_cost", "box_cost", "truncated", "grid", "boxgrid"):
            mp.setattr(_EStep, name, no_estimate)
        for s2 in (1.0, 0.05**2, 0.005**2):  # grid, box and truncated ranges at any size
            got = _estep.run_estep(est, t, s2, None, None, sample)
            assert got.nnz == len(t) * len(x)
            close(got, dense_sums(t, x, s2, 0.1), 1e-5)
        assert est.choice is None
    monkeypatch.setattr(_estep, "DENSE_ONLY_MAX_PAIRS", len(t) * len(x) - 1)
    got = _estep.run_estep(est, t, 0.005**2, None, None, sample)
    assert est.choice is not None and est.choice[1] == "truncated"
    assert got.nnz < len(t) * len(x)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_compiled_dense_estep_is_weighed_against_the_grids_at_its_speed(
        monkeypatch: pytest.MonkeyPatch, dtype: str) -> None:
    """Up to COMPILED_DENSE_MAX_PAIRS pairs, with the compiled passes, the grid and box
    E-steps must beat the dense one's estimate divided by their measured speed-ups; above,
    or with numpy's passes, the choice is as fitted (the estimates compared as they are)."""
    x, t = curve(500, 5), curve(450, 6, wobble=0.05)
    sample = np.unique(np.linspace(0, len(t) - 1, 64).astype(np.intp))
    pairs = len(t) * len(x)
    dense = pairs * (_estep.DENSE_PAIR_COST_F32 if dtype == "float32" else 1.0)
    est = _EStep(x, len(t), 0.1, dtype)
    if _switch.BUILT is None:
        pytest.skip("the compiled passes are not built here")
    monkeypatch.setattr(_switch, "CKERNEL", _switch.BUILT)
    monkeypatch.setattr(_estep, "COMPILED_DENSE_MAX_PAIRS", pairs)

    def choose(grid: float | None, box: float | None) -> str:
        monkeypatch.setattr(_EStep, "grid_cost", lambda self, t, s2: grid)
        monkeypatch.setattr(_EStep, "box_cost", lambda self, t, s2, bound: box)
        name, out = _estep._choose_estep(est, t, 0.3**2, False, None, sample)
        close(out, dense_sums(t, x, 0.3**2, 0.1), 1e-5 if dtype == "float32" else 1e-8)
        return name

    grid_speedup = _estep.COMPILED_DENSE_SPEEDUP_GRID
    box_speedup = _estep.COMPILED_DENSE_SPEEDUP_BOX
    # estimated cheaper than the dense pass, but not by the compiled pass's speed-up
    assert choose(0.5 * dense, None) == "dense"
    assert choose(None, 0.5 * dense) == "dense"
    # cheaper by more than that: taken
    assert choose(0.9 * dense / grid_speedup, None) == "grid"
    assert choose(None, 0.9 * dense / box_speedup) == "box"
    assert choose(0.9 * dense / grid_speedup, 0.8 * dense / grid_speedup) == "box"
    # one pair more, or numpy's passes: the estimates compared as they are
    monkeypatch.setattr(_estep, "COMPILED_DENSE_MAX_PAIRS", pairs - 1)
    assert choose(0.5 * dense, None) == "grid"
    assert choose(None, 0.5 * dense) == "box"
    monkeypatch.setattr(_estep, "COMPILED_DENSE_MAX_PAIRS", pairs)
    monkeypatch.setattr(_switch, "CKERNEL", None)
    assert choose(0.5 * dense, None) == "grid"
    assert choose(None, 0.5 * dense) == "box"
    assert choose(1.1 * dense, 1.2 * dense) == "dense"


def test_sparse_correspondences_match_dense(monkeypatch: pytest.MonkeyPatch) -> None:
    x, t = curve(400, 8), curve(380, 9, wobble=0.05)
    monkeypatch.setattr(_estep, "POSTERIOR_DENSE_MAX_PAIRS", 0)
    monkeypatch.setattr(_estep, "POSTERIOR_DENSE_MAX_PAIRS_COMPILED", 0)
    for s2, w in ((0.01**2, 0.1), (0.02**2, 0.0), (0.005**2, 0.3)):
        arg, best = _posterior_max(t, x, s2, w)
        arg_d, best_d = _posterior_max_dense(t, x, s2, w)
        np.testing.assert_allclose(best, best_d, rtol=1e-8, atol=1e-12)
        clear = best_d > 1e-6  # ties among vanishing posteriors may pick another index
        np.testing.assert_array_equal(arg[clear], arg_d[clear])


@pytest.mark.parametrize("sigma", [0.002, 0.02, 0.3])
def test_dense_correspondences_match_the_posterior_matrix(sigma: float) -> None:
    # the pass computes its exponents by one product per block and clips them at -700 (an
    # exp below that leaves numpy's vector path): the same posteriors as the full matrix
    # from coordinate differences, also where most pairs underflow (sigma 0.002). Not
    # with w = 0 there: subject points 37 sigma from every centroid then have only
    # denormal kernels over a floored denominator, ratios without significant digits
    # (the pass gives them 0, the matrix up to 1e-4)
    x, t = curve(400, 8), curve(380, 9, wobble=0.05)
    for w in (0.1, 0.0) if sigma > 0.01 else (0.1, 0.01):
        k = np.exp(-((t[:, None, :] - x[None, :, :]) ** 2).sum(-1) / (2 * sigma**2))
        den = np.maximum(k.sum(axis=0) + _estep._outlier_const(sigma**2, w, len(t), len(x)),
                         1e-300)
        p = k / den
        arg, best = _posterior_max_dense(t, x, sigma**2, w)
        np.testing.assert_allclose(best, p.max(axis=1), rtol=1e-9, atol=1e-14)
        clear = best > 1e-6
        np.testing.assert_array_equal(arg[clear], p.argmax(axis=1)[clear])


def test_sparse_hint_gives_the_dense_correspondences(monkeypatch: pytest.MonkeyPatch) -> None:
    # below POSTERIOR_DENSE_MAX_PAIRS, `sparse` (the last E-step was the truncated one)
    # takes the pairs within the radius, with the dense pass's answer (the compiled dense
    # pass, when built, is taken whatever `sparse` says: set aside here)
    monkeypatch.setattr(_estep, "POSTERIOR_DENSE_MAX_PAIRS_COMPILED", 0)
    x, t = curve(400, 8), curve(380, 9, wobble=0.05)
    assert len(x) * len(t) <= _estep.POSTERIOR_DENSE_MAX_PAIRS
    for s2, w in ((0.01**2, 0.1), (0.3**2, 0.1)):  # the second: too many pairs, dense
        arg, best = _posterior_max(t, x, s2, w, sparse=True)
        arg_d, best_d = _posterior_max_dense(t, x, s2, w)
        np.testing.assert_allclose(best, best_d, rtol=1e-8, atol=1e-12)
        clear = best_d > 1e-6
        np.testing.assert_array_equal(arg[clear], arg_d[clear])


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(2)
    model = curve(700, 10) * 40 + [200, 100]
    subject = curve(750, 11, wobble=0.08) * 42 + [205, 98]
    return model, subject + 0.1 * rng.standard_normal(subject.shape)


@pytest.fixture(scope="module")
def dense_run(pair: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    model, subject = pair
    return np.asarray(cpd_nonrigid(model, subject, tol=0.0, max_iter=60, low_rank=False,
                                   truncate=False, gauss_grid=False).warped)


@pytest.mark.parametrize(
    ("opts", "rel"),
    [
        (dict(gauss_grid=True, truncate=False, low_rank=False), 1e-6),
        (dict(gauss_grid=True), 1e-6),
        (dict(), 1e-6),
        (dict(low_rank=True, gauss_grid=False, truncate=False), 1e-6),
        (dict(dtype="float32"), 1e-4),
    ],
)
def test_runs_match_dense(pair: tuple[np.ndarray, np.ndarray], dense_run: np.ndarray,
                          opts: dict[str, object], rel: float) -> None:
    model, subject = pair
    res = cpd_nonrigid(model, subject, tol=0.0, max_iter=60, **opts)  # type: ignore[arg-type]
    scale = float(np.sqrt(np.mean(np.sum((subject - subject.mean(0)) ** 2, axis=1))))
    assert np.max(np.abs(res.warped - dense_run)) < rel * scale
    np.testing.assert_allclose(res.transform.apply(model), res.warped, rtol=0,
                               atol=1e-8 * scale)


def test_gauss_grid_is_validated(pair: tuple[np.ndarray, np.ndarray]) -> None:
    with pytest.raises(ValueError, match="gauss_grid must be True, False or None"):
        cpd_nonrigid(*pair, gauss_grid="yes")  # type: ignore[arg-type]


def test_the_bounding_box_of_several_sets_keeps_nan_and_infinity() -> None:
    """The grids' box, a column at a time: the same corners as numpy's reduction over
    the stacked sets, NaN where any point has NaN in that coordinate."""
    from registration._cpd._fgt import bounding_box

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(50, 2)), rng.normal(size=(7, 2)) + 5.0
    lo, hi = bounding_box(a, b)
    np.testing.assert_array_equal(lo, np.vstack([a, b]).min(axis=0))
    np.testing.assert_array_equal(hi, np.vstack([a, b]).max(axis=0))
    b[3] = [np.nan, np.inf]
    lo, hi = bounding_box(b, a)
    assert np.isnan(lo[0]) and np.isnan(hi[0])
    assert lo[1] == a[:, 1].min() and hi[1] == np.inf

"""CPD's compiled passes (``registration/_cpd/_ckernel.c``) against numpy's: the truncated
E-step's, and the dense Gauss sums (dense E-step, correspondences, kernel product, the
low-rank kernel's pivoted Cholesky factor).

The extension is optional (setup.py builds it when a C compiler is present); without it
the library runs the numpy passes and these comparisons skip, unless
``REGTREE_REQUIRE_CKERNEL=1`` (set by ``.ci/run``), which makes a missing build a failure.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import pytest

from registration._cpd import _estep, _switch, cpd_nonrigid
from registration._cpd._estep import _EStep, _posterior_max_dense
from registration._cpd._fgt import _cheb_nodes, _interp_matrix
from registration._cpd._field import _gauss_kernel
from registration._cpd._switch import compiled_kernel, compiled_simd
from registration._points import farthest_point_indices

from .test_cpd_fast import close, curve, naive_sums

REQUIRED = os.environ.get("REGTREE_REQUIRE_CKERNEL") == "1"


def test_the_compiled_kernel_is_built_where_required() -> None:
    if REQUIRED:
        assert compiled_kernel(), "REGTREE_REQUIRE_CKERNEL=1 but _ckernel is not importable"
    elif not compiled_kernel():
        pytest.skip("registration._cpd._ckernel not built (no C compiler at install)")


#: The CPU flags (as /proc/cpuinfo names them) of the x86-64-v3 level: AVX2 with FMA.
X86_64_V3 = {"avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "abm", "movbe", "xsave"}


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def test_compiled_simd_names_the_dispatched_instruction_set() -> None:
    simd = compiled_simd()
    if not compiled_kernel():
        assert simd is None
        pytest.skip("registration._cpd._ckernel not built")
    assert simd in {"x86-64-v4", "x86-64-v3", "avx512f", "avx2", "fma", "baseline"}
    if X86_64_V3 <= _cpu_flags():
        # an AVX2 + FMA CPU runs a vectorised clone (with GCC: one that has FMA, which
        # halves the dense pass's time against the AVX2 clone without it)
        assert simd != "baseline"


@pytest.fixture
def ckernel() -> object:
    if _switch.CKERNEL is None:
        if REQUIRED:
            pytest.fail("REGTREE_REQUIRE_CKERNEL=1 but _ckernel is not importable")
        pytest.skip("registration._cpd._ckernel not built")
    return _switch.CKERNEL


def truncated(x: np.ndarray, t: np.ndarray, s2: float, w: float,
              engine: object, dtype: str = "float64") -> _estep._EStepOut:
    saved = _switch.CKERNEL
    _switch.CKERNEL = engine
    try:
        est = _EStep(x, len(t), w, dtype)
        est.force_truncate = True
        out = est.truncated(t, s2, est.radius(t, s2))
        assert out is not None
        assert (est._j32 is not None) == (engine is not None)  # the engine asked for ran
        return out
    finally:
        _switch.CKERNEL = saved


@pytest.mark.parametrize(("sigma", "w"), [(0.01, 0.1), (0.03, 0.1), (0.03, 0.0), (0.1, 0.5)])
def test_compiled_sums_equal_numpy_and_exact(ckernel: object, sigma: float, w: float) -> None:
    x, t = curve(700, 1), curve(600, 2, wobble=0.05)
    s2 = sigma * sigma
    got = truncated(x, t, s2, w, ckernel)
    want = truncated(x, t, s2, w, None)
    assert got.nnz == want.nnz < len(t) * len(x)
    close(got, want, 1e-13)  # the same sums, up to their order
    close(got, naive_sums(t, x, s2, w), 1e-8)  # and the stated tolerance of the dense ones


@pytest.mark.parametrize("sigma", [0.01, 0.05])
def test_compiled_float32_kernel_within_float32_tolerance(ckernel: object, sigma: float) -> None:
    """In float32 runs the compiled step keeps the kernel in float32 (the sums in float64):
    within the truncated float32 E-step's stated 1e-5 of the dense sums."""
    x, t = curve(700, 1), curve(600, 2, wobble=0.05)
    s2 = sigma * sigma
    got = truncated(x, t, s2, 0.1, ckernel, "float32")
    close(got, naive_sums(t, x, s2, 0.1), 1e-5)
    close(got, truncated(x, t, s2, 0.1, ckernel, "float64"), 1e-6)


def test_compiled_step_on_a_pruned_list(ckernel: object) -> None:
    """The list shrinks as sigma does (pruned, not searched again): the compiled passes
    read the pruned list's own arrays."""
    x, t = curve(500, 5), curve(450, 6, wobble=0.05)
    est = _EStep(x, len(t), 0.1, "float64")
    est.force_truncate = True
    for s2 in (0.04**2, 0.02**2, 0.01**2, 0.005**2):
        out = est.truncated(t, s2, est.radius(t, s2))
        assert out is not None and est._j32 is not None
        assert len(est._j32) == len(est._pj) == est._xj.shape[1]  # type: ignore[arg-type,union-attr]
        close(out, naive_sums(t, x, s2, 0.1), 1e-8)


def test_compiled_prune_keeps_the_pairs_numpys_keeps(ckernel: object) -> None:
    """A loose list pruned to a smaller radius by the compiled scan holds the pairs, in the
    order, that numpy's prune keeps: those now within the radius, centroid by centroid."""
    x, t = curve(500, 5), curve(450, 6, wobble=0.05)
    moved = t + 1e-4 * curve(450, 7)
    lists = []
    for engine in (ckernel, None):
        saved = _switch.CKERNEL
        _switch.CKERNEL = engine
        try:
            est = _EStep(x, len(t), 0.1, "float64")
            assert est._build_list(t, 0.3)
            assert est._prune_list(moved, 0.12)
            lists.append((est._counts.copy(), est._pj.copy(), est._xj.copy(),  # type: ignore[union-attr]
                          est._indptr.copy()))  # type: ignore[union-attr]
        finally:
            _switch.CKERNEL = saved
    (counts, pj, xj, indptr), (counts_np, pj_np, xj_np, indptr_np) = lists
    np.testing.assert_array_equal(counts, counts_np)
    np.testing.assert_array_equal(pj, pj_np)
    np.testing.assert_array_equal(xj, xj_np)
    np.testing.assert_array_equal(indptr, indptr_np)
    assert 0 < len(pj) < 450 * 500
    i = np.repeat(np.arange(len(t)), counts)
    d2 = np.sum((moved[i] - x[pj]) ** 2, axis=1)
    assert np.all(d2 <= 0.12**2)
    full = np.sum((moved[:, None, :] - x[None, :, :]) ** 2, axis=2) <= 0.12**2
    assert full.sum() == len(pj)  # every pair within the radius is kept


@pytest.mark.parametrize("r", [1, 2, 13, 38])
def test_compiled_interpolation_weights_equal_numpys(ckernel: object, r: int) -> None:
    """The Chebyshev grids' barycentric weights (`_fgt._interp_matrix`): within an ulp of
    numpy's, one-hot on a node or a denormal away from one, at the ends of the interval,
    and for no point at all."""
    nodes = _cheb_nodes(r)
    u = np.r_[np.random.default_rng(3).uniform(-1.0, 1.0, 500), -1.0, 1.0, nodes,
              nodes + 5e-324, nodes - 5e-324, nodes[0] + 1e-15]
    got = _interp_matrix(u, r)
    saved = _switch.CKERNEL
    _switch.CKERNEL = None
    try:
        want = _interp_matrix(u, r)
        assert _interp_matrix(u[:0], r).shape == (0, r)
    finally:
        _switch.CKERNEL = saved
    assert got.shape == want.shape == (len(u), r)
    np.testing.assert_allclose(got, want, rtol=0, atol=4e-15)
    np.testing.assert_array_equal(got[500 + 2:500 + 2 + 3 * r], want[500 + 2:500 + 2 + 3 * r])
    assert _interp_matrix(u[:0], r).shape == (0, r)
    with pytest.raises(ValueError, match="out"):
        _switch.CKERNEL.interp(u, nodes, np.ones(r), np.empty((len(u), r + 1)))
    with pytest.raises(ValueError, match="wb"):
        _switch.CKERNEL.interp(u, nodes, np.ones(r + 1), np.empty((len(u), r)))


def test_whole_runs_agree(ckernel: object) -> None:
    model, subject = curve(900, 3), 1.1 * curve(800, 4, wobble=0.08) + 0.05
    runs = []
    for engine in (ckernel, None):
        saved = _switch.CKERNEL
        _switch.CKERNEL = engine
        try:
            runs.append(cpd_nonrigid(model, subject, tol=0.0, max_iter=60, truncate=True))
        finally:
            _switch.CKERNEL = saved
    scale = math.sqrt(float(np.mean(np.sum((subject - subject.mean(0)) ** 2, axis=1))))
    assert np.max(np.abs(runs[0].warped - runs[1].warped)) < 1e-9 * scale
    assert runs[0].sigma2 == pytest.approx(runs[1].sigma2, rel=1e-9)


def test_compiled_passes_check_their_arrays(ckernel: object) -> None:
    ck = ckernel
    t = np.zeros((3, 2))
    xj = np.zeros((2, 4))
    ip = np.array([0, 1, 3, 4], dtype=np.int64)
    out = np.empty(4)
    ck.kernels(t, xj, ip, 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="t holds 40 bytes, expected 48"):
        ck.kernels(np.zeros(5), xj, ip, 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="xj holds"):
        ck.kernels(t, np.zeros((2, 3)), ip, 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="indptr must run from 0 to the pair count"):
        ck.kernels(t, xj, np.array([1, 1, 3, 4]), 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="xj holds 64 bytes, expected 80"):  # 5 pairs
        ck.kernels(t, xj, np.array([0, 1, 3, 5]), 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="out holds 24 bytes, expected 8 or 4 a pair"):
        ck.kernels(t, xj, ip, 1.0, np.empty(3))  # type: ignore[attr-defined]
    out32 = np.empty(4, dtype=np.float32)
    ck.kernels(t, xj + 1.0, ip, 0.5, out32)  # type: ignore[attr-defined]
    np.testing.assert_allclose(out32, np.exp(-1.0), rtol=2e-7)
    ck.kernels(t, xj + 1.0, ip, 0.5, out)  # type: ignore[attr-defined]
    np.testing.assert_allclose(out, np.exp(-1.0), rtol=4e-16)
    with pytest.raises(ValueError, match="indptr must not decrease"):
        ck.kernels(t, xj, np.array([0, 3, 1, 4]), 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(TypeError, match="read-write"):  # strided or read-only output
        ck.kernels(t, xj, ip, 1.0, np.empty(8)[::2])  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="not C-contiguous"):  # strided input
        ck.kernels(np.zeros((2, 3)).T, xj, ip, 1.0, out)  # type: ignore[attr-defined]
    x = np.zeros((2, 2))
    n_bufs = [np.empty(2), np.empty((2, 3)), np.empty(3), np.empty((3, 2)), np.empty(2)]
    kern = np.ones(4)
    ck.sums(kern, ip, np.array([0, 1, 1, 0], dtype=np.int32), x, 0.1, 1e-300,  # type: ignore[attr-defined]
            *n_bufs)
    with pytest.raises(ValueError, match="subject index is out of range"):
        ck.sums(kern, ip, np.array([0, 1, 2, 0], dtype=np.int32), x, 0.1, 1e-300,  # type: ignore[attr-defined]
                *n_bufs)
    with pytest.raises(ValueError, match="j holds 32 bytes, expected 16"):
        ck.sums(kern, ip, np.array([0, 1, 1, 0]), x, 0.1, 1e-300, *n_bufs)  # type: ignore[attr-defined]


# --- the dense Gauss sums ----------------------------------------------------------------


def with_engine(engine: object, fn: Any) -> Any:
    saved = _switch.CKERNEL
    _switch.CKERNEL = engine
    try:
        return fn()
    finally:
        _switch.CKERNEL = saved


@pytest.mark.parametrize("sigma", [1.0, 0.1, 0.02, 0.005])
@pytest.mark.parametrize("w", [0.1, 0.0])
def test_compiled_dense_estep_equals_numpy_and_exact(ckernel: object, sigma: float,
                                                     w: float) -> None:
    """float64: within 1e-11 of numpy's dense sums and the exact ones (the kernels within
    2 ulp of numpy's exp; at sigma 0.005 numpy's expanded exponents are the ones off by
    1e-12); float32 within its 1e-5, also at a sigma where float32 coordinates would lose
    the exponents (their differences are taken in float64), and without an outlier weight,
    where a subject point far from every centroid has a floored denominator."""
    x, t = curve(530, 1), curve(470, 2, wobble=0.05)
    s2 = sigma * sigma
    exact = naive_sums(t, x, s2, w)
    for dtype, rel in (("float64", 1e-11), ("float32", 1e-5)):
        est = _EStep(x, len(t), w, dtype)
        got = with_engine(ckernel, lambda est=est: est.dense(t, s2))
        want = with_engine(None, lambda est=est: est.dense(t, s2))
        assert got.nnz == want.nnz == len(t) * len(x)
        close(got, exact, rel)
        close(got, want, rel)


def test_compiled_dense_estep_far_from_every_centroid(ckernel: object) -> None:
    """A subject point hundreds of sigma from every centroid: its kernels are 0 (below the
    exponent -700, or -87 in float32), so without an outlier weight its denominator is
    the floor and it takes no posterior, as numpy's clipped kernels give."""
    x = np.vstack([curve(200, 1), [[50.0, 0.0]]])
    t = curve(180, 2)
    for dtype in ("float64", "float32"):
        est = _EStep(x, len(t), 0.0, dtype)
        got = with_engine(ckernel, lambda est=est: est.dense(t, 0.01))
        assert got.pt1[-1] == 0.0 and np.isfinite(got.p1).all() and np.isfinite(got.nll)
        close(got, naive_sums(t, x, 0.01, 0.0), 1e-11 if dtype == "float64" else 1e-5)


@pytest.mark.parametrize(("sigma", "w"), [(0.3, 0.1), (0.02, 0.1), (0.01, 0.0)])
def test_compiled_correspondences_equal_numpy(ckernel: object, sigma: float, w: float) -> None:
    x, t = curve(400, 8), curve(380, 9, wobble=0.05)
    s2 = sigma * sigma
    arg, best = with_engine(ckernel, lambda: _posterior_max_dense(t, x, s2, w))
    arg0, best0 = with_engine(None, lambda: _posterior_max_dense(t, x, s2, w))
    np.testing.assert_array_equal(arg, arg0)
    # numpy's exponents come from an expanded product, off by about eps |x|^2 / sigma^2
    np.testing.assert_allclose(best, best0, rtol=1e-10, atol=1e-300)
    assert arg.dtype == np.intp and best.min() >= 0.0 and best.max() <= 1.0


def test_compiled_kernel_product_equals_numpy(ckernel: object) -> None:
    """The field's kernel product (few points: dense) and a warp with its Jacobian."""
    from registration._cpd._field import NonrigidTransform, kernel_product

    cp, z = curve(120, 3), curve(90, 4, wobble=0.1) * 1.1
    q = np.random.default_rng(0).normal(size=(len(cp), 6))
    for beta in (2.0, 0.3):
        got = with_engine(ckernel, lambda beta=beta: kernel_product(z, cp, q, beta))
        want = with_engine(None, lambda beta=beta: kernel_product(z, cp, q, beta))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.abs(q).sum(axis=0).max())
    field = NonrigidTransform(cp, q[:, :2], 1.0, np.zeros(2), 1.0, np.zeros(2), 1.0)
    a = with_engine(ckernel, lambda: field.apply_with_jacobian(z))
    b = with_engine(None, lambda: field.apply_with_jacobian(z))
    for got, want in zip(a, b, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    # points at infinity or NaN take numpy's route (0 kernel at infinity, NaN for NaN)
    far = np.vstack([z[:3], [[np.inf, 0.0], [np.nan, 1.0]]])
    with np.errstate(all="ignore"):
        got = with_engine(ckernel, lambda: kernel_product(far, cp, q, 1.0))
        want = with_engine(None, lambda: kernel_product(far, cp, q, 1.0))
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[:4], want[:4], rtol=0, atol=1e-12)


@pytest.mark.parametrize("beta", [2.0, 0.5, 0.1])
def test_compiled_pivoted_cholesky_equals_numpy(ckernel: object, beta: float) -> None:
    """The same first pivots and columns, and the same guarantee: the residual's largest
    entry within the trace tolerance. Once the residual diagonal is down to rounding (the
    last columns of a wide kernel), which point it pivots on is rounding's choice, so the
    ranks may differ by a few columns. A rank past the first 64 columns grows the factor
    and resumes where it stopped."""
    from registration._cpd._fgt import pivoted_cholesky
    from registration._cpd._mstep import LOW_RANK_TRACE_TOL

    y = curve(300, 5, wobble=0.1)
    g = _gauss_kernel(y, y, beta)
    for rank in (None, 7, 100):
        got = with_engine(ckernel, lambda rank=rank: pivoted_cholesky(
            y, beta, rank, LOW_RANK_TRACE_TOL))
        want = with_engine(None, lambda rank=rank: pivoted_cholesky(
            y, beta, rank, LOW_RANK_TRACE_TOL))
        assert abs(got.shape[1] - want.shape[1]) <= max(2, 0.05 * want.shape[1])
        first = min(got.shape[1], want.shape[1], 20)
        np.testing.assert_allclose(got[:, :first], want[:, :first], rtol=0, atol=1e-10)
        if rank is None:
            assert np.max(np.abs(g - got @ got.T)) <= LOW_RANK_TRACE_TOL * len(y)
        elif rank <= 64 or want.shape[1] > 64:
            assert got.shape[1] == want.shape[1]


def test_compiled_dense_passes_check_their_arrays(ckernel: object) -> None:
    ck = ckernel
    tt, x = np.zeros((2, 3)), np.zeros((4, 2))
    p1, px, pt1 = np.empty(3), np.empty((2, 3)), np.empty(4)
    ck.dense(tt, x, 1.0, 0.1, 1e-300, False, p1, px, pt1)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="tt holds 40 bytes, expected 48"):
        ck.dense(np.zeros(5), x, 1.0, 0.1, 1e-300, False, p1, px, pt1)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="pt1 holds 24 bytes, expected 32"):
        ck.dense(tt, x, 1.0, 0.1, 1e-300, True, p1, px, np.empty(3))  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="arg holds"):
        ck.posterior_max(tt, x, 1.0, 0.1, 1e-300, np.empty(2, dtype=np.int64),  # type: ignore[attr-defined]
                         np.empty(3))
    with pytest.raises(ValueError, match="qt holds"):
        ck.product(x, tt, np.zeros(7), 1.0, np.empty((4, 2)))  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="out holds"):
        ck.product(x, tt, np.zeros((2, 3)), 1.0, np.empty((4, 3)))  # type: ignore[attr-defined]
    factor, d = np.zeros((3, 2)), np.ones(3)
    with pytest.raises(ValueError, match="k0 must lie"):
        ck.pivoted_cholesky(np.zeros((3, 2)), 1.0, 3, -1.0, factor, d, 5)  # type: ignore[attr-defined]
    # three coincident points: one column, then nothing left
    assert ck.pivoted_cholesky(np.zeros((3, 2)), 1.0, 3, -1.0, factor, d, 0) == (1, True)  # type: ignore[attr-defined]


def test_compiled_dense_passes_take_read_only_mixture_weights(ckernel: object) -> None:
    """The log mixture weights are only read: a read-only array is taken and gives what a
    writable one gives; an output must still be writable."""
    ck = ckernel
    x, t = curve(120, 1), curve(100, 2, wobble=0.05)
    tt = np.ascontiguousarray(t.T)
    lw = np.log(np.linspace(0.5, 1.0, len(t)))
    frozen = lw.copy()
    frozen.setflags(write=False)
    dense, posterior = [], []
    for weights in (lw, frozen):
        p1, px, pt1 = np.empty(len(t)), np.empty((2, len(t))), np.empty(len(x))
        nll = ck.dense(tt, x, 50.0, 0.1, 1e-300, False, p1, px, pt1, weights)  # type: ignore[attr-defined]
        dense.append((nll, p1, px, pt1))
        arg, best = np.empty(len(t), dtype=np.int64), np.empty(len(t))
        ck.posterior_max(tt, x, 50.0, 0.1, 1e-300, arg, best, weights)  # type: ignore[attr-defined]
        posterior.append((arg, best))
    for a, b in zip(dense[0], dense[1], strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(posterior[0], posterior[1], strict=True):
        np.testing.assert_array_equal(a, b)
    read_only_out = np.empty(len(x))
    read_only_out.setflags(write=False)
    with pytest.raises(TypeError, match="read-write"):
        ck.dense(tt, x, 50.0, 0.1, 1e-300, False, np.empty(len(t)),  # type: ignore[attr-defined]
                 np.empty((2, len(t))), read_only_out, lw)


def test_compiled_nearest_neighbours(ckernel: object) -> None:
    """Both directions from one pass, for a batch of problems: the first index at the least
    squared distance (as argmin) and that distance; e (eq. 10) from it equals the k-d
    trees' within rounding, and the batch ICP takes the same neighbours."""
    from registration._error import registration_error
    from registration._icp._pairwise import _batch_icp

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(4, 50, 2)), rng.normal(size=(4, 37, 2))
    b[:, 5] = b[:, 2]  # a tie: the first index wins
    row_arg, row_d2 = np.empty((4, 50), dtype=np.int64), np.empty((4, 50))
    col_arg, col_d2 = np.empty((4, 37), dtype=np.int64), np.empty((4, 37))
    ckernel.nearest(np.ascontiguousarray(a[..., 0]), np.ascontiguousarray(a[..., 1]),  # type: ignore[attr-defined]
                    np.ascontiguousarray(b[..., 0]), np.ascontiguousarray(b[..., 1]), 50, 37,
                    row_arg, row_d2, col_arg, col_d2)
    d2 = ((a[:, :, None, :] - b[:, None, :, :]) ** 2).sum(-1)
    np.testing.assert_array_equal(row_arg, d2.argmin(axis=2))
    np.testing.assert_array_equal(col_arg, d2.argmin(axis=1))
    np.testing.assert_allclose(row_d2, d2.min(axis=2), rtol=1e-15)
    np.testing.assert_allclose(col_d2, d2.min(axis=1), rtol=1e-15)
    assert not (row_arg == 5).any()
    with pytest.raises(ValueError, match="row_arg holds"):
        ckernel.nearest(a[0, :, 0].copy(), a[0, :, 1].copy(), b[0, :, 0].copy(),  # type: ignore[attr-defined]
                        b[0, :, 1].copy(), 50, 37, np.empty(3, dtype=np.int64), None, None,
                        None)
    q, y = a[0], b[0]
    e = registration_error(q, y)
    assert e == pytest.approx(with_engine(None, lambda: registration_error(q, y)), rel=1e-14)
    x = rng.normal(size=(6, 40, 2))
    start = (np.tile(np.eye(2), (6, 1, 1)), np.zeros((6, 2)))
    got = with_engine(ckernel, lambda: _batch_icp(x, b[0], *start, 8))
    want = with_engine(None, lambda: _batch_icp(x, b[0], *start, 8))
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-12)


# --- the low-rank M-step -----------------------------------------------------------------


def _mstep_inputs(m: int, seed: int) -> tuple[np.ndarray, Any]:
    rng = np.random.default_rng(seed)
    y = curve(m, seed)
    p1 = rng.uniform(0.0, 2.0, m)
    p1[::7] = 0.0  # centroids no subject point is near
    px = p1[:, None] * (y + 0.05 * rng.standard_normal((m, 2)))
    return y, _estep._EStepOut(p1=p1, pt1=np.ones(m), px=px, nll=0.0, nnz=0)


@pytest.mark.parametrize("m", [157, 400])
@pytest.mark.parametrize("beta", [2.0, 1.0, 0.5])
def test_compiled_low_rank_mstep_equals_numpy(ckernel: object, m: int, beta: float) -> None:
    """The compiled M-step (Gram matrix in register tiles, Cholesky by rows) solves the
    same system as numpy and LAPACK: W and the displacement within 1e-13 of theirs, at
    ranks that fill its tiles (multiples of 4 and 8) and ranks that do not, with the AVX2
    tiles (where the CPU has them) and the plain ones."""
    from registration._cpd._mstep import LowRankMStep, _low_rank_factor, _mstep_low_rank

    y, est = _mstep_inputs(m, 3)
    q, lam = _low_rank_factor(y, beta, None)
    for rank in (len(lam), 1, 8, 13):
        qr, lr = np.ascontiguousarray(q[:, :rank]), lam[:rank]
        for reg in (1e-3, 2.0):
            got = with_engine(ckernel, lambda qr=qr, lr=lr, reg=reg: LowRankMStep(qr, lr).solve(
                y, est, reg)[:2])
            want = _mstep_low_rank(qr, lr, y, est, reg)
            for g, w in zip(got, want, strict=True):
                assert np.max(np.abs(g - w)) <= 1e-13 * max(1.0, float(np.max(np.abs(w))))
            # the plain tiles, which a CPU without AVX2 and FMA runs
            padded = np.zeros((m, -(-rank // 8) * 8))
            padded[:, :rank] = qr
            plain = np.empty((m, 2)), np.empty((m, 2))
            assert ckernel.lowrank_mstep(padded, np.ascontiguousarray(lr), y, est.p1,  # type: ignore[attr-defined]
                                         est.px, reg, *plain, True)
            for g, w in zip(plain, want, strict=True):
                assert np.max(np.abs(g - w)) <= 1e-13 * max(1.0, float(np.max(np.abs(w))))


def test_compiled_low_rank_mstep_sums_equal_numpy(ckernel: object) -> None:
    """The sums the EM loop reads after the compiled M-step (``LowRankMStep.solve``) are
    numpy's of the same W and displacement to rounding: sum P1, sum P1 |T|^2, sum PX . T,
    sum W . disp (T = Y + disp), and the finiteness flag, which a non-finite input turns
    off; numpy's route gives no sums."""
    from registration._cpd._mstep import LowRankMStep, _low_rank_factor

    y, est = _mstep_inputs(300, 7)
    q, lam = _low_rank_factor(y, 1.0, None)
    w, disp, sums = with_engine(ckernel, lambda: LowRankMStep(q, lam).solve(y, est, 1e-2))
    assert sums is not None
    t = y + disp
    want = [est.p1.sum(), np.dot(est.p1, (t * t).sum(axis=1)), (est.px * t).sum(),
            (w * disp).sum()]
    np.testing.assert_allclose(sums[:4], want, rtol=1e-12)
    assert sums[4] == 1.0
    est.px[3, 1] = np.inf
    sums = with_engine(ckernel, lambda: LowRankMStep(q, lam).solve(y, est, 1e-2))[2]
    assert sums is not None and sums[4] == 0.0
    assert with_engine(None, lambda: LowRankMStep(q, lam).solve(y, est, 1e-2))[2] is None


def test_compiled_low_rank_mstep_leaves_indefinite_systems_to_lapack(
        ckernel: object, monkeypatch: pytest.MonkeyPatch) -> None:
    """A system rounding leaves indefinite (no subject point near most centroids, no
    regulariser) is not solved by the compiled pass, which writes nothing: numpy's solve
    with its ridge takes it, with the same result as without the compiled pass. Above
    COMPILED_MSTEP_MAX_RANK numpy solves every system."""
    from registration._cpd import _mstep
    from registration._cpd._mstep import LowRankMStep, _low_rank_factor, _mstep_low_rank

    y, est = _mstep_inputs(200, 5)
    q, lam = _low_rank_factor(y, 0.5, None)
    est.p1[5:] = 0.0
    est.px[5:] = 0.0
    kp = -(-len(lam) // 8) * 8
    padded = np.zeros((len(y), kp))
    padded[:, :len(lam)] = q
    w, disp = np.full((len(y), 2), 7.0), np.full((len(y), 2), 7.0)
    assert not ckernel.lowrank_mstep(padded, lam, y, est.p1, est.px, 0.0, w, disp)  # type: ignore[attr-defined]
    assert (w == 7.0).all() and (disp == 7.0).all()
    got = with_engine(ckernel, lambda: LowRankMStep(q, lam).solve(y, est, 0.0)[:2])
    want = _mstep_low_rank(q, lam, y, est, 0.0)
    for g, wt in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, wt)
    y, est = _mstep_inputs(200, 6)
    monkeypatch.setattr(_mstep, "COMPILED_MSTEP_MAX_RANK", len(lam) - 1)
    got = with_engine(ckernel, lambda: LowRankMStep(q, lam).solve(y, est, 1e-3)[:2])
    want = _mstep_low_rank(q, lam, y, est, 1e-3)
    for g, wt in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, wt)


def test_compiled_low_rank_mstep_checks_its_arrays(ckernel: object) -> None:
    ck = ckernel
    y, p1, px = np.zeros((5, 2)), np.ones(5), np.zeros((5, 2))
    w, disp = np.empty((5, 2)), np.empty((5, 2))
    lam = np.ones(3)
    assert ck.lowrank_mstep(np.eye(5, 8), lam, y, p1, px, 1.0, w, disp)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(disp, 0.0)
    # one centroid, rank 1: (0.25 + 1) v = 0.5, W = disp = 0.5 v
    one = np.empty((1, 2)), np.empty((1, 2))
    assert ck.lowrank_mstep(np.full((1, 8), 0.5) * (np.arange(8) == 0), np.ones(1),  # type: ignore[attr-defined]
                            np.zeros((1, 2)), np.ones(1), np.ones((1, 2)), 1.0, *one)
    np.testing.assert_allclose(one[0], 0.2, rtol=1e-15)
    np.testing.assert_allclose(one[1], 0.2, rtol=1e-15)
    with pytest.raises(ValueError, match="multiple of 8"):
        ck.lowrank_mstep(np.eye(5, 4), lam, y, p1, px, 1.0, w, disp)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="multiple of 8"):
        ck.lowrank_mstep(np.eye(5, 8), np.ones(9), y, p1, px, 1.0, w, disp)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="y holds"):
        ck.lowrank_mstep(np.eye(5, 8), lam, np.zeros(5), p1, px, 1.0, w, disp)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="disp holds"):
        ck.lowrank_mstep(np.eye(5, 8), lam, y, p1, px, 1.0, w, np.empty(4))  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="sums holds"):
        ck.lowrank_mstep(np.eye(5, 8), lam, y, p1, px, 1.0, w, disp, False, np.empty(4))  # type: ignore[attr-defined]
    # the sums of the one-centroid system above: P1, P1 |T|^2, PX . T, W . disp, finite
    sums = np.empty(5)
    assert ck.lowrank_mstep(np.full((1, 8), 0.5) * (np.arange(8) == 0), np.ones(1),  # type: ignore[attr-defined]
                            np.zeros((1, 2)), np.ones(1), np.ones((1, 2)), 1.0, *one, False,
                            sums)
    np.testing.assert_allclose(sums, [1.0, 0.08, 0.4, 0.08, 1.0], rtol=1e-15)


def test_compiled_farthest_point_picks_equal_numpy(ckernel: object) -> None:
    """The same picks bit for bit (the same sums, no FMA), ties included: duplicated
    points and points on a coarse grid."""
    rng = np.random.default_rng(3)
    sets = [rng.normal(size=(1900, 2)), curve(700, 1),
            np.repeat(rng.normal(size=(30, 2)), 4, axis=0),
            np.round(rng.normal(size=(500, 2)), 1)]
    for pts in sets:
        for n in (1, 2, 17, 100, 119):
            got = farthest_point_indices(pts, n)
            saved = _switch.CKERNEL
            _switch.CKERNEL = None
            try:
                want = farthest_point_indices(pts, n)
            finally:
                _switch.CKERNEL = saved
            assert got.dtype == want.dtype == np.intp
            np.testing.assert_array_equal(got, want)


def test_compiled_farthest_point_picks_check_their_arrays(ckernel: object) -> None:
    x, y, d2 = np.zeros(5), np.zeros(5), np.ones(5)
    with pytest.raises(ValueError, match="len"):
        ckernel.farthest(x, y, d2, np.zeros(6, dtype=np.int64))  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="y"):
        ckernel.farthest(x, np.zeros(4), d2, np.zeros(2, dtype=np.int64))  # type: ignore[attr-defined]

"""The truncated E-step's compiled passes (``registration/_cpd/_ckernel.c``) against numpy's.

The extension is optional (setup.py builds it when a C compiler is present); without it
the library runs the numpy passes and these comparisons skip, unless
``REGTREE_REQUIRE_CKERNEL=1`` (set by ``.ci/run``), which makes a missing build a failure.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from registration._cpd import _estep, cpd_nonrigid
from registration._cpd._estep import _EStep, compiled_kernel

from .test_cpd_fast import close, curve, naive_sums

REQUIRED = os.environ.get("REGTREE_REQUIRE_CKERNEL") == "1"


def test_the_compiled_kernel_is_built_where_required() -> None:
    if REQUIRED:
        assert compiled_kernel(), "REGTREE_REQUIRE_CKERNEL=1 but _ckernel is not importable"
    elif not compiled_kernel():
        pytest.skip("registration._cpd._ckernel not built (no C compiler at install)")


@pytest.fixture
def ckernel() -> object:
    if _estep._CKERNEL is None:
        if REQUIRED:
            pytest.fail("REGTREE_REQUIRE_CKERNEL=1 but _ckernel is not importable")
        pytest.skip("registration._cpd._ckernel not built")
    return _estep._CKERNEL


def truncated(x: np.ndarray, t: np.ndarray, s2: float, w: float,
              engine: object, dtype: str = "float64") -> _estep._EStepOut:
    saved = _estep._CKERNEL
    _estep._CKERNEL = engine
    try:
        est = _EStep(x, len(t), w, dtype)
        est.force_truncate = True
        out = est.truncated(t, s2, est.radius(t, s2))
        assert out is not None
        assert (est._j32 is not None) == (engine is not None)  # the engine asked for ran
        return out
    finally:
        _estep._CKERNEL = saved


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


def test_whole_runs_agree(ckernel: object) -> None:
    model, subject = curve(900, 3), 1.1 * curve(800, 4, wobble=0.08) + 0.05
    runs = []
    for engine in (ckernel, None):
        saved = _estep._CKERNEL
        _estep._CKERNEL = engine
        try:
            runs.append(cpd_nonrigid(model, subject, tol=0.0, max_iter=60, truncate=True))
        finally:
            _estep._CKERNEL = saved
    scale = math.sqrt(float(np.mean(np.sum((subject - subject.mean(0)) ** 2, axis=1))))
    assert np.max(np.abs(runs[0].warped - runs[1].warped)) < 1e-9 * scale
    assert runs[0].sigma2 == pytest.approx(runs[1].sigma2, rel=1e-9)


def test_compiled_passes_check_their_arrays(ckernel: object) -> None:
    ck = ckernel
    t = np.zeros((3, 2))
    xj = np.zeros((2, 4))
    ip = np.array([0, 1, 3, 4], dtype=np.int64)
    out = np.empty(4)
    ck.exponents(t, xj, ip, 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="t holds 40 bytes, expected 48"):
        ck.exponents(np.zeros(5), xj, ip, 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="xj holds"):
        ck.exponents(t, np.zeros((2, 3)), ip, 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="indptr must run from 0 to the pair count"):
        ck.exponents(t, xj, np.array([1, 1, 3, 4]), 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="xj holds 64 bytes, expected 80"):  # 5 pairs
        ck.exponents(t, xj, np.array([0, 1, 3, 5]), 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="out holds 24 bytes, expected 8 or 4 a pair"):
        ck.exponents(t, xj, ip, 1.0, np.empty(3))  # type: ignore[attr-defined]
    out32 = np.empty(4, dtype=np.float32)
    ck.exponents(t, xj + 1.0, ip, 0.5, out32)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(out32, -1.0)
    with pytest.raises(ValueError, match="indptr must not decrease"):
        ck.exponents(t, xj, np.array([0, 3, 1, 4]), 1.0, out)  # type: ignore[attr-defined]
    with pytest.raises(TypeError, match="read-write"):  # strided or read-only output
        ck.exponents(t, xj, ip, 1.0, np.empty(8)[::2])  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="not C-contiguous"):  # strided input
        ck.exponents(np.zeros((2, 3)).T, xj, ip, 1.0, out)  # type: ignore[attr-defined]
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

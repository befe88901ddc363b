"""CPD's M-step: the dense SPD solve and the low-rank kernel with the Woodbury solve."""

from __future__ import annotations

import functools

import numpy as np
import scipy.linalg.lapack

from . import _switch
from ._estep import _EStepOut
from ._fgt import pivoted_cholesky
from ._field import FloatArray

#: Automatic low-rank: the pivoted Cholesky factor stops once the trace of ``G - L L^T``
#: (a bound on its spectral norm) is at most this fraction of ``trace(G) = M``. At 1e-10
#: instead of 1e-12 the factor of a 400-point glyph has rank 36 / 68 / 143 at beta 2 / 1 /
#: 0.5 (46 / 85 / 175), is built in 0.6-0.8x the time and makes every M-step cheaper:
#: the tree's CPU on 30 永 glyphs 0.92x (its polish 0.89x; min of three rounds each), its
#: warped points within 1.2e-5 of the glyphs' size and no parent changed; plain CPD on the
#: 1000- and 8000-point fish (150 iterations) within 6e-7 and 7e-6 of the size, the same
#: ground-truth error to four digits. At 1e-8 that error moved (0.664 -> 0.667 %, 0.274 ->
#: 0.281 %): too loose (bench/RESULTS.md 7.9).
LOW_RANK_TRACE_TOL = 1e-10
#: Largest rank the compiled low-rank M-step takes (:class:`LowRankMStep`); above it numpy
#: and LAPACK, whose blocked products and Cholesky keep ahead once the k x k system
#: outgrows the second-level cache (400 points: the compiled pass takes 0.35-0.5x numpy's
#: time at rank 33-63, 0.7x at 117-132, 0.9x at 157 and 1.1x at 283).
COMPILED_MSTEP_MAX_RANK = 160
_POTRF = scipy.linalg.lapack.dpotrf
_POTRS = scipy.linalg.lapack.dpotrs


def _low_rank_factor(y: FloatArray, beta: float, num_eig: int | None
                     ) -> tuple[FloatArray, FloatArray]:
    """``(Q, lam)`` with ``G ~= Q diag(lam) Q^T``, ``Q`` orthonormal (to about 1e-7 at
    rank 150), for the Gaussian kernel of ``y`` (width ``beta``), without forming ``G``.

    A pivoted Cholesky factor ``G ~= L L^T`` (:func:`._fgt.pivoted_cholesky`: ``num_eig``
    columns, or with ``num_eig=None`` as many as :data:`LOW_RANK_TRACE_TOL` asks) is turned
    into eigenpairs through its k x k Gram matrix: ``L^T L = V diag(lam) V^T``,
    ``Q = L V diag(lam)^-1/2``, so ``Q diag(lam) Q^T = L L^T`` to rounding. Cost
    ``O(M k^2)`` instead of the ``O(M^2)`` kernel and its eigendecomposition; 0.6x the
    time of a QR of ``L`` first, whose ``Q`` is orthonormal to rounding. Both give
    ``Q diag(lam) Q^T`` to the factor's own 1e-9 (bench/RESULTS.md 7.26); where the Gram
    route's ``Q`` is not orthonormal to :data:`FACTOR_GRAM_ORTHO_TOL` (eigenvalues near
    its rounding, from a ``num_eig`` past the tolerance's rank) the QR route is taken.

    The last few factors of up to :data:`FACTOR_CACHE_MAX_POINTS` points are kept
    (:func:`_cached_factor`): one tree's finishes register the same root model onto every
    subject.
    """
    y = np.ascontiguousarray(y, dtype=np.float64)
    key = (y.tobytes(), y.shape, float(beta), num_eig, LOW_RANK_TRACE_TOL)
    return (_cached_factor(*key) if len(y) <= FACTOR_CACHE_MAX_POINTS
            else _factor(*key))


def _factor(y_bytes: bytes, shape: tuple[int, ...], beta: float, num_eig: int | None,
            tol: float) -> tuple[FloatArray, FloatArray]:
    """:func:`_low_rank_factor` of the points in `y_bytes` (float64, `shape`), read-only."""
    y = np.frombuffer(y_bytes, dtype=np.float64).reshape(shape)
    lmat = pivoted_cholesky(y, beta, num_eig, tol)
    lam, v = np.linalg.eigh(lmat.T @ lmat)
    q, lam = _ordered(lmat, lam, v, True)
    off = q.T @ q
    off.flat[:: len(lam) + 1] -= 1.0
    if not float(np.max(np.abs(off))) <= FACTOR_GRAM_ORTHO_TOL:
        # eigenvalues near the Gram matrix's rounding (a `num_eig` past the tolerance's
        # rank): its Q is not orthonormal, which the M-step's W and displacement need
        q0, r = np.linalg.qr(lmat)
        lam, v = np.linalg.eigh(r @ r.T)
        q, lam = _ordered(q0, lam, v, False)
    q.setflags(write=False)
    lam.setflags(write=False)
    return q, lam


def _ordered(basis: FloatArray, lam: FloatArray, v: FloatArray, scale: bool
             ) -> tuple[FloatArray, FloatArray]:
    """The eigenpairs `lam`, `v` largest first, the negligible ones dropped, and the
    orthonormal columns ``basis v`` (`scale`: ``basis v diag(lam)^-1/2``)."""
    order = np.argsort(lam)[::-1]
    lam, v = lam[order], v[:, order]
    keep = max(1, int(np.sum(lam > np.finfo(np.float64).eps * float(lam[0]) * 1e-4)))
    lam = np.ascontiguousarray(lam[:keep])
    cols = v[:, :keep] / np.sqrt(lam) if scale else v[:, :keep]
    return np.ascontiguousarray(basis @ cols), lam


#: :func:`_factor`, the last 32 kept. On the 73 full-resolution 永 glyphs 405 of a tree's
#: 1398 factors repeat one made before in the same process (the finishes' and the stored
#: finishes' root model among them); the last 32 catch 386 of them (the last 8 only
#: 190). With the Gram route, the tree's factors took 0.9 s instead of 1.9 s (one
#: process). A benchmark that times the same CPD again calls
#: ``_cached_factor.cache_clear()`` first.
_cached_factor = functools.lru_cache(maxsize=32)(_factor)
#: Largest model (points) whose factor is kept: the tree's working resolution and its
#: stored-resolution control points (at rank 150, 0.7 MB a factor).
FACTOR_CACHE_MAX_POINTS = 600
#: The Gram route's Q is used when it is orthonormal to this (max |Q^T Q - I|), else the
#: QR route's: with the trace tolerance's rank, 2e-13 (rank 37) to 1e-7 (rank 144) on a
#: 400-point glyph; with a `num_eig` past it, eigenvalues at the Gram matrix's rounding
#: (1e-17 of the largest) left 0.2-0.5.
FACTOR_GRAM_ORTHO_TOL = 1e-6


def _mstep_dense(g: FloatArray, y: FloatArray, est: _EStepOut, reg: float) -> FloatArray:
    """Solve ``(d(P1) G + reg I) W = P X - d(P1) Y`` in the symmetric positive-definite form.

    With ``S = d(sqrt(P1))`` and ``W = S V``: ``(S G S + reg I) V = S^-1 (P X - d(P1) Y)``,
    which needs no division by ``P1`` (rows with ``P1 = 0`` have a zero right-hand side and
    ``W = 0``, as in the unsymmetric form) and is SPD with eigenvalues ``>= reg``.
    """
    p1 = est.p1
    s = np.sqrt(p1)
    f = est.px - p1[:, None] * y
    rhs = np.divide(f, s[:, None], out=np.zeros_like(f), where=s[:, None] > 0)
    k = g * s[:, None]
    k *= s[None, :]
    k.flat[:: len(k) + 1] += reg
    return s[:, None] * _spd_solve(k, rhs)


def _spd_solve(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cholesky solve of an SPD system; if rounding made it indefinite (a kernel that is
    numerically rank-deficient next to a vanishing ``lambda sigma^2``, e.g. ``beta`` far
    larger than the data), add a ridge of ``1e-12 * max(diag)`` and retry.

    LAPACK's ``potrf``/``potrs`` are called directly: the same routines as
    ``scipy.linalg.cho_factor``/``cho_solve`` (the same result, bit for bit), without their
    argument checks, which cost as much as the solve itself on the k x k systems of the
    low-rank M-step (about 0.4 of 0.8 ms per iteration at 400 points).
    """
    x = _cholesky_solve(a, b)
    if x is not None:
        return x
    ridge = 1e-12 * float(np.max(np.abs(np.diag(a)))) + np.finfo(np.float64).tiny
    a = a.copy()
    a.flat[:: len(a) + 1] += ridge
    x = _cholesky_solve(a, b)
    if x is not None:
        return x
    out: FloatArray = np.asarray(np.linalg.lstsq(a, b, rcond=None)[0], dtype=np.float64)
    return out


class LowRankMStep:
    """The low-rank M-step of one CPD run, its kernel ``G ~= Q diag(lam) Q^T`` fixed
    (:func:`_low_rank_factor`): :meth:`solve` gives ``(w, disp)`` as
    :func:`_mstep_low_rank` does, with the EM loop's next sums.

    The compiled pass (``_ckernel.lowrank_mstep``) solves the same system by Cholesky,
    equal to rounding (1e-15 of the displacement), up to rank
    :data:`COMPILED_MSTEP_MAX_RANK`; it reads ``Q`` row by row, padded with zeros to a
    multiple of 8 columns, copied once per run. Where it finds the system not numerically
    positive definite, above that rank, or without it, :func:`_mstep_low_rank` solves it.
    """

    def __init__(self, q: FloatArray, lam: FloatArray) -> None:
        self.q = q
        self.lam = np.ascontiguousarray(lam, dtype=np.float64)
        self._padded: FloatArray | None = None

    def solve(self, y: FloatArray, est: _EStepOut, reg: float
              ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """``(w, disp, sums)``: the M-step, and when the compiled pass
        solved it the sums the EM loop reads next, taken in the same pass over the rows
        (with ``t = y + disp``): ``sum P1``, ``sum_m P1_m |t_m|^2``, ``sum PX * t``,
        ``sum w * disp`` (the regulariser's ``tr(W^T G W)``, as ``G W = disp``) and 1.0
        when every ``w`` and ``t`` is finite (else 0.0); None when numpy solved it."""
        ck = _switch.CKERNEL
        if ck is not None and len(self.lam) <= COMPILED_MSTEP_MAX_RANK:
            if self._padded is None:
                m, k = self.q.shape
                self._padded = np.zeros((m, -(-k // 8) * 8))
                self._padded[:, :k] = self.q
            w = np.empty((len(y), 2))
            disp = np.empty((len(y), 2))
            sums = np.empty(5)
            if ck.lowrank_mstep(self._padded, self.lam, np.ascontiguousarray(y, np.float64),
                                np.ascontiguousarray(est.p1, np.float64),
                                np.ascontiguousarray(est.px, np.float64), float(reg), w, disp,
                                False, sums):
                return w, disp, sums
        w, disp = _mstep_low_rank(self.q, self.lam, y, est, reg)
        return w, disp, None


def _cholesky_solve(a: FloatArray, b: FloatArray) -> FloatArray | None:
    """``a^-1 b`` by Cholesky, or None when ``a`` is not numerically positive definite."""
    c, info = _POTRF(a, lower=False, clean=False, overwrite_a=False)
    if info != 0:
        return None
    x, info = _POTRS(c, b, lower=False, overwrite_b=False)
    if info != 0:
        return None
    return np.asarray(x, dtype=np.float64)


def _mstep_low_rank(q: FloatArray, lam: FloatArray, y: FloatArray, est: _EStepOut,
                    reg: float) -> tuple[FloatArray, FloatArray]:
    """Low-rank M-step (the CPD paper's fast variant) with ``G ~= Q diag(lam) Q^T``.

    MATLAB's ``cpd_GRBF_lowrank`` solves ``(reg lam^-1 + Q^T d(P1) Q) z = Q^T F`` with
    ``F = P X - d(P1) Y`` (Woodbury), and moves the centroids by ``Q diag(lam) Q^T W``,
    which only depends on ``Q^T W``.  We keep ``W = Q a`` in the span of ``Q`` (so the
    exact kernel reproduces the displacement: ``G W = Q diag(lam) a`` up to the dropped
    spectrum) and solve directly for the displacement coefficients ``v = diag(lam) a``:
    ``(Q^T d(P1) Q + reg diag(1/lam)) v = Q^T F``, an SPD ``k x k`` system.

    Returns
    -------
    w : ndarray (M, 2)
        Kernel weights ``Q a``.
    disp : ndarray (M, 2)
        Displacement ``Q v`` (the new centroids are ``Y + disp``).
    """
    p1 = est.p1
    f = est.px - p1[:, None] * y
    h = q.T @ (q * p1[:, None])
    h.flat[:: len(h) + 1] += reg / lam
    v = _spd_solve(h, q.T @ f)
    return q @ (v / lam[:, None]), q @ v

"""CPD's M-step: the dense SPD solve and the low-rank kernel with the Woodbury solve."""

from __future__ import annotations

import numpy as np
import scipy.linalg

from ._estep import _EStepOut
from ._field import FloatArray

#: Automatic low-rank: dropped kernel eigenvalues are below this fraction of the largest.
LOW_RANK_RTOL = 1e-12


def _low_rank_factor(g: FloatArray, num_eig: int | None) -> tuple[FloatArray, FloatArray]:
    """``(Q, lam)`` with ``G ~= Q diag(lam) Q^T``, ``Q`` orthonormal: leading eigenpairs.

    With ``num_eig=None`` the rank is the number of eigenvalues above
    ``LOW_RANK_RTOL * lambda_max``; otherwise exactly ``num_eig`` (fewer if ``G`` has fewer
    positive eigenvalues).  Uses a randomised range finder with one power iteration
    (Halko et al. 2011) and a fixed seed, doubling the sketch until the spectrum below the
    threshold is reached; a full ``eigh`` when the sketch would exceed half of ``M``.
    """
    m = len(g)
    rng = np.random.default_rng(0)
    sketch = min(m, (num_eig + 16) if num_eig is not None else 64)
    while True:
        if 2 * sketch >= m:
            lam, q = scipy.linalg.eigh(g)
            full = True
        else:
            z = g @ rng.standard_normal((m, sketch))
            q, _ = np.linalg.qr(z)
            q, _ = np.linalg.qr(g @ q)
            gq = g @ q
            bmat = q.T @ gq
            bmat = 0.5 * (bmat + bmat.T)
            lam, v = np.linalg.eigh(bmat)
            q = q @ v
            full = False
        order = np.argsort(lam)[::-1]
        lam = lam[order]
        q = q[:, order]
        lam_max = float(lam[0])
        if num_eig is not None:
            keep = min(num_eig, int(np.sum(lam > 0)))
        else:
            keep = int(np.sum(lam > LOW_RANK_RTOL * lam_max))
            if keep == len(lam) and not full:
                sketch = min(m, 2 * sketch)
                continue
        keep = max(keep, 1)
        lam_k = np.maximum(lam[:keep], np.finfo(np.float64).tiny)
        return np.ascontiguousarray(q[:, :keep]), lam_k


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
    larger than the data), add a ridge of ``1e-12 * max(diag)`` and retry."""
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(a, check_finite=False), b,
                                      check_finite=False)
    except np.linalg.LinAlgError:
        ridge = 1e-12 * float(np.max(np.abs(np.diag(a)))) + np.finfo(np.float64).tiny
        a = a.copy()
        a.flat[:: len(a) + 1] += ridge
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(a, check_finite=False), b,
                                          check_finite=False)
        except np.linalg.LinAlgError:
            out: FloatArray = np.asarray(np.linalg.lstsq(a, b, rcond=None)[0], dtype=np.float64)
            return out


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

"""The pycpd backend of :func:`cpd_nonrigid`: ``pycpd.DeformableRegistration`` run on the
same normalised data, as a reference."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from .._executor import checkpoint
from ._field import FloatArray


def _run_pycpd(x: FloatArray, y: FloatArray, xs: float, beta: float, lmbda: float, w: float,
               tol: float, max_iter: int, s2: float,
               callback: Callable[[int, float, float], None] | None
               ) -> tuple[FloatArray, FloatArray, float, int, bool]:
    """Fit with pycpd; returns ``(W, G, sigma2, iterations, converged)`` in normalised units.

    Its stopping rule is pycpd's (``|sigma2 - sigma2_old| <= tol``), and the callback's
    objective is that difference.  Raises ``FloatingPointError`` on non-finite output.
    """
    from pycpd import DeformableRegistration

    reg = DeformableRegistration(X=x.copy(), Y=y.copy(), alpha=lmbda, beta=beta, w=w,
                                 tolerance=tol, max_iterations=max_iter, sigma2=s2)

    def _cb(**kwargs: Any) -> None:
        checkpoint()
        if callback is not None:
            callback(int(kwargs["iteration"]), float(reg.sigma2) * xs * xs, float(reg.diff))

    reg.register(_cb)
    wmat = np.asarray(reg.W, dtype=np.float64)
    s2_out = float(reg.sigma2)
    if not (np.isfinite(wmat).all() and np.isfinite(reg.TY).all() and math.isfinite(s2_out)
            and s2_out > 0):
        raise FloatingPointError("pycpd produced non-finite values (W, TY or sigma2)")
    converged = bool(reg.diff <= tol)
    return wmat, np.asarray(reg.G), s2_out, int(reg.iteration), converged

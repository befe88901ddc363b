"""Coherent Point Drift, non-rigid (Myronenko & Song 2010), in numpy/scipy.

This module implements the Gaussian-RBF non-rigid CPD of the reference MATLAB code
(``cpd_GRBF.m`` called from ``cpd_register.m``) with the same defaults and stopping rule,
plus three optional accelerations, each exact to within a stated tolerance of the dense
float64 computation:

* a vectorised, chunked E-step: the exponents ``-|x - t|^2 / (2 sigma^2)`` of one block of
  subject points come out of a single BLAS product of augmented 4-column matrices (no
  ``M x N x D`` temporary), the exponential is taken in place, and ``P1``, ``Pt1`` and ``P X``
  come out of one more product, without ever normalising ``P`` explicitly;
* a low-rank kernel ``G ~= U U^T`` (randomised eigendecomposition, rank chosen from the
  spectrum) with the Woodbury M-step of the paper's fast variant;
* a truncated E-step once sigma is small: only pairs closer than a radius derived from a
  rigorous bound on the dropped mass are evaluated (``scipy.spatial.cKDTree``), giving a
  sparse ``P``.

Conventions: ``model`` is ``Y`` in the CPD paper (M x 2, the GMM centroids, the set that
moves) and ``subject`` is ``X`` (N x 2, the data).  The kernel is
``G[i, j] = exp(-|y_i - y_j|^2 / (2 beta^2))`` and the transform is ``T = Y + G W``.
"""

from __future__ import annotations

import contextlib
import math
import numbers
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from ._executor import checkpoint
from ._points import as_points

__all__ = ["CPDResult", "NonrigidTransform", "cpd_nonrigid"]

FloatArray = NDArray[np.float64]

# --- numerical constants (see the docstring of ``cpd_nonrigid`` for what they mean) -------
#: sigma^2 floor, relative to the mean squared norm of the centred subject (which is 1 in
#: normalised coordinates).  MATLAB's cpd_GRBF stops once sigma2 <= 1e-8 (normalised).
SIGMA2_FLOOR_REL = 1e-8
#: Relative bound on every posterior changed by the truncated E-step.
TRUNCATION_EPS = 1e-10
#: The truncated E-step's neighbour list is built with this multiple of the radius, so it
#: can be reused while the centroids move by less than the difference.
TRUNCATION_SKIN = 1.3
#: ... and rebuilt when its radius exceeds this multiple of the current radius.
TRUNCATION_SHRINK = 1.8
#: Automatic low-rank: dropped kernel eigenvalues are below this fraction of the largest.
LOW_RANK_RTOL = 1e-12
#: Automatic low-rank switches on for more model points than this (measured crossover of a
#: per-iteration Cholesky against the one-off randomised eigendecomposition; bench_cpd.py).
AUTO_LOW_RANK_MIN_M = 150
#: Automatic truncation switches on when the estimated fraction of (model, subject) pairs
#: within the truncation radius is below this (dense float64 / float32 E-step).
AUTO_TRUNCATE_MAX_DENSITY = {"float64": 0.15, "float32": 0.05}
#: Elements of one E-step block (M x block columns), bounds the E-step's memory.
_BLOCK_ELEMS = 1 << 22
_DEN_FLOOR = 1e-300
#: BLAS threads used during a call (via threadpoolctl when it is installed; ``None`` leaves
#: the BLAS alone).  The heavy BLAS calls here are memory-bound products with 3-4 columns,
#: which gain little from threads, while a threaded OpenBLAS on an oversubscribed machine
#: (several workers / test runs on 2 cores) was measured 5-10x slower than one thread.
BLAS_THREADS: int | None = 1
_controller: Any = None


@contextlib.contextmanager
def _blas_limit() -> Iterator[None]:
    global _controller
    if BLAS_THREADS is None:
        yield
        return
    if _controller is None:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:  # optional dependency
            _controller = False
        else:
            _controller = ThreadpoolController()
    if not _controller:
        yield
        return
    with _controller.limit(limits=BLAS_THREADS, user_api="blas"):
        yield


# ----------------------------------------------------------------------------------------
# results
# ----------------------------------------------------------------------------------------
def _readonly(a: ArrayLike, dtype: Any = np.float64) -> NDArray[Any]:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def _gauss_kernel(a: FloatArray, b: FloatArray, beta: float) -> FloatArray:
    """``exp(-|a_i - b_j|^2 / (2 beta^2))`` computed from coordinate differences."""
    k = np.subtract.outer(a[:, 0], b[:, 0])
    np.square(k, out=k)
    d1 = np.subtract.outer(a[:, 1], b[:, 1])
    np.square(d1, out=d1)
    k += d1
    k *= -0.5 / (beta * beta)
    np.exp(k, out=k)
    return k


@dataclass(frozen=True, eq=False)
class NonrigidTransform:
    """A fitted CPD Gaussian-RBF displacement field that can warp any 2D points.

    For caller-coordinate points ``p`` the warp is::

        z = (p - model_shift) / model_scale
        out = (z + G(z, control_points) @ coefficients) * subject_scale + subject_shift

    with ``G(a, b)[i, j] = exp(-|a_i - b_j|^2 / (2 beta^2))``.  ``control_points`` are the
    normalised model points the field was fitted on (``Y`` of the CPD paper) and
    ``coefficients`` the weights ``W``.

    Attributes
    ----------
    control_points : ndarray, shape (M, 2)
        Normalised model points (kernel centres).
    coefficients : ndarray, shape (M, 2)
        Kernel weights ``W``.
    beta : float
        Kernel width, in normalised units.
    model_shift, subject_shift : ndarray, shape (2,)
        Translations of the model and subject normalisations.
    model_scale, subject_scale : float
        Scales of the model and subject normalisations.
    """

    control_points: FloatArray
    coefficients: FloatArray
    beta: float
    model_shift: FloatArray
    model_scale: float
    subject_shift: FloatArray
    subject_scale: float

    def __post_init__(self) -> None:
        cp = _readonly(self.control_points)
        co = _readonly(self.coefficients)
        if cp.ndim != 2 or cp.shape[1] != 2 or co.shape != cp.shape:
            raise ValueError(
                "control_points and coefficients must both have shape (M, 2); "
                f"got {cp.shape} and {co.shape}"
            )
        for name, v in (("beta", self.beta), ("model_scale", self.model_scale),
                        ("subject_scale", self.subject_scale)):
            if not (math.isfinite(float(v)) and float(v) > 0):
                raise ValueError(f"{name} must be a positive finite number; got {v!r}")
        object.__setattr__(self, "control_points", cp)
        object.__setattr__(self, "coefficients", co)
        object.__setattr__(self, "model_shift", _readonly(self.model_shift).reshape(2))
        object.__setattr__(self, "subject_shift", _readonly(self.subject_shift).reshape(2))
        object.__setattr__(self, "beta", float(self.beta))
        object.__setattr__(self, "model_scale", float(self.model_scale))
        object.__setattr__(self, "subject_scale", float(self.subject_scale))

    def apply(self, points: ArrayLike) -> FloatArray:
        """Warp points given in the model's (caller's) coordinates.

        Parameters
        ----------
        points : array_like, shape (K, 2)
            Points to warp; ``K`` may be 0.

        Returns
        -------
        ndarray, shape (K, 2)
            Warped points in the subject's (caller's) coordinates.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must have shape (k, 2); got {p.shape}")
        z = (p - self.model_shift) / self.model_scale
        out = z.copy()
        m = max(1, len(self.control_points))
        step = max(1, _BLOCK_ELEMS // m)
        for a in range(0, len(z), step):
            g = _gauss_kernel(z[a:a + step], self.control_points, self.beta)
            out[a:a + step] += g @ self.coefficients
        out *= self.subject_scale
        out += self.subject_shift
        return out

    __call__ = apply

    def __repr__(self) -> str:  # short: the arrays are not printed
        from ._repr import nonrigid_repr

        return nonrigid_repr(self)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable representation (nested lists of floats).

        Returns
        -------
        dict
            Keys ``kind``, ``version``, ``beta``, ``control_points``, ``coefficients``,
            ``model_shift``, ``model_scale``, ``subject_shift``, ``subject_scale``.
        """
        return {
            "kind": "cpd_nonrigid",
            "version": 1,
            "beta": self.beta,
            "control_points": self.control_points.tolist(),
            "coefficients": self.coefficients.tolist(),
            "model_shift": self.model_shift.tolist(),
            "model_scale": self.model_scale,
            "subject_shift": self.subject_shift.tolist(),
            "subject_scale": self.subject_scale,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> NonrigidTransform:
        """Rebuild a transform from :meth:`to_dict` output.

        Parameters
        ----------
        data : dict
            As returned by :meth:`to_dict` (possibly after a JSON round trip).

        Returns
        -------
        NonrigidTransform
        """
        if data.get("kind") != "cpd_nonrigid" or data.get("version") != 1:
            raise ValueError(
                "not a serialised NonrigidTransform (expected kind 'cpd_nonrigid', version 1); "
                f"got kind={data.get('kind')!r}, version={data.get('version')!r}"
            )
        cp = np.asarray(data["control_points"], dtype=np.float64).reshape(-1, 2)
        co = np.asarray(data["coefficients"], dtype=np.float64).reshape(-1, 2)
        return cls(
            control_points=cp,
            coefficients=co,
            beta=float(data["beta"]),
            model_shift=np.asarray(data["model_shift"], dtype=np.float64),
            model_scale=float(data["model_scale"]),
            subject_shift=np.asarray(data["subject_shift"], dtype=np.float64),
            subject_scale=float(data["subject_scale"]),
        )


@dataclass(frozen=True, eq=False)
class CPDResult:
    """Outcome of :func:`cpd_nonrigid`.

    Attributes
    ----------
    warped : ndarray, shape (M, 2)
        The model points moved onto the subject, in the caller's coordinates; equal to
        ``transform.apply(model)``.
    transform : NonrigidTransform
        The fitted displacement field; warps any points.
    correspondence : ndarray of int, shape (M,)
        For each model point ``m``, the subject index ``n`` maximising the posterior
        ``P(m | x_n)`` at the final ``warped`` positions and ``sigma2``.
    probability : ndarray, shape (M,)
        That maximum, ``max_n P(m | x_n)``, in ``[0, 1]``.  ``P(m | x_n)`` is the CPD
        posterior of centroid ``m`` given data point ``x_n`` (it sums to at most 1 over ``m``,
        the remainder being the outlier class), so a value near 1 means some subject point
        is explained by this model point alone.
    sigma2 : float
        Final GMM variance, in the caller's subject units squared.
    iterations : int
        EM iterations performed.
    converged : bool
        True if the stopping rule fired (relative change of the objective ``<= tol``, or
        sigma^2 reached its floor); False if ``max_iter`` was reached or the run stopped on a
        non-finite value (the last finite iterate is returned).
    objective : float
        Negative log-likelihood plus ``lambda/2 tr(W^T G W)`` at the last E-step, in
        normalised units (``nan`` for the pycpd backend, which does not compute it).
    """

    warped: FloatArray
    transform: NonrigidTransform
    correspondence: NDArray[np.intp]
    probability: FloatArray
    sigma2: float
    iterations: int
    converged: bool
    objective: float = float("nan")

    def __repr__(self) -> str:  # short: the arrays are not printed
        from ._repr import cpd_repr

        return cpd_repr(self)


# ----------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------
def _real(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise ValueError(f"{name} must be a real number; got {v!r}")
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"{name} must be finite; got {v!r}")
    return f


def _check_params(beta: Any, lmbda: Any, w: Any, tol: Any, max_iter: Any, sigma2: Any,
                  num_eig: Any, dtype: Any, backend: Any, low_rank: Any, truncate: Any,
                  normalize: Any, callback: Any, m: int) -> None:
    if _real("beta", beta) <= 0:
        raise ValueError(f"beta must be > 0; got {beta!r}")
    if _real("lmbda", lmbda) <= 0:
        raise ValueError(f"lmbda must be > 0; got {lmbda!r}")
    if not 0 <= _real("w", w) < 1:
        raise ValueError(f"w must satisfy 0 <= w < 1; got {w!r}")
    if _real("tol", tol) < 0:
        raise ValueError(f"tol must be >= 0; got {tol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ValueError(f"max_iter must be an integer >= 1; got {max_iter!r}")
    if sigma2 is not None and _real("sigma2", sigma2) <= 0:
        raise ValueError(f"sigma2 must be > 0 or None; got {sigma2!r}")
    if num_eig is not None and (isinstance(num_eig, bool)
                                or not isinstance(num_eig, numbers.Integral)
                                or not 1 <= int(num_eig) <= m):
        raise ValueError(f"num_eig must be None or an integer in [1, {m}]; got {num_eig!r}")
    if dtype not in ("float64", "float32"):
        raise ValueError(f"dtype must be 'float64' or 'float32'; got {dtype!r}")
    if backend not in ("native", "pycpd"):
        raise ValueError(f"backend must be 'native' or 'pycpd'; got {backend!r}")
    for name, v in (("low_rank", low_rank), ("truncate", truncate)):
        if v is not None and not isinstance(v, bool | np.bool_):
            raise ValueError(f"{name} must be True, False or None; got {v!r}")
    if not isinstance(normalize, bool | np.bool_):
        raise ValueError(f"normalize must be True or False; got {normalize!r}")
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable or None; got {callback!r}")


# ----------------------------------------------------------------------------------------
# normalisation
# ----------------------------------------------------------------------------------------
def _normalisation(pts: FloatArray) -> tuple[FloatArray, float]:
    """Mean and RMS scale of ``pts`` (MATLAB's cpd_normalize); scale 1 if degenerate."""
    shift = pts.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((pts - shift) ** 2, axis=1))))
    ref = float(np.max(np.abs(pts))) if pts.size else 0.0
    if not (scale > 1e-12 * max(ref, 1.0)):
        scale = 1.0
    return shift, scale


# ----------------------------------------------------------------------------------------
# E-step
# ----------------------------------------------------------------------------------------
@dataclass
class _EStepOut:
    p1: FloatArray  # (M,) row sums of P
    pt1: FloatArray  # (N,) column sums of P
    px: FloatArray  # (M, 2) P @ X
    nll: float  # -sum(log den) + N D/2 log sigma2 (MATLAB's cpd_P objective)
    nnz: int  # pairs evaluated (M*N when dense)


def _outlier_const(sigma2: float, w: float, m: int, n: int) -> float:
    # (2 pi sigma2)^(D/2) w/(1-w) M/N with D = 2
    return 2.0 * math.pi * sigma2 * w / (1.0 - w) * m / n


class _EStep:
    """Workspace for repeated E-steps against a fixed subject ``x`` (normalised)."""

    def __init__(self, x: FloatArray, m: int, w: float, dtype: str) -> None:
        self.x = x
        self.n = len(x)
        self.m = m
        self.w = w
        self.dtype = np.dtype(dtype)
        self.xsq = np.einsum("ij,ij->i", x, x)
        self.block = max(1, min(self.n, _BLOCK_ELEMS // max(m, 1)))
        self._buf64 = np.empty(m * self.block)
        self._buf32 = np.empty(m * self.block, dtype=np.float32) if dtype == "float32" else None
        self._tree_x: cKDTree | None = None
        # neighbour list of the truncated E-step
        self.max_density = 1.0
        self.force_truncate = False
        self._pi: NDArray[np.intp] | None = None
        self._pj: NDArray[np.intp] | None = None
        self._xj: FloatArray | None = None
        self._t_build: FloatArray | None = None
        self._r_build = 0.0

    @property
    def tree_x(self) -> cKDTree:
        if self._tree_x is None:
            self._tree_x = cKDTree(self.x)
        return self._tree_x

    # -- dense -------------------------------------------------------------------------
    def dense(self, t: FloatArray, sigma2: float) -> _EStepOut:
        m, n, x = self.m, self.n, self.x
        c = _outlier_const(sigma2, self.w, m, n)
        inv2s = 0.5 / sigma2
        # exponent[m, n] = (t_m . x_n)/s2 - |t_m|^2/(2 s2) - |x_n|^2/(2 s2) = ta @ xa.T
        ta = np.empty((m, 4))
        ta[:, :2] = t
        ta[:, 2] = -inv2s * np.einsum("ij,ij->i", t, t)
        ta[:, 3] = 1.0
        p1 = np.zeros(m)
        px = np.zeros((m, 2))
        pt1 = np.empty(n)
        nll = 0.0
        ones = np.ones(m, dtype=self.dtype)
        for a in range(0, n, self.block):
            b = min(n, a + self.block)
            k = b - a
            xa = np.empty((4, k))
            xa[:2] = x[a:b].T / sigma2
            xa[2] = 1.0
            xa[3] = -inv2s * self.xsq[a:b]
            e64 = self._buf64[: m * k].reshape(m, k)
            np.matmul(ta, xa, out=e64)
            np.minimum(e64, 0.0, out=e64)  # exact value is <= 0; drop rounding
            if self._buf32 is not None:
                e: NDArray[Any] = self._buf32[: m * k].reshape(m, k)
                e[...] = e64
            else:
                e = e64
            np.exp(e, out=e)
            colsum = (ones @ e).astype(np.float64)
            den = colsum + c
            np.maximum(den, _DEN_FLOOR, out=den)
            inv = 1.0 / den
            rhs = np.empty((k, 3), dtype=self.dtype)
            rhs[:, :2] = x[a:b] * inv[:, None]
            rhs[:, 2] = inv
            acc = (e @ rhs).astype(np.float64)
            px += acc[:, :2]
            p1 += acc[:, 2]
            pt1[a:b] = colsum * inv
            nll -= float(np.sum(np.log(den)))
        nll += n * math.log(sigma2)  # N D/2 log sigma2, D = 2
        return _EStepOut(p1, pt1, px, nll, m * n)

    # -- truncated ---------------------------------------------------------------------
    def radius(self, t: FloatArray, sigma2: float) -> float:
        """Truncation radius: dropped terms change no posterior by more than TRUNCATION_EPS.

        Every dropped term is ``<= tau = exp(-r^2 / (2 sigma2))`` and there are at most ``M``
        of them per subject point, so the relative change of each denominator, hence of every
        kept posterior, is ``<= M tau / den_min`` and every dropped posterior is
        ``<= tau / den_min``.  With ``w > 0``, ``den >= c`` (outlier constant); with ``w = 0``
        ``den_n >= exp(-d_n^2 / (2 sigma2))`` with ``d_n`` the distance from ``x_n`` to the
        nearest centroid, so ``r^2 = max_n d_n^2 + 2 sigma2 log(M / eps)``.
        """
        m = self.m
        if self.w > 0:
            c = _outlier_const(sigma2, self.w, m, self.n)
            return math.sqrt(2.0 * sigma2 * math.log(m / (TRUNCATION_EPS * min(c, 1.0))))
        dmin, _ = cKDTree(t).query(self.x, k=1)
        return math.sqrt(float(np.max(dmin)) ** 2
                         + 2.0 * sigma2 * math.log(m / TRUNCATION_EPS))

    def density(self, t: FloatArray, r: float, sample: NDArray[np.intp]) -> float:
        """Estimated fraction of pairs within ``r`` (from a fixed sample of centroids)."""
        counts = self.tree_x.query_ball_point(t[sample], r, return_length=True)
        return float(np.mean(counts)) / self.n

    def truncated(self, t: FloatArray, sigma2: float, r: float) -> _EStepOut | None:
        """Sparse E-step over all pairs closer than ``r`` (and possibly a few more).

        Candidate pairs come from a neighbour list built with a larger radius
        ``r_build = TRUNCATION_SKIN * r`` around the centroids ``t_build`` (one
        ``cKDTree.sparse_distance_matrix``).  The list stays valid while
        ``r + max_m |t_m - t_build_m| <= r_build``: then every pair now closer than ``r``
        was closer than ``r_build`` at build time (triangle inequality), so it is in the
        list.  Extra pairs in the list are evaluated exactly, which only adds accuracy.
        A list built for a radius more than ``TRUNCATION_SHRINK * r`` is rebuilt.
        Returns None (caller falls back to dense) if a rebuilt list holds more than
        ``max_density`` of all pairs.
        """
        m, n = self.m, self.n
        if not self._list_valid(t, r):
            if not self._build_list(t, TRUNCATION_SKIN * r):
                return None
        i, j, xj = self._pi, self._pj, self._xj
        assert i is not None and j is not None and xj is not None
        c = _outlier_const(sigma2, self.w, m, n)
        ti = t[i]
        ti -= xj
        np.square(ti, out=ti)
        e = ti[:, 0] + ti[:, 1]
        e *= -0.5 / sigma2
        np.exp(e, out=e)
        colsum = np.bincount(j, weights=e, minlength=n)
        den = colsum + c
        np.maximum(den, _DEN_FLOOR, out=den)
        inv = 1.0 / den
        e *= inv[j]  # e is now P on the listed pairs
        p1: FloatArray = np.bincount(i, weights=e, minlength=m).astype(np.float64)
        px = np.empty((m, 2))
        px[:, 0] = np.bincount(i, weights=e * xj[:, 0], minlength=m)
        px[:, 1] = np.bincount(i, weights=e * xj[:, 1], minlength=m)
        pt1 = colsum * inv
        nll = -float(np.sum(np.log(den))) + n * math.log(sigma2)
        return _EStepOut(p1, pt1, px, nll, len(e))

    def _list_valid(self, t: FloatArray, r: float) -> bool:
        if self._pi is None or self._t_build is None:
            return False
        if self._r_build > TRUNCATION_SHRINK * r:  # list much too loose: rebuild
            return False
        d = t - self._t_build
        return r + math.sqrt(float(np.max(np.einsum("ij,ij->i", d, d)))) <= self._r_build

    def _build_list(self, t: FloatArray, r_build: float) -> bool:
        pairs = cKDTree(t).sparse_distance_matrix(self.tree_x, r_build, output_type="ndarray")
        if len(pairs) > self.max_density * self.m * self.n and not self.force_truncate:
            self._pi = None
            return False
        self._pi = pairs["i"].astype(np.intp)
        self._pj = pairs["j"].astype(np.intp)
        self._xj = self.x[self._pj]
        self._t_build = t.copy()
        self._r_build = r_build
        return True


def _posterior_max(t: FloatArray, x: FloatArray, sigma2: float, w: float
                   ) -> tuple[NDArray[np.intp], FloatArray]:
    """For each centroid, ``argmax_n`` and ``max_n`` of ``P(m | x_n)`` (dense, chunked)."""
    m, n = len(t), len(x)
    c = _outlier_const(sigma2, w, m, n)
    best = np.full(m, -1.0)
    arg = np.zeros(m, dtype=np.intp)
    step = max(1, _BLOCK_ELEMS // m)
    for a in range(0, n, step):
        b = min(n, a + step)
        e = _gauss_kernel(t, x[a:b], math.sqrt(sigma2))
        den = e.sum(axis=0) + c
        np.maximum(den, _DEN_FLOOR, out=den)
        e /= den
        k = np.argmax(e, axis=1)
        v = e[np.arange(m), k]
        better = v > best
        best[better] = v[better]
        arg[better] = k[better] + a
    return arg, np.clip(best, 0.0, 1.0)


# ----------------------------------------------------------------------------------------
# M-step
# ----------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------
# main entry point
# ----------------------------------------------------------------------------------------
def cpd_nonrigid(
    model: ArrayLike,
    subject: ArrayLike,
    *,
    beta: float = 2.0,
    lmbda: float = 3.0,
    w: float = 0.1,
    tol: float = 1e-5,
    max_iter: int = 150,
    sigma2: float | None = None,
    normalize: bool = True,
    low_rank: bool | None = None,
    num_eig: int | None = None,
    dtype: str = "float64",
    truncate: bool | None = None,
    backend: Literal["native", "pycpd"] = "native",
    callback: Callable[[int, float, float], None] | None = None,
) -> CPDResult:
    """Non-rigid Coherent Point Drift: move ``model`` onto ``subject``.

    Follows the reference MATLAB implementation (``cpd_GRBF.m``): EM on a Gaussian
    mixture whose centroids ``T = Y + G W`` are the warped model points, with an outlier
    component of weight ``w``.

    Parameters
    ----------
    model : array_like, shape (M, 2)
        Points to move (``Y`` in the CPD paper, the GMM centroids).  ``M >= 3``, finite.
    subject : array_like, shape (N, 2)
        Target points (``X`` in the CPD paper).  ``N >= 3``, finite.
    beta : float, default 2.0
        Width of the Gaussian kernel, in normalised units when ``normalize`` (else in the
        caller's units).
    lmbda : float, default 3.0
        Regularisation weight (``lambda`` in the paper, ``alpha`` in pycpd).
    w : float, default 0.1
        Weight of the uniform outlier component, ``0 <= w < 1``.
    tol : float, default 1e-5
        Stop when the relative change of the objective ``|L - L_old| / |L| <= tol``, where
        ``L`` is the negative log-likelihood plus ``lmbda/2 tr(W^T G W)`` (as MATLAB).
        ``tol=0`` runs exactly ``max_iter`` iterations (unless sigma^2 reaches its floor).
    max_iter : int, default 150
        Maximum number of EM iterations.
    sigma2 : float, optional
        Initial variance, in the subject's units squared.  Default: the sum of all squared
        model-subject distances divided by ``D M N``.
    normalize : bool, default True
        Normalise both sets to zero mean and unit RMS radius internally (MATLAB's
        ``opt.normalize=1``).  Results are always returned in the caller's coordinates.
        With ``False`` both sets are still shifted by the subject mean internally (CPD is
        translation-equivariant, so this only improves rounding).
    low_rank : bool, optional
        Use the low-rank kernel ``G ~= U U^T`` and the Woodbury M-step.  ``None``: on when
        ``M > AUTO_LOW_RANK_MIN_M`` (150).
    num_eig : int, optional
        Rank of the low-rank kernel.  ``None``: keep every eigenvalue above
        ``1e-12 * lambda_max`` (numerically the exact kernel).
    dtype : {"float64", "float32"}, default "float64"
        Precision of the dense E-step's exponentials and products (exponents are always
        formed in float64; the M-step is always float64).
    truncate : bool, optional
        Truncated (sparse) E-step: only pairs within a radius of roughly 9 sigma are
        evaluated, chosen so that no posterior changes by more than ``1e-10`` relatively
        (see ``_EStep.radius``).  ``None``: used on iterations where a cheap sample estimates
        that less than 15% (float64) / 5% (float32) of the pairs lie within the radius.
    backend : {"native", "pycpd"}, default "native"
        ``"pycpd"`` runs ``pycpd.DeformableRegistration`` (alpha=lmbda, beta, w, tolerance,
        max_iterations, sigma2) on the same normalised data as a reference.  Its stopping
        rule is pycpd's (``|sigma2 - sigma2_old| <= tol``) and its callback objective is
        that difference.  ``low_rank``, ``num_eig``, ``dtype`` and ``truncate`` are ignored.
    callback : callable, optional
        ``callback(iteration, sigma2, objective)`` after every iteration (``iteration``
        counts from 1, ``sigma2`` in caller units squared, ``objective`` in normalised
        units).  An exception raised by it propagates unchanged and aborts the run;
        nothing the caller owns has been modified.

    Returns
    -------
    CPDResult

    Raises
    ------
    ValueError
        If an input or parameter is invalid (the message names it).
    FloatingPointError
        Only for ``backend="pycpd"``, if pycpd produced non-finite values.

    Notes
    -----
    * sigma^2 floor: if the update gives ``sigma2 < 1e-8 * s2`` (``s2`` = mean squared norm
      of the centred subject, i.e. 1 in normalised units) or a non-positive value, sigma^2
      is set to that floor and the run stops with ``converged=True`` (MATLAB stops at
      ``sigma2 <= 1e-8``).
    * Non-finite values: if an E- or M-step produces a non-finite objective, ``W`` or
      sigma^2, the previous (finite) iterate is kept and the run stops with
      ``converged=False``.  The result never contains NaN.
    * Tolerances of the accelerations against dense float64 (measured, tests check them):
      low-rank (automatic rank) and truncation change the warped points by less than
      ``1e-6`` of the subject's RMS radius; float32 by less than ``1e-4``.
      ``transform.apply(model)`` equals ``warped`` to ``1e-8`` relative in every mode.
    """
    with _blas_limit():
        return _cpd_nonrigid(model, subject, beta=beta, lmbda=lmbda, w=w, tol=tol,
                             max_iter=max_iter, sigma2=sigma2, normalize=normalize,
                             low_rank=low_rank, num_eig=num_eig, dtype=dtype,
                             truncate=truncate, backend=backend, callback=callback)


def _cpd_nonrigid(model: ArrayLike, subject: ArrayLike, *, beta: Any, lmbda: Any, w: Any,
                  tol: Any, max_iter: Any, sigma2: Any, normalize: Any, low_rank: Any,
                  num_eig: Any, dtype: Any, truncate: Any, backend: Any,
                  callback: Callable[[int, float, float], None] | None) -> CPDResult:
    y_in = as_points(model, name="model")
    x_in = as_points(subject, name="subject")
    m, n = len(y_in), len(x_in)
    _check_params(beta, lmbda, w, tol, max_iter, sigma2, num_eig, dtype, backend, low_rank,
                  truncate, normalize, callback, m)
    beta, lmbda, w, tol = float(beta), float(lmbda), float(w), float(tol)
    max_iter = int(max_iter)

    if normalize:
        xd, xs = _normalisation(x_in)
        yd, ys = _normalisation(y_in)
    else:
        xd = x_in.mean(axis=0)
        yd, xs, ys = xd, 1.0, 1.0
    x = (x_in - xd) / xs
    y = (y_in - yd) / ys
    s2_ref = float(np.mean(np.sum(x * x, axis=1))) if not normalize else 1.0
    if not s2_ref > 0:
        s2_ref = 1.0
    floor = SIGMA2_FLOOR_REL * s2_ref

    if sigma2 is None:
        # sum_{m,n} |x_n - y_m|^2 / (D M N), expanded (MATLAB's cpd_GRBF)
        s2 = float((m * np.sum(x * x) + n * np.sum(y * y)
                    - 2.0 * np.dot(x.sum(axis=0), y.sum(axis=0))) / (2 * m * n))
    else:
        s2 = float(sigma2) / (xs * xs)
    if not (math.isfinite(s2) and s2 > floor):
        s2 = max(floor, s2_ref) if not math.isfinite(s2) else max(s2, floor)

    if backend == "pycpd":
        return _run_pycpd(x, y, xd, xs, yd, ys, beta, lmbda, w, tol, max_iter, s2, callback)

    g = _gauss_kernel(y, y, beta)
    use_low_rank = (m > AUTO_LOW_RANK_MIN_M) if low_rank is None else bool(low_rank)
    basis = _low_rank_factor(g, num_eig) if use_low_rank else None

    estep = _EStep(x, m, w, dtype)
    estep.force_truncate = bool(truncate)
    sample = np.unique(np.linspace(0, m - 1, min(m, 64)).astype(np.intp))
    max_density = AUTO_TRUNCATE_MAX_DENSITY[dtype]
    estep.max_density = max_density

    wmat = np.zeros((m, 2))
    t = y.copy()
    objective = float("nan")
    l_old = float("nan")
    converged = False
    it = 0
    while it < max_iter:
        checkpoint()  # a serial executor's cancellation check (no-op in pool processes)
        # ---- E-step
        est: _EStepOut | None = None
        if truncate is not False and (w > 0 or truncate):
            r = estep.radius(t, s2)
            if truncate or estep._list_valid(t, r) or \
                    estep.density(t, TRUNCATION_SKIN * r, sample) < max_density:
                est = estep.truncated(t, s2, r)
        if est is None:
            est = estep.dense(t, s2)
        lval = est.nll + 0.5 * lmbda * float(np.sum(wmat * (t - y)))  # G W = T - Y
        if not math.isfinite(lval):
            break
        ntol = abs(lval - l_old) / abs(lval) if (math.isfinite(l_old) and lval != 0) else (
            0.0 if lval == l_old else math.inf)
        # ---- M-step
        reg = lmbda * s2
        if basis is not None:
            w_new, disp = _mstep_low_rank(basis[0], basis[1], y, est, reg)
            t_new = y + disp
        else:
            w_new = _mstep_dense(g, y, est, reg)
            t_new = y + g @ w_new
        np_sum = float(np.sum(est.p1))
        s2_new = abs(float(np.dot(est.pt1, estep.xsq))
                     + float(np.dot(est.p1, np.einsum("ij,ij->i", t_new, t_new)))
                     - 2.0 * float(np.sum(est.px * t_new))) / (np_sum * 2.0) if np_sum > 0 \
            else math.nan
        if not (np.isfinite(w_new).all() and np.isfinite(t_new).all()
                and math.isfinite(s2_new)):
            break
        wmat, t, objective, l_old = w_new, t_new, lval, lval
        it += 1
        hit_floor = s2_new <= floor
        s2 = floor if hit_floor else s2_new
        if callback is not None:
            callback(it, s2 * xs * xs, lval)
        if hit_floor or ntol <= tol:
            converged = True
            break

    return _finish(x, y, wmat=wmat, g=g, s2=s2, w=w, beta=beta, xd=xd, xs=xs,
                   yd=yd, ys=ys, iterations=it, converged=converged, objective=objective)


def _finish(x: FloatArray, y: FloatArray, *, wmat: FloatArray,
            g: FloatArray | None, s2: float, w: float, beta: float, xd: FloatArray, xs: float,
            yd: FloatArray, ys: float, iterations: int, converged: bool,
            objective: float) -> CPDResult:
    transform = NonrigidTransform(control_points=y, coefficients=wmat, beta=beta,
                                  model_shift=yd, model_scale=ys, subject_shift=xd,
                                  subject_scale=xs)
    # The exact kernel defines the result; with low_rank W lies in span(U) so this equals
    # the internal centroids up to the dropped spectrum.
    t = y + (g if g is not None else _gauss_kernel(y, y, beta)) @ wmat
    corr, prob = _posterior_max(t, x, s2, w)
    warped = t * xs + xd
    warped.setflags(write=False)
    corr.setflags(write=False)
    prob.setflags(write=False)
    return CPDResult(warped=warped, transform=transform, correspondence=corr,
                     probability=prob, sigma2=float(s2 * xs * xs), iterations=iterations,
                     converged=converged, objective=float(objective))


def _run_pycpd(x: FloatArray, y: FloatArray, xd: FloatArray, xs: float, yd: FloatArray,
               ys: float, beta: float, lmbda: float, w: float, tol: float, max_iter: int,
               s2: float, callback: Callable[[int, float, float], None] | None) -> CPDResult:
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
    return _finish(x, y, wmat=wmat, g=np.asarray(reg.G), s2=s2_out, w=w,
                   beta=beta, xd=xd, xs=xs, yd=yd, ys=ys, iterations=int(reg.iteration),
                   converged=converged, objective=float("nan"))

"""The public entry point :func:`cpd_nonrigid`, its EM loop and its result :class:`CPDResult`.

The E-step engine is in :mod:`._estep`, the M-step in :mod:`._mstep`, the pycpd backend
in :mod:`._pycpd`, the options and their validation in :mod:`._options`.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._executor import checkpoint
from .._points import as_points, sampling_weights
from .._repr import number_text, points_text
from ._estep import _EStep, _MixtureWeights, _posterior_max, run_estep
from ._field import FloatArray, NonrigidTransform, _gauss_kernel, kernel_product
from ._mstep import LowRankMStep, _low_rank_factor, _mstep_dense, _spd_solve
from ._options import MIXTURES, CPDOptions, check_run_options
from ._pycpd import _run_pycpd


def _sum(a: NDArray[Any]) -> Any:
    """``np.sum(a)`` (every element), the same reduction without np.sum's wrapper."""
    return np.add.reduce(a, axis=None)

# --- numerical constants (see the docstring of ``cpd_nonrigid`` for what they mean) -------
#: sigma^2 floor, relative to the mean squared norm of the centred subject (which is 1 in
#: normalised coordinates).  MATLAB's cpd_GRBF stops once sigma2 <= 1e-8 (normalised).
SIGMA2_FLOOR_REL = 1e-8
#: Automatic low-rank switches on for more model points than this (measured crossover of a
#: per-iteration Cholesky against the one-off randomised eigendecomposition; bench_cpd.py).
AUTO_LOW_RANK_MIN_M = 150
#: Automatic truncation switches on when the estimated fraction of (model, subject) pairs
#: within the truncation radius is below this (dense float64 / float32 E-step): the
#: truncated E-step's cost per pair over the dense one's (``_estep.TRUNCATED_PAIR_COST``).
AUTO_TRUNCATE_MAX_DENSITY = {"float64": 0.6, "float32": 0.45}
#: Largest step of the accelerated EM (``accelerate``): the extrapolation moves at most
#: this many times the plain step (SQUAREM's step length, clamped to ``[1, this]``; after a
#: rejected extrapolation the bound restarts at ``ACCEL_STEP_RESTART`` and doubles with
#: each accepted one).
ACCEL_STEP_MAX = 4.0
ACCEL_STEP_RESTART = 2.0
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


class _Posterior:
    """A run's final correspondences (:func:`~._estep._posterior_max` at its last
    centroids and variance), computed when first asked for."""

    __slots__ = ("_args", "_value")

    def __init__(self, t: FloatArray, x: FloatArray, s2: float, w: float, sparse: bool,
                 mix: _MixtureWeights | Callable[[], _MixtureWeights | None] | None = None
                 ) -> None:
        # `mix`: the mixture weights, or how to compute them (only once asked for)
        self._args: tuple[FloatArray, FloatArray, float, float, bool,
                          _MixtureWeights | Callable[[], _MixtureWeights | None] | None
                          ] | None = (t, x, s2, w, sparse, mix)
        self._value: tuple[NDArray[np.intp], FloatArray] | None = None

    def value(self) -> tuple[NDArray[np.intp], FloatArray]:
        if self._value is None:
            assert self._args is not None
            t, x, s2, w, sparse, mix = self._args
            corr, prob = _posterior_max(t, x, s2, w, sparse,
                                        mix() if callable(mix) else mix)
            corr.setflags(write=False)
            prob.setflags(write=False)
            self._value, self._args = (corr, prob), None
        return self._value

    def __getstate__(self) -> tuple[NDArray[np.intp], FloatArray]:
        return self.value()  # sent to another process: computed here, where it was made

    def __setstate__(self, state: tuple[NDArray[np.intp], FloatArray]) -> None:
        self._args, self._value = None, state


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
        is explained by this model point alone. Both are computed when first read (a pass
        over every pair, as an E-step): most runs inside the tree are intermediate steps
        whose correspondences nobody reads.
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
    sigma2: float
    iterations: int
    converged: bool
    objective: float = float("nan")
    _posterior: _Posterior | None = field(default=None, repr=False)

    @property
    def correspondence(self) -> NDArray[np.intp]:
        assert self._posterior is not None, "CPDResult is made by cpd_nonrigid"
        return self._posterior.value()[0]

    @property
    def probability(self) -> FloatArray:
        assert self._posterior is not None, "CPDResult is made by cpd_nonrigid"
        return self._posterior.value()[1]

    def __repr__(self) -> str:  # short: the arrays are not printed
        return (
            f"CPDResult(warped={points_text(self.warped)}, iterations={self.iterations}, "
            f"converged={self.converged}, sigma2={number_text(self.sigma2)}, "
            f"objective={number_text(self.objective)})"
        )


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


def _checked_frame(frame: Any) -> tuple[FloatArray, float]:
    """A caller's ``model_frame``, validated: a finite shift of shape (2,) and a finite
    positive scale."""
    try:
        shift, scale = frame
        shift = np.asarray(shift, dtype=np.float64)
        scale = float(scale)
    except (TypeError, ValueError):
        raise ValueError(f"model_frame must be (shift, scale); got {frame!r}") from None
    if shift.shape != (2,) or not np.isfinite(shift).all():
        raise ValueError(f"model_frame's shift must be 2 finite numbers; got {shift!r}")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"model_frame's scale must be finite and > 0; got {scale!r}")
    return shift, scale


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
    gauss_grid: bool | None = None,
    backend: Literal["native", "pycpd"] = "native",
    callback: Callable[[int, float, float], None] | None = None,
    init_warped: ArrayLike | None = None,
    control: ArrayLike | None = None,
    accelerate: bool = False,
    model_frame: tuple[ArrayLike, float] | None = None,
    mixture_weights: ArrayLike | Literal["uniform", "sampling"] | None = None,
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
        Rank of the low-rank kernel.  ``None``: a pivoted Cholesky factor of ``G`` (never
        formed) grown until the trace of what it leaves out is ``<= 1e-10 M`` (the warped
        points within about 1e-5 of the subject's size of the exact kernel's; ``O(M k^2)``).
    dtype : {"float64", "float32"}, default "float64"
        Precision of the dense E-step's exponentials and products (exponents are always
        formed in float64; the truncated E-step and the M-step are always float64).
    truncate : bool, optional
        Truncated (sparse) E-step: only pairs within a radius of roughly 9 sigma are
        evaluated, chosen so that no posterior changes by more than ``1e-10`` relatively
        (see ``_EStep.radius``).  ``None``: used on iterations where a cheap sample estimates
        that less than 60% (float64) / 45% (float32) of the pairs lie within the radius
        and the truncated E-step is estimated cheaper than the grid E-step.
    gauss_grid : bool, optional
        Grid E-step: the E-step's sums through a Chebyshev-grid fast Gauss transform
        (``registration._cpd._fgt``), ``O((M + N) r^2)`` with ``r`` nodes per axis growing
        as the bounding box over sigma, so it pays while sigma is wide.  Every kernel value
        is interpolated to about ``1e-10`` absolute (the peak is 1), so the sums ``P1``,
        ``Pt1``, ``P X`` match the dense ones to ``1e-8`` relative (tests check it).  Its
        box-wise form (``registration._cpd._boxfgt``, a one-level FMM: Chebyshev nodes only
        in boxes of 8 sigma that hold points, each meeting its 8 neighbours; kernel values
        to ``1e-12``, sums within ``1e-11 sum|q|``) costs ``O((M + N) p^2 + boxes p^3)``
        with the boxes growing as the contour's length over sigma, not with the points:
        it takes the middle sigma range (with ``w > 0``).
        ``None``: used on iterations where its estimated cost is below the dense and the
        truncated E-step's.  ``True``: whenever its grid stays under 400 nodes per axis
        (or the box-wise grid applies).
    backend : {"native", "pycpd"}, default "native"
        ``"pycpd"`` runs ``pycpd.DeformableRegistration`` (alpha=lmbda, beta, w, tolerance,
        max_iterations, sigma2) on the same normalised data as a reference.  Its stopping
        rule is pycpd's (``|sigma2 - sigma2_old| <= tol``) and its callback objective is
        that difference.  ``low_rank``, ``num_eig``, ``dtype``, ``truncate`` and
        ``gauss_grid`` are ignored.
    callback : callable, optional
        ``callback(iteration, sigma2, objective)`` after every iteration (``iteration``
        counts from 1, ``sigma2`` in caller units squared, ``objective`` in normalised
        units).  An exception raised by it propagates unchanged and aborts the run;
        nothing the caller owns has been modified.
    init_warped : array_like, shape (M, 2), optional
        Warm start: the starting positions of the model points on the subject, in the
        subject's (caller's) coordinates, e.g. a previous registration to refine.  The
        kernel and the regulariser stay those of ``model`` (the field is still model ->
        subject); the first E-step uses these positions and the default initial sigma^2 is
        computed from them instead of from ``model``.  Native backend only.
    control : array_like of int, optional
        Indices of the model points the mixture is made of (at least 3, distinct, each in
        ``[0, M)``): the EM runs on those centroids alone, and the field it fits (whose
        control points they are) then moves every model point: ``warped``,
        ``correspondence`` and ``probability`` are for all ``M`` points, the last two from
        the posterior of all ``M`` warped points at the final sigma^2 (as without
        ``control``).  Each E-step then costs ``len(control) * N`` pairs instead of
        ``M * N``: for a model already near its subject (a warm start) a few hundred
        well-spread points fit the same smooth field as every point.  ``init_warped``
        stays one row per model point.  Native backend only.
    accelerate : bool, default False
        SQUAREM (Varadhan & Roland 2008, scheme S3): after every two EM iterations the
        state ``(W, sigma^2)`` is extrapolated along them (a step of up to
        :data:`ACCEL_STEP_MAX` times theirs), and the extrapolated state is kept only when
        its objective is no larger than the last iterate's (else EM's own iterate is
        restored; that E-step counts as an iteration).  From a start already aligned with
        the subject (a warm start, ``init_warped`` or a model near it) EM converges
        linearly and slowly; this reaches the same fixed point in about half the
        iterations, at an objective no larger.  Meant for such starts: from far away the
        path through the shrinking sigma^2 matters, and a long step can skip it.  Native
        backend only.
    model_frame : (shift, scale), optional
        With ``normalize``: the shift (shape ``(2,)``) and scale the model is normalised by,
        instead of its own centroid and RMS radius (the subject keeps its own).  For a
        model already placed near its subject, whose centroid and radius would compare
        with the subject's only if both shapes were sampled alike (see the tree's polish).
        The returned transform carries it (``model_shift``, ``model_scale``).
    mixture_weights : array_like of shape (M,), "uniform", "sampling" or None, default None
        The mixture weight of each model point's Gaussian, relative (positive and finite;
        scaled to mean 1): ``P(m | x_n)`` is proportional to ``pi_m exp(-|x_n -
        t_m|^2 / (2 sigma^2))``. None or ``"uniform"``: every centroid alike, as CPD.
        ``"sampling"``: :func:`~registration._points.sampling_weights` of the model, the
        outline length each point stands for, so a randomly sampled model's clusters do
        not outweigh its gaps (with ``control``: of the control points during the EM,
        of every model point for the final correspondences). With ``control``, an array's
        entries at the control points weight the EM's centroids. Native backend only.

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
      low-rank (automatic rank), truncation and the grid E-step change the warped points
      by less than ``1e-6`` of the subject's RMS radius; float32 by less than ``1e-4``.
      Without a dense ``G`` (low rank) the final ``G W`` also comes from the grid
      transform (about ``1e-13`` per kernel value).  The final correspondences come from
      the pairs within the truncation radius (within ``TRUNCATION_EPS`` of the dense
      pass) for more than ``POSTERIOR_DENSE_MAX_PAIRS`` pairs, or when the last E-step
      was the truncated one (few pairs lie within the radius then).
      ``transform.apply(model)`` equals ``warped`` to ``1e-8`` relative in every mode.
    """
    with _blas_limit():
        return _cpd_nonrigid(model, subject, beta=beta, lmbda=lmbda, w=w, tol=tol,
                             max_iter=max_iter, sigma2=sigma2, normalize=normalize,
                             low_rank=low_rank, num_eig=num_eig, dtype=dtype,
                             truncate=truncate, gauss_grid=gauss_grid, backend=backend,
                             callback=callback, init_warped=init_warped, control=control,
                             accelerate=accelerate, model_frame=model_frame,
                             mixture_weights=mixture_weights)


def _cpd_nonrigid(model: ArrayLike, subject: ArrayLike, *, beta: Any, lmbda: Any, w: Any,
                  tol: Any, max_iter: Any, sigma2: Any, normalize: Any, low_rank: Any,
                  num_eig: Any, dtype: Any, truncate: Any, gauss_grid: Any, backend: Any,
                  callback: Callable[[int, float, float], None] | None,
                  init_warped: ArrayLike | None = None,
                  control: ArrayLike | None = None,
                  accelerate: Any = False,
                  model_frame: tuple[ArrayLike, float] | None = None,
                  mixture_weights: Any = None) -> CPDResult:
    y_in = as_points(model, name="model")
    x_in = as_points(subject, name="subject")
    idx = _control_indices(control, len(y_in), backend)
    weights = _checked_weights(mixture_weights, len(y_in), backend)
    m, n = (len(y_in) if idx is None else len(idx)), len(x_in)
    CPDOptions(beta=beta, lmbda=lmbda, w=w, max_iter=max_iter, tol=tol, dtype=dtype)
    check_run_options(sigma2, num_eig, backend, low_rank, truncate, normalize, callback, m,
                      gauss_grid)
    if not isinstance(accelerate, bool | np.bool_):
        raise ValueError(f"accelerate must be True or False; got {accelerate!r}")
    if accelerate and backend != "native":
        raise ValueError("accelerate needs backend='native'")
    beta, lmbda, w, tol = float(beta), float(lmbda), float(w), float(tol)
    max_iter = int(max_iter)

    if model_frame is not None and not normalize:
        raise ValueError("model_frame needs normalize=True")
    if normalize:
        xd, xs = _normalisation(x_in)
        yd, ys = _normalisation(y_in) if model_frame is None else _checked_frame(model_frame)
    else:
        xd = x_in.mean(axis=0)
        yd, xs, ys = xd, 1.0, 1.0
    x = (x_in - xd) / xs
    y_all = (y_in - yd) / ys
    y = y_all if idx is None else y_all[idx]
    t0 = y
    if init_warped is not None:
        if backend != "native":
            raise ValueError("init_warped needs backend='native'")
        w_in = as_points(init_warped, name="init_warped")
        if w_in.shape != y_in.shape:
            raise ValueError(f"init_warped must have the model's shape {y_in.shape}; "
                             f"got {w_in.shape}")
        t0 = (w_in - xd) / xs
        if idx is not None:
            t0 = t0[idx]
    s2_ref = float(np.mean(np.sum(x * x, axis=1))) if not normalize else 1.0
    if not s2_ref > 0:
        s2_ref = 1.0
    floor = SIGMA2_FLOOR_REL * s2_ref

    if sigma2 is None:
        # sum_{m,n} |x_n - y_m|^2 / (D M N), expanded (MATLAB's cpd_GRBF)
        s2 = float((m * np.sum(x * x) + n * np.sum(t0 * t0)
                    - 2.0 * np.dot(x.sum(axis=0), t0.sum(axis=0))) / (2 * m * n))
    else:
        s2 = float(sigma2) / (xs * xs)
    if not (math.isfinite(s2) and s2 > floor):
        s2 = max(floor, s2_ref) if not math.isfinite(s2) else max(s2, floor)

    if backend == "pycpd":
        wmat, g, s2, it, converged = _run_pycpd(x, y, xs, beta, lmbda, w, tol, max_iter, s2,
                                                callback)
        return _finish(x, y, wmat=wmat, g=g, s2=s2, w=w, beta=beta, xd=xd, xs=xs, yd=yd,
                       ys=ys, iterations=it, converged=converged, objective=float("nan"))

    use_low_rank = (m > AUTO_LOW_RANK_MIN_M) if low_rank is None else bool(low_rank)
    basis = _low_rank_factor(y, beta, num_eig) if use_low_rank else None
    mstep_low_rank = None if basis is None else LowRankMStep(*basis)
    gk: FloatArray | None = None if use_low_rank else _gauss_kernel(y, y, beta)

    mix: _MixtureWeights | None = None  # the EM's centroids'
    # every model point's, for the correspondences (computed when they are first read)
    mix_all: _MixtureWeights | Callable[[], _MixtureWeights | None] | None = None
    if isinstance(weights, str):
        # an evenly sampled model's are all 1: the uniform mixture's passes, bit for bit
        mix = _mixture_or_none(sampling_weights(y))
        mix_all = mix if idx is None else (
            lambda: _mixture_or_none(sampling_weights(y_all)))
    elif weights is not None:
        mix_all = _MixtureWeights(weights)
        # (mean 1 over the centroids: a common factor would scale the outlier weight)
        mix = mix_all if idx is None else _MixtureWeights(weights[idx] / weights[idx].mean())
    estep = _EStep(x, m, w, dtype, mix)
    estep.force_truncate = bool(truncate)
    sample = np.unique(np.linspace(0, m - 1, min(m, 64)).astype(np.intp))
    max_density = AUTO_TRUNCATE_MAX_DENSITY[dtype]
    estep.max_density = max_density

    wmat = np.zeros((m, 2))
    t = y.copy()
    if init_warped is not None:
        # W of the start (slightly ridged: G is ill-conditioned), so that a run stopped
        # before its first M-step still returns about the start, and the first objective
        # carries the start's regulariser
        # (the low-rank kernel's W reproduces the start within the kernel's range)
        if gk is not None:
            wmat = np.asarray(np.linalg.solve(gk + 1e-8 * np.eye(m), t0 - y), dtype=np.float64)
        else:
            assert basis is not None
            q, lam = basis
            wmat = q @ ((q.T @ (t0 - y)) / (lam + 1e-8)[:, None])
        t = t0.copy()
    objective = float("nan")
    l_old = float("nan")
    converged = False
    it = 0
    # accelerate: the plain EM iterates since the last extrapolation, and (while the state
    # is an extrapolated one) the EM iterate it replaced with the objective it must beat
    history: list[tuple[FloatArray, FloatArray, float]] = []
    # sum(W * (T - Y)) of the current state when the M-step that made it gave it, else None
    reg_term: float | None = None
    fallback: tuple[tuple[FloatArray, FloatArray, float], float] | None = None
    step_max = ACCEL_STEP_MAX
    while it < max_iter:
        checkpoint()  # a serial executor's cancellation check (no-op in pool processes)
        # ---- E-step
        est = run_estep(estep, t, s2, truncate, gauss_grid, sample)
        # (np.add.reduce: np.sum's own reduction, bit for bit, without its Python wrapper,
        # 2-3 us a call: 2 % of a serial tree's CPU in these EM loops)
        if reg_term is None:
            reg_term = float(_sum(wmat * (t - y)))  # G W = T - Y
        lval = est.nll + 0.5 * lmbda * reg_term
        extrapolated = fallback is not None
        if fallback is not None:
            (wmat_em, t_em, s2_em), l_beat = fallback
            fallback = None
            if not (math.isfinite(lval) and lval <= l_beat):
                # the extrapolated state did not lower the objective: back to EM's own
                # iterate (this E-step counts as an iteration, so max_iter still bounds)
                wmat, t, s2 = wmat_em, t_em, s2_em
                reg_term = None
                history = []
                step_max = ACCEL_STEP_RESTART
                it += 1
                continue
            step_max = min(ACCEL_STEP_MAX, 2.0 * step_max)
        if not math.isfinite(lval):
            break
        ntol = abs(lval - l_old) / abs(lval) if (math.isfinite(l_old) and lval != 0) else (
            0.0 if lval == l_old else math.inf)
        # ---- M-step
        reg = lmbda * s2
        sums = None
        if mstep_low_rank is not None:
            w_new, disp, sums = mstep_low_rank.solve(y, est, reg)
            t_new = y + disp
        else:
            assert gk is not None
            w_new = _mstep_dense(gk, y, est, reg)
            t_new = y + gk @ w_new
        if sums is not None:
            # the compiled M-step's sums over its rows (LowRankMStep.solve)
            np_sum, p1_tt, px_t, reg_new = float(sums[0]), float(sums[1]), float(sums[2]), \
                float(sums[3])
            finite = sums[4] == 1.0
        else:
            np_sum = float(_sum(est.p1))
            p1_tt = float(np.dot(est.p1, np.einsum("ij,ij->i", t_new, t_new)))
            px_t = float(_sum(est.px * t_new))
            reg_new = None
            finite = bool(np.isfinite(w_new).all() and np.isfinite(t_new).all())
        s2_new = abs(float(np.dot(est.pt1, estep.xsq)) + p1_tt - 2.0 * px_t) / (np_sum * 2.0) \
            if np_sum > 0 else math.nan
        if not (finite and math.isfinite(s2_new)):
            break
        if accelerate:
            history.append((wmat, t, s2))
        wmat, t, objective, l_old = w_new, t_new, lval, lval
        reg_term = reg_new
        it += 1
        hit_floor = s2_new <= floor
        s2 = floor if hit_floor else s2_new
        if callback is not None:
            callback(it, s2 * xs * xs, lval)
        # an accepted extrapolation's objective is compared with the state one EM step
        # before the iterate it replaced, not with an EM step's change: one that lands at
        # about that objective made no progress, which is no sign of convergence (only EM
        # steps end a run; bench/RESULTS.md 7.6)
        if hit_floor or (ntol <= tol and not extrapolated):
            converged = True
            break
        if accelerate and len(history) == 2:
            jump = _squarem(history[0], history[1], (wmat, t, s2), step_max, floor)
            history = []
            if jump is not None:
                fallback = ((wmat, t, s2), lval)
                wmat, t, s2 = jump
                reg_term = None
    if fallback is not None:  # stopped on an extrapolated state not yet checked
        wmat, t, s2 = fallback[0]
    return _finish(x, y, wmat=wmat, g=gk, s2=s2, w=w, beta=beta, xd=xd, xs=xs,
                   yd=yd, ys=ys, iterations=it, converged=converged, objective=objective,
                   moved=None if idx is None else y_all,
                   sparse=truncate is True or (estep.choice is not None
                                               and estep.choice[1] == "truncated"),
                   mix=mix_all)


def _squarem(s0: tuple[FloatArray, FloatArray, float], s1: tuple[FloatArray, FloatArray, float],
             s2: tuple[FloatArray, FloatArray, float], step_max: float, floor: float
             ) -> tuple[FloatArray, FloatArray, float] | None:
    """SQUAREM's extrapolation (Varadhan & Roland 2008, scheme S3) from three successive
    EM states ``(W, T, sigma^2)``: with ``r = s1 - s0`` and ``v = s2 - 2 s1 + s0``, the
    state ``s0 + 2 a r + a^2 v`` at step ``a = |r| / |v|`` (norms over the centroids ``T``;
    ``W`` and ``T = Y + G W`` move together, being linear in each other), clamped to
    ``[1, step_max]``. None when the step is 1 (that is ``s2`` itself) or sigma^2 would
    fall to its floor."""
    r_t = s1[1] - s0[1]
    v_t = s2[1] - s1[1]
    v_t -= r_t
    flat_r, flat_v = r_t.ravel(), v_t.ravel()
    nr = math.sqrt(float(np.dot(flat_r, flat_r)))
    nv = math.sqrt(float(np.dot(flat_v, flat_v)))
    if not (nv > 0 and math.isfinite(nr / nv)):
        return None
    a = min(step_max, nr / nv)
    if not a > 1.0:
        return None
    sig2 = s0[2] + 2.0 * a * (s1[2] - s0[2]) + a * a * ((s2[2] - s1[2]) - (s1[2] - s0[2]))
    if not (math.isfinite(sig2) and sig2 > floor):
        return None

    def ext(p0: FloatArray, r: FloatArray, v: FloatArray) -> FloatArray:
        # p0 + 2 a r + a^2 v, in place in the differences (fresh arrays)
        r *= 2.0 * a
        v *= a * a
        r += v
        r += p0
        return r

    r_w = s1[0] - s0[0]
    v_w = s2[0] - s1[0]
    v_w -= r_w
    return ext(s0[0], r_w, v_w), ext(s0[1], r_t, v_t), float(sig2)


def interpolating_field(points: ArrayLike, targets: ArrayLike, beta: float,
                        ridge: float = 1e-3) -> NonrigidTransform:
    """CPD's Gaussian-RBF field of width `beta` that moves each of `points` onto its
    `target`, smooth in between: ``W = (G + ridge I)^-1 (targets - points)`` (the kernel is
    1 at distance 0, so the ridge bounds how far a point may stay off its target). In the
    points' own coordinates (no normalisation). The solve runs with the BLAS limited as in
    :func:`cpd_nonrigid`, so a pool worker and the calling process get the same bits.

    Raises
    ------
    ValueError
        If `points` or `targets` is not a finite (n, 2) array, their shapes differ, or
        `beta` or `ridge` is not positive.
    """
    x = as_points(points, name="points", min_points=1)
    t = as_points(targets, name="targets", min_points=1)
    if t.shape != x.shape:
        raise ValueError(f"targets must have the shape of points {x.shape}; got {t.shape}")
    if not (math.isfinite(beta) and beta > 0 and math.isfinite(ridge) and ridge > 0):
        raise ValueError(f"beta and ridge must be positive; got {beta!r} and {ridge!r}")
    g = _gauss_kernel(x, x, beta)
    g.flat[:: len(x) + 1] += ridge
    with _blas_limit():
        coefficients = _spd_solve(g, t - x)
    zero = np.zeros(2)
    return NonrigidTransform(control_points=x, coefficients=coefficients, beta=beta,
                             model_shift=zero, model_scale=1.0, subject_shift=zero,
                             subject_scale=1.0)


def _mixture_or_none(weights: FloatArray) -> _MixtureWeights | None:
    return None if bool(np.all(weights == 1.0)) else _MixtureWeights(weights)


def _checked_weights(weights: Any, m: int, backend: Any) -> FloatArray | str | None:
    """`mixture_weights` checked: None ("uniform" too), "sampling", or M positive finite
    floats (mean 1)."""
    if weights is None or (isinstance(weights, str) and weights == "uniform"):
        return None
    if backend != "native":
        raise ValueError("mixture_weights needs backend='native'")
    if isinstance(weights, str):
        if weights not in MIXTURES:
            raise ValueError(f"mixture_weights must be None, 'uniform', 'sampling' or an "
                             f"array of {m} positive numbers; got {weights!r}")
        return weights
    try:
        arr = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"mixture_weights must be None, 'uniform', 'sampling' or an array "
                         f"of {m} positive numbers; got {type(weights).__name__}") from exc
    if arr.shape != (m,):
        raise ValueError(f"mixture_weights must have one entry per model point, shape "
                         f"({m},); got shape {arr.shape}")
    if not (np.all(np.isfinite(arr)) and np.all(arr > 0)):
        raise ValueError("mixture_weights must be finite and > 0")
    return np.asarray(arr / arr.mean(), dtype=np.float64)


def _control_indices(control: ArrayLike | None, m: int, backend: Any) -> NDArray[np.intp] | None:
    """``control`` as validated model indices; None for every point."""
    if control is None:
        return None
    if backend != "native":
        raise ValueError("control needs backend='native'")
    arr = np.asarray(control)
    if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"control must be a 1-D array of integer model indices; got shape "
                         f"{arr.shape} and dtype {arr.dtype}")
    if len(arr) < 3:
        raise ValueError(f"control must name at least 3 model points; got {len(arr)}")
    if arr.min() < 0 or arr.max() >= m:
        raise ValueError(f"control indices must lie in [0, {m}) (the model's points); got "
                         f"{int(arr.min())}..{int(arr.max())}")
    if len(np.unique(arr)) != len(arr):
        raise ValueError("control indices must be distinct")
    return arr.astype(np.intp)


def _finish(x: FloatArray, y: FloatArray, *, wmat: FloatArray,
            g: FloatArray | None, s2: float, w: float, beta: float, xd: FloatArray, xs: float,
            yd: FloatArray, ys: float, iterations: int, converged: bool,
            objective: float, moved: FloatArray | None = None,
            sparse: bool = False,
            mix: _MixtureWeights | Callable[[], _MixtureWeights | None] | None = None
            ) -> CPDResult:
    transform = NonrigidTransform(control_points=y, coefficients=wmat, beta=beta,
                                  model_shift=yd, model_scale=ys, subject_shift=xd,
                                  subject_scale=xs)
    # The exact kernel defines the result (with low_rank W lies in span(U), so this equals
    # the internal centroids up to the dropped spectrum); without a dense G, the kernel
    # product is the transform's own (dense or the Chebyshev Gauss transform, about 1e-13
    # per kernel value), so ``warped`` is ``transform.apply(model)``.
    # `moved`: every model point when the field was fitted with control points
    if moved is not None:
        t = moved + kernel_product(moved, y, wmat, beta)
    else:
        t = y + (g @ wmat if g is not None else kernel_product(y, y, wmat, beta))
    warped = t * xs + xd
    warped.setflags(write=False)
    return CPDResult(warped=warped, transform=transform, sigma2=float(s2 * xs * xs),
                     iterations=iterations, converged=converged, objective=float(objective),
                     _posterior=_Posterior(t, x, s2, w, sparse, mix))


"""CPD's E-step engine: dense (chunked BLAS) and truncated (sparse, cell list) posteriors.

Both return the sums the M-step needs (``P1``, ``Pt1``, ``P X``) and the objective, never
``P`` itself.  Coordinates are normalised (see :mod:`._nonrigid`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from . import _switch
from ._boxfgt import BOX_WIDTHS, BoxGrid, box_rank, box_work
from ._fgt import FGT_MAX_RANK, ChebGrid, bounding_box, fgt_ranks
from ._field import (
    _BLOCK_ELEMS,
    FloatArray,
    _exponent_cols,
    _exponent_rows,
    _gauss_kernel,
)
from ._neighbours import _scan_compiled, near_pairs

#: Cost of the grid E-step per point, ``FGT_NODE_COST * (r_x r_y) ** FGT_NODE_POWER``, in
#: units of one pair of the float64 dense E-step (fitted on fish contours of 8000 points
#: at sigma 0.04-0.22, 2400-41000 grid nodes: larger grids use the BLAS better).
FGT_NODE_COST = 2.5
FGT_NODE_POWER = 0.56
#: Cost of the box-grid E-step (:mod:`._boxfgt`) in the same units: per point and node of
#: a box (``p^2``), and per node-to-node multiply-add (``(pairs + rows * boxes) p^3``), for
#: its four weight columns together (fitted on fish contours of 2000-8000 points at sigma
#: 0.005-0.2: predictions within 0.5-1.5x of the measured CPU time).
BOX_POINT_COST = 0.12
BOX_NODE_COST = 0.15
#: Cost of one pair of the float32 dense E-step relative to float64 (measured).
DENSE_PAIR_COST_F32 = 0.6
#: The compiled dense E-step (:mod:`._ckernel`) against the grid and the box E-steps:
#: up to :data:`COMPILED_DENSE_MAX_PAIRS` pairs the dense pass's estimate is divided by
#: these before it is compared with theirs (fitted beside numpy's dense pass). Measured on
#: `bench/bench_estep.py`'s fish contours at 1000-4000 points, sigma 1-0.02 (best of 3 CPU
#: each), beside the compiled dense pass the grid took 3.9-5.5x the time its estimate gave
#: it (median 4.6), the box 5-6x where its points dominate its cost and 2.9-3.5x where its
#: nodes do; at 1000 points the grid was taken for the first 15-18 iterations at 1.3-3x the
#: dense pass's time. Above that many pairs the choice is as fitted at 2000-8000 points:
#: there every rescaling of the estimates tried lost (8000 points 1.02-1.19x the run;
#: bench/RESULTS.md 7.19), as the dense pass is rarely a contender and the others'
#: estimates are off together.
COMPILED_DENSE_SPEEDUP_GRID = 4.7
COMPILED_DENSE_SPEEDUP_BOX = 3.0
COMPILED_DENSE_MAX_PAIRS = 1 << 22
#: Cost of one pair of the truncated E-step relative to the float64 dense E-step (measured
#: CPU time at 4000 points: 19-27 ns against 15 ns, and 9.4 ns for the float32 dense one).
#: The dense E-step has since become several times cheaper (2.7-3.6 ns a pair) and the
#: truncated one 7-10 ns: a ratio of 2.0-3.8 (median 2.4); with its column sums from the
#: list's transpose, 5.5-6.3 ns at 8000 points (bench/RESULTS.md 7.9). The grid's and the
#: box's constants are off by the same kind of factor; fitted again together they changed
#: no whole run beyond the machine's noise (bench/RESULTS.md 7.7), so they stay.
TRUNCATED_PAIR_COST = 1.5
#: Building the truncated E-step's neighbour list (a cell-list search at the larger
#: radius, the CSR index) costs 1.4-4.5 evaluations of the list (measured at 2000 and 8000
#: points, sigma 0.005-0.1; with the k-d tree search it replaced, 6-9), and a list lasts
#: several iterations (pruned, not rebuilt, as sigma shrinks): the estimated cost of an
#: iteration that must build it is taken this many times higher (chosen with the k-d tree:
#: 3 against 2 moved the switch from the box E-step at 8000 points from sigma ~0.018 to
#: ~0.01; with the cell list, 1.5 and 2 time the same within the machine's noise).
TRUNCATION_BUILD_COST = 3.0
#: The truncated E-step's neighbour list holds at most this many pairs (memory: ~40 bytes
#: each); beyond, the grid or dense E-step runs.
TRUNCATION_MAX_PAIRS = 6_000_000
#: Relative bound on every posterior changed by the truncated E-step.
TRUNCATION_EPS = 1e-10
#: ... in float32 runs: their dense E-step rounds every kernel value to 6e-8 relative and
#: sums in float32 (the truncated one sums in float64), so a bound of 1e-7 keeps the
#: truncation below the precision the run asked for; the radius is 0.92x the float64 one
#: at 8000 points (sqrt of the log ratio), and so is the number of pairs.
TRUNCATION_EPS_F32 = 1e-7
#: The truncated E-step's neighbour list is built with this multiple of the radius, so it
#: can be reused while the centroids move by less than the difference (1.3 -> 1.15: 1.32x
#: the pairs within the radius evaluated instead of 1.69x, for a few more rebuilds at the
#: smallest sigma; 8000 points: 7.75 -> 6.53 s CPU for the whole run).
TRUNCATION_SKIN = 1.15
#: ... and pruned (or rebuilt) when its radius exceeds this multiple of the current one.
TRUNCATION_SHRINK = 1.8
_DEN_FLOOR = 1e-300
#: An E-step method chosen by its estimated cost is reused while sigma^2 stays within this
#: factor of the sigma^2 it was chosen at. The estimates (a k-d tree count around 64
#: centroids, the grids' box occupancy) cost about 1 ms per iteration whatever the size:
#: as much as the whole dense E-step at 400 points. The costs change smoothly with sigma,
#: so a choice made within this factor is at worst slightly off near a crossover; every
#: method is exact to its stated tolerance, so only the time can differ.
ENGINE_REUSE_FACTOR = 1.25
#: Up to this many (model, subject) pairs the E-step is dense without estimating the
#: others' costs. At the tree's 400 x 400 points the dense float32 E-step takes 0.23-0.31
#: ms, and so does the estimate itself (a k-d tree count, the grids' sizes); the grid
#: E-step, when chosen there, took 0.78 ms (its cost model is fitted at 2000-8000 points,
#: where its fixed costs do not show), the truncated one 0.27 ms after 1.4 ms for its
#: neighbour list (25 永 glyphs' tree, every CPD: bench/RESULTS.md 7.6).
DENSE_ONLY_MAX_PAIRS = 1 << 18
#: Smallest exponent the float64 kernels are evaluated at (see `_kernel_in_place`).
_EXP_MIN = -700.0
#: ... and its kernel, by numpy's vector exp (the one `_kernel_in_place` runs;
#: ``math.exp`` may differ in the last bit, which would leave the clipped kernels at
#: +-1e-320, not 0)
_KERNEL_MIN = float(np.exp(np.full(8, _EXP_MIN))[0])
#: The final correspondence pass is dense up to this many (model, subject) pairs ...
POSTERIOR_DENSE_MAX_PAIRS = 1 << 21
#: ... and with the compiled pass, up to this many, even after a truncated E-step: at
#: 2200 x 2100 points it took 5.3 ms against the sparse pass's 6-25 ms (sigma^2 1e-3 -
#: 1e-5), at 4400 x 4300 21-23 ms against 22-40, at 8900 x 8500 82-90 ms against 66-126.
POSTERIOR_DENSE_MAX_PAIRS_COMPILED = 1 << 25
#: ... and above that, still dense when this fraction of the pairs or more lies within
#: the truncation radius (estimated first from a sample of centroids: listing the pairs
#: only to find too many cost 30 ms of a 150 ms stored-resolution CPD at 2000 points).
POSTERIOR_SPARSE_MAX_DENSITY = 0.25


@dataclass
class _EStepOut:
    p1: FloatArray  # (M,) row sums of P
    pt1: FloatArray  # (N,) column sums of P
    px: FloatArray  # (M, 2) P @ X
    nll: float  # -sum(log den) + N D/2 log sigma2 (MATLAB's cpd_P objective)
    nnz: int  # pairs evaluated (M*N when dense)


def _max_exponent(t: FloatArray, x: FloatArray, sigma2: float) -> float:
    """An upper bound on ``|t_m - x_n|^2 / (2 sigma2)`` over all pairs: the squared
    diagonal of the two sets' bounding box over ``2 sigma2``."""
    lo, hi = bounding_box(t, x)
    return float(np.sum((hi - lo) ** 2)) / (2.0 * sigma2)


def _kernel_in_place(e: NDArray[Any], clip: bool) -> None:
    """The kernel ``exp(e)`` of exponents whose exact values are <= 0, in place.

    ``-|e|`` drops the rounding above 0 (``np.minimum(e, 0)``, which propagates NaNs, cost
    as much as the exp; abs and negate 0.15x of it). With `clip` (float64, where some
    exponent may lie below -708: numpy's float64 exp leaves its vector path there, 7.5 ns
    a value against 0.85) the exponents are clipped at :data:`_EXP_MIN` and the clipped
    kernel is taken off after the exp: every kernel moves by at most 1e-304 and the
    clipped ones are 0, as they underflowed before."""
    np.abs(e, out=e)
    if clip:
        np.minimum(e, -_EXP_MIN, out=e)
    np.negative(e, out=e)
    np.exp(e, out=e)
    if clip:
        e -= _KERNEL_MIN


def _outlier_const(sigma2: float, w: float, m: int, n: int) -> float:
    # (2 pi sigma2)^(D/2) w/(1-w) M/N with D = 2
    return 2.0 * math.pi * sigma2 * w / (1.0 - w) * m / n


class _MixtureWeights:
    """The centroids' mixture weights ``pi_m`` (mean 1; the uniform mixture's are all 1)
    in the form every E-step pass takes them: scaled so that the largest is 1, ``rel =
    pi / max(pi)`` (and ``log_rel``, <= 0, added to the kernels' exponents), so every
    weighted kernel stays in ``(0, 1]``; the outlier constant is scaled by the same
    ``1 / max(pi)`` (:func:`_outlier_scaled`), which leaves every posterior as with
    ``pi`` itself, and each denominator is ``max(pi)`` times smaller (:attr:`log_max`,
    per subject point, restores the objective)."""

    __slots__ = ("log_max", "log_min_rel", "log_rel", "rel")

    def __init__(self, weights: FloatArray) -> None:
        wmax = float(np.max(weights))
        self.rel = np.ascontiguousarray(weights / wmax, dtype=np.float64)
        self.log_rel = np.log(self.rel)
        self.log_max = math.log(wmax)
        self.log_min_rel = float(np.min(self.log_rel))


def _outlier_scaled(sigma2: float, w: float, m: int, n: int,
                    mix: _MixtureWeights | None) -> float:
    """The outlier constant as the passes take it: scaled by ``1 / max(pi)``
    (:class:`_MixtureWeights`)."""
    c = _outlier_const(sigma2, w, m, n)
    return c if mix is None else c * math.exp(-mix.log_max)


class _EStep:
    """Workspace for repeated E-steps against a fixed subject ``x`` (normalised); `mix`:
    the centroids' mixture weights (None: uniform, CPD's)."""

    def __init__(self, x: FloatArray, m: int, w: float, dtype: str,
                 mix: _MixtureWeights | None = None) -> None:
        self.x = x
        self.n = len(x)
        self.m = m
        self.w = w
        self.mix = mix
        # each pass's sum of log denominators is off by n log(max pi) (see _MixtureWeights)
        self._nll_shift = 0.0 if mix is None else -self.n * mix.log_max
        self.dtype = np.dtype(dtype)
        self.xsq = np.einsum("ij,ij->i", x, x)
        self.x_c = np.ascontiguousarray(x, dtype=np.float64)  # for _ckernel
        self.block = max(1, min(self.n, _BLOCK_ELEMS // max(m, 1)))
        self._buf64 = np.empty(m * self.block)
        self._buf32 = np.empty(m * self.block, dtype=np.float32) if dtype == "float32" else None
        self._tree_x: cKDTree | None = None
        # neighbour list of the truncated E-step
        self.max_density = 1.0
        self.force_truncate = False
        self._pj: NDArray[np.intp] | None = None
        self._xj: FloatArray | None = None
        self._indptr: NDArray[np.int64] | None = None  # CSR row pointers of the list
        self._j32: NDArray[np.int32] | None = None  # its subject indices, for _ckernel
        self._kern: NDArray[Any] | None = None  # the kernel on its pairs, for _ckernel
        # with mixture weights: each listed pair's, as the list's passes take them (the
        # compiled: rel in the kernel's precision; numpy's: log rel), made with the list
        self._pair_weights: NDArray[Any] | None = None
        self._kmat: scipy.sparse.csr_matrix | None = None  # numpy's passes: the list as CSR
        self._kmat_t: Any = None  # its transpose (CSC, sharing its arrays)
        self._ones_m = np.ones(m)
        self._counts: NDArray[np.intp] = np.zeros(m, dtype=np.intp)
        self._t_build: FloatArray | None = None
        self._r_build = 0.0
        # the method the estimated costs last chose, and the sigma^2 it was chosen at
        self.choice: tuple[float, str] | None = None

    @property
    def tree_x(self) -> cKDTree:
        if self._tree_x is None:
            self._tree_x = cKDTree(self.x)
        return self._tree_x

    # -- dense -------------------------------------------------------------------------
    def dense(self, t: FloatArray, sigma2: float) -> _EStepOut:
        m, n, x = self.m, self.n, self.x
        c = _outlier_scaled(sigma2, self.w, m, n, self.mix)
        if _switch.CKERNEL is not None:
            return self._dense_compiled(t, sigma2, c)
        # float32's exp keeps its vector path below -708 (see _kernel_in_place)
        clip = self.dtype == np.float64 and _max_exponent(t, x, sigma2) > -_EXP_MIN
        ta = _exponent_rows(t, sigma2)
        if self.mix is not None:
            ta[:, 2] += self.mix.log_rel  # the column that multiplies 1
        p1 = np.zeros(m)
        px = np.zeros((m, 2))
        pt1 = np.empty(n)
        nll = 0.0
        ones = np.ones(m, dtype=self.dtype)
        for a in range(0, n, self.block):
            b = min(n, a + self.block)
            k = b - a
            xa = _exponent_cols(x[a:b], self.xsq[a:b], sigma2)
            e64 = self._buf64[: m * k].reshape(m, k)
            np.matmul(ta, xa, out=e64)
            if self._buf32 is not None:
                e: NDArray[Any] = self._buf32[: m * k].reshape(m, k)
                e[...] = e64
            else:
                e = e64
            _kernel_in_place(e, clip)
            colsum = (ones @ e).astype(np.float64)
            lost = None
            if self._buf32 is not None:
                # subject points whose kernels all fall below float32's range (no outlier
                # weight, far from every centroid): their columns in float64, as the
                # compiled pass takes them (else their weights 1 / den overflow float32)
                lost = np.flatnonzero(colsum < 1e-30)
                if len(lost):
                    e64l = e64[:, lost]
                    _kernel_in_place(e64l, True)
                    e[:, lost] = 0.0
                    colsum[lost] = e64l.sum(axis=0)
            den = colsum + c
            np.maximum(den, _DEN_FLOOR, out=den)
            inv = 1.0 / den
            weight = inv
            if lost is not None and len(lost):
                weight = inv.copy()
                weight[lost] = 0.0
            rhs = np.empty((k, 3), dtype=self.dtype)
            rhs[:, :2] = x[a:b] * weight[:, None]
            rhs[:, 2] = weight
            acc = (e @ rhs).astype(np.float64)
            if lost is not None and len(lost):
                acc += e64l @ np.column_stack([x[a:b][lost] * inv[lost, None], inv[lost]])
            px += acc[:, :2]
            p1 += acc[:, 2]
            pt1[a:b] = colsum * inv
            nll -= float(np.sum(np.log(den)))
        nll += n * math.log(sigma2) + self._nll_shift  # N D/2 log sigma2, D = 2
        return _EStepOut(p1, pt1, px, nll, m * n)

    def _dense_compiled(self, t: FloatArray, sigma2: float, c: float) -> _EStepOut:
        """The dense E-step's sums by :mod:`._ckernel`: each subject point's kernels from
        the coordinate differences through a vectorised exp, in one pass (the numpy passes
        above: a product for the exponents, the clamp, the exp, two products for the sums).
        The exponents in float64, the kernels in the run's precision (float32: the
        centroids' sums too, added up in float64 every 256 subject points); every kernel
        within 2 ulp of numpy's exp of the same exponent."""
        m, n = self.m, self.n
        p1 = np.empty(m)
        px = np.empty((2, m))
        pt1 = np.empty(n)
        ck = _switch.CKERNEL
        sumlog = ck.dense(np.ascontiguousarray(t.T, dtype=np.float64), self.x_c,
                          0.5 / sigma2, c, _DEN_FLOOR, self.dtype == np.float32, p1, px, pt1,
                          None if self.mix is None else self.mix.log_rel)
        return _EStepOut(p1, pt1, px.T, n * math.log(sigma2) - sumlog + self._nll_shift,
                         m * n)

    # -- grid (fast Gauss transform) ----------------------------------------------------
    def grid_cost(self, t: FloatArray, sigma2: float) -> float | None:
        """Estimated cost of :meth:`grid` in dense pairs, or None if its ranks are too
        large."""
        rx, ry = fgt_ranks(*bounding_box(t, self.x), math.sqrt(sigma2))
        if max(rx, ry) > FGT_MAX_RANK:
            return None
        return (self.m + self.n) * FGT_NODE_COST * (rx * ry) ** FGT_NODE_POWER

    def grid(self, t: FloatArray, sigma2: float) -> _EStepOut:
        """The dense E-step's sums through two Chebyshev-grid Gauss transforms
        (:mod:`._fgt`): the column sums of the kernel at the subject points, then ``P1`` and
        ``P X`` at the centroids from the weights ``1 / den`` and ``x / den``."""
        grid = ChebGrid(*bounding_box(t, self.x), math.sqrt(sigma2))
        tx, ty = grid.interp(t)
        xx, xy = grid.interp(self.x)
        return self._transformed(
            t, sigma2, lambda q: grid.gather(xx, xy, grid.spread(tx, ty, q)),
            lambda q: grid.gather(tx, ty, grid.spread(xx, xy, q)))

    def box_cost(self, t: FloatArray, sigma2: float, bound: float) -> float | None:
        """Estimated cost of :meth:`boxgrid` in dense pairs; None if its grid is too large
        or its cost exceeds ``bound`` (checked first from the per-point part alone)."""
        per_point = (self.m + self.n) * BOX_POINT_COST * box_rank(BOX_WIDTHS) ** 2
        if per_point >= bound:
            return None
        work = box_work(*bounding_box(t, self.x), math.sqrt(sigma2), t, self.x)
        if work is None:
            return None
        return (self.m + self.n) * BOX_POINT_COST * work[0] + BOX_NODE_COST * work[1]

    def boxgrid(self, t: FloatArray, sigma2: float) -> _EStepOut:
        """The same sums as :meth:`grid` through the box-wise transform
        (:mod:`._boxfgt`): Chebyshev nodes only in the boxes the points occupy."""
        grid = BoxGrid(*bounding_box(t, self.x), math.sqrt(sigma2), t, self.x)
        lt, lx = grid.interp(t), grid.interp(self.x)
        return self._transformed(t, sigma2, lambda q: grid.gather(lx, grid.spread(lt, q)),
                                 lambda q: grid.gather(lt, grid.spread(lx, q)))

    def _transformed(self, t: FloatArray, sigma2: float,
                     to_x: Callable[[FloatArray], FloatArray],
                     to_t: Callable[[FloatArray], FloatArray]) -> _EStepOut:
        """The E-step from two Gauss transforms: ``to_x(q)`` sums weights ``q`` (M, k) at
        the centroids onto the subject points, ``to_t`` the reverse."""
        m, n, x = self.m, self.n, self.x
        c = _outlier_scaled(sigma2, self.w, m, n, self.mix)
        rel = None if self.mix is None else self.mix.rel[:, None]
        colsum = to_x(np.ones((m, 1)) if rel is None else rel)[:, 0]
        np.maximum(colsum, 0.0, out=colsum)
        den = colsum + c
        np.maximum(den, _DEN_FLOOR, out=den)
        inv = 1.0 / den
        q = np.empty((n, 3))
        q[:, 0] = inv
        q[:, 1:] = x * inv[:, None]
        acc = to_t(q)
        if rel is not None:
            acc *= rel
        nll = -float(np.sum(np.log(den))) + n * math.log(sigma2) + self._nll_shift
        return _EStepOut(np.ascontiguousarray(acc[:, 0]), colsum * inv,
                         np.ascontiguousarray(acc[:, 1:]), nll, 0)

    # -- truncated ---------------------------------------------------------------------
    def radius(self, t: FloatArray, sigma2: float) -> float:
        """Truncation radius: dropped terms change no posterior by more than TRUNCATION_EPS
        (TRUNCATION_EPS_F32 in float32 runs).

        Every dropped term is ``<= tau = exp(-r^2 / (2 sigma2))`` and there are at most ``M``
        of them per subject point, so the relative change of each denominator, hence of every
        kept posterior, is ``<= M tau / den_min`` and every dropped posterior is
        ``<= tau / den_min``.  With ``w > 0``, ``den >= c`` (outlier constant); with ``w = 0``
        ``den_n >= exp(-d_n^2 / (2 sigma2))`` with ``d_n`` the distance from ``x_n`` to the
        nearest centroid, so ``r^2 = max_n d_n^2 + 2 sigma2 log(M / eps)``.
        """
        m = self.m
        eps = TRUNCATION_EPS_F32 if self.dtype == np.float32 else TRUNCATION_EPS
        if self.w > 0:
            c = _outlier_scaled(sigma2, self.w, m, self.n, self.mix)
            return math.sqrt(2.0 * sigma2 * math.log(m / (eps * min(c, 1.0))))
        # weighted: a subject point's nearest centroid may carry the least weight
        low = 0.0 if self.mix is None else -self.mix.log_min_rel
        dmin, _ = cKDTree(t).query(self.x, k=1)
        return math.sqrt(float(np.max(dmin)) ** 2 + 2.0 * sigma2 * (math.log(m / eps) + low))

    def density(self, t: FloatArray, r: float, sample: NDArray[np.intp]) -> float:
        """Estimated fraction of pairs within ``r`` (from a fixed sample of centroids)."""
        counts = self.tree_x.query_ball_point(t[sample], r, return_length=True)
        return float(np.mean(counts)) / self.n

    def truncated(self, t: FloatArray, sigma2: float, r: float) -> _EStepOut | None:
        """Sparse E-step over all pairs closer than ``r`` (and possibly a few more).

        Candidate pairs come from a neighbour list built with a larger radius
        ``r_build = TRUNCATION_SKIN * r`` around the centroids ``t_build`` (one cell-list
        search, :func:`._neighbours.near_pairs`).  The list stays valid while
        ``r + max_m |t_m - t_build_m| <= r_build``: then every pair now closer than ``r``
        was closer than ``r_build`` at build time (triangle inequality), so it is in the
        list.  Extra pairs in the list are evaluated exactly, which only adds accuracy.
        A list built for a radius more than ``TRUNCATION_SHRINK * r`` is pruned to the pairs
        now within ``TRUNCATION_SKIN * r`` when the centroids have moved little enough for
        that to be complete (:meth:`_prune_list`), else rebuilt.  Returns None (caller falls
        back to dense) if a rebuilt list holds more than ``max_density`` of all pairs.
        """
        if not self._list_valid(t, r) and not self._prune_list(t, TRUNCATION_SKIN * r):
            if not self._build_list(t, TRUNCATION_SKIN * r):
                return None
        if self._j32 is not None:
            return self._truncated_compiled(t, sigma2)
        return self._truncated_numpy(t, sigma2)

    def _truncated_compiled(self, t: FloatArray, sigma2: float) -> _EStepOut:
        """The truncated E-step's sums by :mod:`._ckernel`: the kernels in one pass over
        the list (the vectorised exp of the dense pass), then the column sums, the
        denominators and the three row sums in one call (three passes over the list,
        against ten with numpy; with numpy's exp between the exponents and the sums,
        four)."""
        m, n = self.m, self.n
        xj, indptr, j32, kern = self._xj, self._indptr, self._j32, self._kern
        assert xj is not None and indptr is not None and j32 is not None and kern is not None
        ck = _switch.CKERNEL
        ck.kernels(np.ascontiguousarray(t, dtype=np.float64), xj, indptr, 0.5 / sigma2, kern)
        if self._pair_weights is not None:
            kern *= self._pair_weights
        colsum, q, p1 = np.empty(n), np.empty((n, 3)), np.empty(m)
        px, pt1 = np.empty((m, 2)), np.empty(n)
        sumlog = ck.sums(kern, indptr, j32, np.ascontiguousarray(self.x, dtype=np.float64),
                         _outlier_scaled(sigma2, self.w, m, n, self.mix), _DEN_FLOOR,
                         colsum, q, p1, px, pt1)
        return _EStepOut(p1, pt1, px, -sumlog + n * math.log(sigma2) + self._nll_shift,
                         len(kern))

    def _truncated_numpy(self, t: FloatArray, sigma2: float) -> _EStepOut:
        """The truncated E-step's sums with numpy and scipy's sparse products."""
        m, n = self.m, self.n
        kmat = self._numpy_list()
        xj = self._xj
        assert xj is not None
        c = _outlier_scaled(sigma2, self.w, m, n, self.mix)
        # |t_i - x_j|^2 on the listed pairs, one coordinate at a time (1-D passes are
        # several times faster than a (P, 2) einsum); np.repeat = t[i] as rows are sorted
        e64 = np.repeat(t[:, 0], self._counts)
        e64 -= xj[0]
        np.square(e64, out=e64)
        dy = np.repeat(t[:, 1], self._counts)
        dy -= xj[1]
        np.square(dy, out=dy)
        e64 += dy
        e64 *= -0.5 / sigma2
        if self._pair_weights is not None:
            e64 += self._pair_weights
        # the kernel on the listed pairs (rows sorted by centroid), in float64 whatever the
        # dtype (a float32 list costs more in casts than its exp saves), written into the
        # list's own array, which its transpose (CSC) shares: the column sums are one
        # compiled product over int32 indices, the same sums as np.bincount's in 0.5-0.8x
        # its time. At 8000 points the step takes 0.87-0.92x the time it took with
        # np.bincount in float64, 0.89-0.90x in float32 (bench/RESULTS.md 7.9)
        e = kmat.data
        np.exp(e64, out=e)
        colsum = self._kmat_t @ self._ones_m
        # then one sparse product per vector: scipy's CSR times a 3-column block costs
        # 3.8 ns a pair against 2.6 for three vectors (8000 points, ~100 pairs each)
        den = colsum + c
        np.maximum(den, _DEN_FLOOR, out=den)
        inv = 1.0 / den
        xinv = self.x * inv[:, None]
        p1 = kmat @ inv
        px = np.empty((m, 2))
        px[:, 0] = kmat @ xinv[:, 0]
        px[:, 1] = kmat @ xinv[:, 1]
        pt1 = colsum * inv
        nll = -float(np.sum(np.log(den))) + n * math.log(sigma2) + self._nll_shift
        return _EStepOut(p1, pt1, px, nll, len(e))

    def _moved(self, t: FloatArray) -> float:
        assert self._t_build is not None
        d = t - self._t_build
        return math.sqrt(float(np.max(np.einsum("ij,ij->i", d, d))))

    def _list_valid(self, t: FloatArray, r: float) -> bool:
        if self._pj is None or self._t_build is None:
            return False
        if self._r_build > TRUNCATION_SHRINK * r:  # list much too loose: prune or rebuild
            return False
        return r + self._moved(t) <= self._r_build

    def _prune_list(self, t: FloatArray, r_build: float) -> bool:
        """Shrink a loose list to the pairs now within ``r_build``, without a new search.

        Valid when ``r_build + max_m |t_m - t_build_m| <= `` the list's radius: every pair
        now within ``r_build`` was within the list's radius at build time (triangle
        inequality), so it is listed; pairs keep their order (sorted by centroid)."""
        if self._pj is None or self._t_build is None or self._xj is None:
            return False
        if r_build + self._moved(t) > self._r_build:
            return False
        if _switch.CKERNEL is not None:
            # the compiled scan of the cell list's search, over each centroid's run of the
            # list: the same pairs in the same order in one pass to count and one to write
            # (8000 points: 1.3 ms a prune against numpy's 6.8; bench/RESULTS.md 7.19)
            assert self._indptr is not None
            found = _scan_compiled(t, self._xj[0], self._xj[1], self._pj,
                                   self._indptr[:-1, None], self._counts[:, None],
                                   r_build * r_build, None, distances=False)
            assert found is not None  # no cap
            self._set_list(found.counts, found.j, t, r_build, found.xj)
            return True
        dx = np.repeat(t[:, 0], self._counts) - self._xj[0]
        dy = np.repeat(t[:, 1], self._counts) - self._xj[1]
        dx *= dx
        dy *= dy
        dx += dy
        kept = np.flatnonzero(dx <= r_build * r_build)
        counts = np.diff(np.searchsorted(kept, np.cumsum(self._counts)), prepend=0)
        self._set_list(counts, self._pj.take(kept), t, r_build, self._xj.take(kept, axis=1))
        return True

    def _build_list(self, t: FloatArray, r_build: float) -> bool:
        cap = None if self.force_truncate else int(
            min(self.max_density * self.m * self.n, TRUNCATION_MAX_PAIRS))
        found = near_pairs(t, self.x, r_build, cap, distances=False)
        if found is None:
            self._pj = None
            return False
        self._set_list(found.counts, found.j, t, r_build, found.xj)
        return True

    def _set_list(self, counts: NDArray[np.intp], pj: NDArray[np.intp], t: FloatArray,
                  r_build: float, xj: FloatArray) -> None:
        self._pj, self._counts = pj, counts
        self._xj = np.ascontiguousarray(xj, dtype=np.float64)
        indptr = np.zeros(self.m + 1, dtype=np.int64)
        np.cumsum(counts, out=indptr[1:])
        self._indptr = indptr
        # the compiled passes: int32 subject indices, and the kernel's array (kept with
        # the list: a fresh one each step costs its page faults, ~1 ms at 2M pairs)
        compiled = _switch.CKERNEL is not None and self.n < 2**31
        self._j32 = pj.astype(np.int32) if compiled else None
        # float32 runs keep the kernel in float32 here (no casts to pay for, unlike numpy's
        # passes: the exp and the list's traffic halve); every sum is float64
        self._kern = np.empty(len(pj), dtype=self.dtype) if compiled else None
        # the pairs are sorted by centroid
        self._pair_weights = (None if self.mix is None
                              else np.repeat(self.mix.rel, counts).astype(self.dtype)
                              if compiled else np.repeat(self.mix.log_rel, counts))
        self._kmat = self._kmat_t = None
        self._t_build = t.copy()
        self._r_build = r_build

    def _numpy_list(self) -> scipy.sparse.csr_matrix:
        """The list as a CSR matrix (its kernel values written in place by the numpy
        passes) and its CSC transpose sharing its arrays, built once per list."""
        if self._kmat is None:
            assert self._pj is not None and self._indptr is not None
            self._kmat = scipy.sparse.csr_matrix(
                (np.zeros(len(self._pj)), self._pj, self._indptr), shape=(self.m, self.n))
            self._kmat_t = self._kmat.T
        return self._kmat


def _posterior_max(t: FloatArray, x: FloatArray, sigma2: float, w: float,
                   sparse: bool = False, mix: _MixtureWeights | None = None
                   ) -> tuple[NDArray[np.intp], FloatArray]:
    """For each centroid, ``argmax_n`` and ``max_n`` of ``P(m | x_n)`` (`mix`: the
    centroids' mixture weights, None: uniform).

    Above :data:`POSTERIOR_DENSE_MAX_PAIRS` pairs, or with ``sparse`` (the caller's last
    E-step was the truncated one, so few pairs lie within the radius), from the pairs
    within the truncation radius (every posterior within ``TRUNCATION_EPS`` relative of the
    dense one, every dropped one below ``TRUNCATION_EPS``); centroids with no pair within
    it take the dense row.  The dense pass when the radius holds
    :data:`POSTERIOR_SPARSE_MAX_DENSITY` of the pairs (estimated from a sample, then
    counted). With the compiled pass (:mod:`._ckernel`), dense up to
    :data:`POSTERIOR_DENSE_MAX_PAIRS_COMPILED` pairs whatever the last E-step was.
    """
    m, n = len(t), len(x)
    if _switch.CKERNEL is not None and m * n <= POSTERIOR_DENSE_MAX_PAIRS_COMPILED:
        return _posterior_max_dense(t, x, sigma2, w, mix)
    if m * n <= POSTERIOR_DENSE_MAX_PAIRS and not sparse:
        return _posterior_max_dense(t, x, sigma2, w, mix)
    r = _EStep(x, m, w, "float64", mix).radius(t, sigma2)
    x_tree = cKDTree(x)
    # a quarter of the pairs within the radius or more: the dense pass, without first
    # listing them (estimated from 64 centroids, as the E-step's choice does)
    sample = np.unique(np.linspace(0, m - 1, min(m, 64)).astype(np.intp))
    counts = x_tree.query_ball_point(t[sample], r, return_length=True)
    if float(np.mean(counts)) > POSTERIOR_SPARSE_MAX_DENSITY * n:
        return _posterior_max_dense(t, x, sigma2, w, mix)
    found = near_pairs(t, x, r, int(m * n * POSTERIOR_SPARSE_MAX_DENSITY))
    if found is None:
        return _posterior_max_dense(t, x, sigma2, w, mix)
    i, j, dist = found.i, found.j, found.dist
    assert dist is not None
    e = np.exp(-0.5 / sigma2 * dist**2)
    if mix is not None:
        e *= mix.rel[i]
    den = np.bincount(j, weights=e, minlength=n) + _outlier_scaled(sigma2, w, m, n, mix)
    np.maximum(den, _DEN_FLOOR, out=den)
    p = e / den[j]
    best = np.zeros(m)
    arg = np.zeros(m, dtype=np.intp)
    rows = np.zeros(0, dtype=np.intp)
    if len(p):
        # pairs come sorted by centroid: a segmented max, then the first pair that attains
        # it in each segment (the same tie-break as a stable sort), in O(pairs)
        starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
        rows = i[starts]
        top = np.maximum.reduceat(p, starts)
        seg = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(p)]))
        hit = np.flatnonzero(p == top[seg])
        _, first = np.unique(seg[hit], return_index=True)
        best[rows] = top
        arg[rows] = j[hit[first]]
    lone = np.setdiff1d(np.arange(m), rows)
    if len(lone):
        post = _gauss_kernel(t[lone], x, math.sqrt(sigma2)) / den
        if mix is not None:
            post *= mix.rel[lone, None]
        arg[lone] = np.argmax(post, axis=1)
        best[lone] = post[np.arange(len(lone)), arg[lone]]
    return arg, np.clip(best, 0.0, 1.0)


def _posterior_max_dense(t: FloatArray, x: FloatArray, sigma2: float, w: float,
                         mix: _MixtureWeights | None = None
                         ) -> tuple[NDArray[np.intp], FloatArray]:
    """For each centroid, ``argmax_n`` and ``max_n`` of ``P(m | x_n)`` over every pair, in
    blocks of subject points. The exponents come from one product per block, as in the
    dense E-step (the coordinate differences, seven passes over the block, and an exp on
    underflowing values took 13-24 ns a pair: ten dense E-steps' time at 400 x 400
    points); float64 throughout."""
    m, n = len(t), len(x)
    c = _outlier_scaled(sigma2, w, m, n, mix)
    if _switch.CKERNEL is not None:  # one pass (see _EStep._dense_compiled)
        arg = np.empty(m, dtype=np.int64)
        best = np.empty(m)
        _switch.CKERNEL.posterior_max(np.ascontiguousarray(t.T, dtype=np.float64),
                                      np.ascontiguousarray(x, dtype=np.float64), 0.5 / sigma2,
                                      c, _DEN_FLOOR, arg, best,
                                      None if mix is None else mix.log_rel)
        return arg.astype(np.intp, copy=False), np.clip(best, 0.0, 1.0)
    ta = _exponent_rows(t, sigma2)
    if mix is not None:
        ta[:, 2] += mix.log_rel
    xsq = np.einsum("ij,ij->i", x, x)
    clip = _max_exponent(t, x, sigma2) > -_EXP_MIN
    rows = np.arange(m)
    best = np.full(m, -1.0)
    arg = np.zeros(m, dtype=np.intp)
    step = max(1, _BLOCK_ELEMS // m)
    for a in range(0, n, step):
        b = min(n, a + step)
        e = ta @ _exponent_cols(x[a:b], xsq[a:b], sigma2)
        # as in the dense E-step (with w = 0, a subject point far from every centroid keeps
        # its floored, zero posteriors: its clipped kernels are 0)
        _kernel_in_place(e, clip)
        den = e.sum(axis=0) + c
        np.maximum(den, _DEN_FLOOR, out=den)
        e *= 1.0 / den
        k = np.argmax(e, axis=1)
        v = e[rows, k]
        better = v > best
        best[better] = v[better]
        arg[better] = k[better] + a
    return arg, np.clip(best, 0.0, 1.0)


def run_estep(estep: _EStep, t: FloatArray, sigma2: float, truncate: bool | None,
              gauss_grid: bool | None, sample: NDArray[np.intp]) -> _EStepOut:
    """One E-step by the cheapest method allowed: truncated (``truncate``), grid
    (``gauss_grid``: the whole-box grid or the box-wise one) or dense; ``None`` lets the
    estimated cost decide, ``True`` forces a method where it applies (truncation first),
    ``False`` rules it out.

    With both left to the estimate, up to :data:`DENSE_ONLY_MAX_PAIRS` pairs it is dense,
    and above, a choice is reused while ``sigma2`` stays within
    :data:`ENGINE_REUSE_FACTOR` of the variance it was made at (see there)."""
    auto = truncate is None and gauss_grid is None
    if auto and estep.m * estep.n <= DENSE_ONLY_MAX_PAIRS:
        return estep.dense(t, sigma2)
    if auto and estep.choice is not None:
        s2_at, engine = estep.choice
        if s2_at / ENGINE_REUSE_FACTOR <= sigma2 <= s2_at * ENGINE_REUSE_FACTOR:
            out = _run_engine(estep, engine, t, sigma2)
            if out is not None:
                return out
    engine, out = _choose_estep(estep, t, sigma2, truncate, gauss_grid, sample)
    if auto:
        estep.choice = (sigma2, engine)
    return out


def _run_engine(estep: _EStep, engine: str, t: FloatArray, sigma2: float
                ) -> _EStepOut | None:
    if engine == "truncated":
        return estep.truncated(t, sigma2, estep.radius(t, sigma2))
    if engine == "box":
        return estep.boxgrid(t, sigma2)
    if engine == "grid":
        return estep.grid(t, sigma2)
    return estep.dense(t, sigma2)


def _choose_estep(estep: _EStep, t: FloatArray, sigma2: float, truncate: bool | None,
                  gauss_grid: bool | None, sample: NDArray[np.intp]
                  ) -> tuple[str, _EStepOut]:
    """The E-step by the method the estimated costs (and the caller's rule) pick, and its
    name."""
    m, n = estep.m, estep.n
    dense_cost = m * n * (DENSE_PAIR_COST_F32 if estep.dtype == np.float32 else 1.0)
    # the dense pass's cost as the grid's and the box's estimates see it
    dense_vs_grids = dense_vs_box = dense_cost
    if _switch.CKERNEL is not None and m * n <= COMPILED_DENSE_MAX_PAIRS:
        dense_vs_grids = dense_cost / COMPILED_DENSE_SPEEDUP_GRID
        dense_vs_box = dense_cost / COMPILED_DENSE_SPEEDUP_BOX
    grid_cost = estep.grid_cost(t, sigma2) if gauss_grid is not False else None
    grid_wins = grid_cost is not None and grid_cost < dense_vs_grids
    # what runs if neither the truncated nor the box E-step does, at its estimated cost
    best = grid_cost if grid_cost is not None and grid_wins else dense_cost
    box_cost: float | None = None
    # the box transform's error is absolute (per unit weight): without an outlier constant
    # a subject point far from every centroid has a denominator it cannot resolve
    box_checked = gauss_grid is False or estep.w <= 0
    if truncate is not False and (estep.w > 0 or truncate):
        r = estep.radius(t, sigma2)
        use = bool(truncate) or estep._list_valid(t, r)
        if not use and not gauss_grid:
            dens = estep.density(t, TRUNCATION_SKIN * r, sample)
            cost = TRUNCATED_PAIR_COST * TRUNCATION_BUILD_COST * dens * m * n
            use = dens < estep.max_density and dens * m * n < TRUNCATION_MAX_PAIRS
            if use and cost < best:
                box_cost, box_checked = estep.box_cost(t, sigma2, cost), True
            use = use and cost < best and (box_cost is None or cost < box_cost)
        if use:
            out = estep.truncated(t, sigma2, r)
            if out is not None:
                return "truncated", out
    if not box_checked:
        # it must beat the dense pass and the grid (then it is not estimated further)
        bound = min(dense_vs_box, math.inf if grid_cost is None else grid_cost)
        box_cost = estep.box_cost(t, sigma2, math.inf if gauss_grid else bound)
    if box_cost is not None and (gauss_grid or box_cost < dense_vs_box) and (
            grid_cost is None or box_cost < grid_cost):
        return "box", estep.boxgrid(t, sigma2)
    if grid_cost is not None and (gauss_grid or grid_wins):
        return "grid", estep.grid(t, sigma2)
    return "dense", estep.dense(t, sigma2)

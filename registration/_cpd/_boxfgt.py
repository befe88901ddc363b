"""A box-wise Chebyshev fast Gauss transform (a one-level FMM) for narrow kernels.

:mod:`._fgt` interpolates the Gaussian on one Chebyshev grid over the whole bounding box:
``r ~ 3 L / sigma`` nodes per axis, so its cost grows as ``(L / sigma)^2`` per point even
where the points (a contour) fill a small part of the box.  Here the plane is cut into
square boxes of side ``h = BOX_WIDTHS * sigma`` anchored at the bounding box, and only the
boxes holding points are used:

1. *anterpolation*: the weights of the sources in each box are spread onto the box's
   ``p x p`` Chebyshev nodes (``C_b = Lx_b^T diag(q) Ly_b``, one small product per box);
2. *node to node*: every occupied target box receives the exact Gaussian of the nodes of
   every occupied source box within the truncation radius ``R`` (box offsets whose nearest
   points are at most ``R`` apart).  The boxes form a uniform grid, so the kernel between
   the nodes of two boxes depends only on their offset and is separable,
   ``K[dx, dy] = Kx[dx] (x) Ky[dy]``: one product per ``dy`` over all boxes, then one per
   offset over the boxes it pairs;
3. *interpolation*: each target reads its box's convolved nodes back.

Cost ``O((M + N) p^2 + boxes * offsets * p^3)``, with ``p`` fixed by ``BOX_WIDTHS`` and the
number of occupied boxes growing as the contour's length over ``sigma``, independently of
the number of points.

Error bound: every 1-D kernel value ``exp(-(u - v)^2 / (2 sigma^2))`` with ``u`` in a box
and ``v`` anywhere is interpolated on :func:`box_rank` nodes to within
:data:`BOX_ABS_TOL` (measured worst case over ``v``; ``tests/registration/test_cpd_fast.py``
checks it), so each 2-D kernel value between boxes that interact is within about
``4 * BOX_ABS_TOL`` (two axes, both arguments interpolated, Lebesgue constant below 2);
each pair of points in boxes that do not interact is farther apart than ``R`` with
``exp(-R^2 / (2 sigma^2)) = BOX_TRUNC_TOL``.  Hence each sum is within
``(4 BOX_ABS_TOL + BOX_TRUNC_TOL) * sum_j |q_j| <= 1e-11 * sum_j |q_j|`` of the dense one
(the whole-box grid's bound is 1e-9), and only the sources within two boxes of a target
count in that sum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ._fgt import _cheb_nodes, _interp_matrix, bounding_box
from ._field import FloatArray

#: Side of a box in kernel widths (sigma).  At 8 the truncation radius (7.7 sigma) is just
#: under one box, so a box meets only its 8 neighbours (measured on 8000-point contours at
#: sigma 0.01-0.1: 1.2-2x faster than boxes of 2-4 widths, as fast as 6-10).
BOX_WIDTHS = 8.0
#: Absolute error of one interpolated 1-D kernel value (the peak is 1).  Tighter than the
#: whole-box grid's 1e-10: the box transform runs at small sigma, where a subject point
#: between parts of the contour has a denominator as small as the outlier constant.
BOX_ABS_TOL = 1e-12
#: Kernel value at the truncation radius: pairs in boxes farther apart are dropped.
BOX_TRUNC_TOL = 1e-13
#: The transform is not used beyond this many occupied boxes (or 4M boxes in the grid).
BOX_MAX_OCCUPIED = 20_000
_BOX_MAX_CELLS = 4_000_000


def box_rank(widths: float) -> int:
    """Chebyshev nodes per axis of a box ``widths`` sigmas wide for :data:`BOX_ABS_TOL`.

    Measured (worst 1-D error over shifts ``v`` from 9 sigma before the box to 9 after):
    1e-12 needs 13, 17, 24, 31, 34, 37 nodes at 1, 2, 4, 6, 7, 8 widths (1e-10: 11, 15,
    21, 27, -, 33); this is ``3.5 w + 10`` rounded up."""
    return math.ceil(3.5 * widths + 10.0)


def truncation_radius(sigma: float) -> float:
    """``R`` with ``exp(-R^2 / (2 sigma^2)) = BOX_TRUNC_TOL``."""
    return sigma * math.sqrt(2.0 * math.log(1.0 / BOX_TRUNC_TOL))


def _offsets(h: float, radius: float) -> list[tuple[int, int]]:
    """Box offsets ``(dx, dy)`` whose nearest points are at most ``radius`` apart."""
    k = math.floor(radius / h) + 1
    out = []
    for dx in range(-k, k + 1):
        for dy in range(-k, k + 1):
            gx, gy = max(abs(dx) - 1, 0) * h, max(abs(dy) - 1, 0) * h
            if gx * gx + gy * gy <= radius * radius:
                out.append((dx, dy))
    return out


def box_layout(lo: FloatArray, hi: FloatArray, sigma: float
               ) -> tuple[float, tuple[int, int]] | None:
    """Box side and boxes per axis over ``[lo, hi]``; None when the grid is too large."""
    h = BOX_WIDTHS * sigma
    span = np.maximum(hi - lo, 1e-12)
    nb = (max(1, math.ceil(float(span[0]) / h)), max(1, math.ceil(float(span[1]) / h)))
    if nb[0] * nb[1] > _BOX_MAX_CELLS:
        return None
    return h, nb


@dataclass
class _Located:
    """Points of one set sorted by box: order, box of each segment, segment starts,
    interpolation weights per point (in sorted order)."""

    order: NDArray[np.intp]
    boxes: NDArray[np.intp]  # occupied-box index of each segment
    starts: NDArray[np.intp]  # len(boxes) + 1
    lx: FloatArray
    ly: FloatArray


class BoxGrid:
    """Occupied boxes of ``h = BOX_WIDTHS * sigma`` over the given point sets."""

    def __init__(self, lo: FloatArray, hi: FloatArray, sigma: float,
                 *sets: FloatArray) -> None:
        layout = box_layout(lo, hi, sigma)
        if layout is None:
            raise ValueError("box grid too large for this sigma")
        self.h, self.nb = layout
        self.lo = np.asarray(lo, dtype=np.float64)
        self.p = p = box_rank(BOX_WIDTHS)
        g = (_cheb_nodes(p) + 1.0) * 0.5 * self.h
        cells = np.concatenate([self._cell(s) for s in sets])
        occupied = np.unique(cells)
        self.cells = occupied  # flat cell index of each occupied box
        self.index = np.full(self.nb[0] * self.nb[1], -1, dtype=np.intp)
        self.index[occupied] = np.arange(len(occupied))
        radius = truncation_radius(sigma)
        offs = _offsets(self.h, radius)
        d = np.arange(-max(abs(a) for a, _ in offs), max(abs(a) for a, _ in offs) + 1)
        # 1-D node-to-node kernel per box offset: [target node, source node]
        inv = -0.5 / (sigma * sigma)
        self.kern = {int(k): np.exp(inv * (k * self.h + g[:, None] - g[None, :]) ** 2)
                     for k in d}
        bx, by = np.divmod(occupied, self.nb[1])
        self.pairs: dict[int, list[tuple[int, NDArray[np.intp], NDArray[np.intp]]]] = {}
        for dx, dy in offs:
            tx, ty = bx + dx, by + dy
            ok = (tx >= 0) & (tx < self.nb[0]) & (ty >= 0) & (ty < self.nb[1])
            tgt = np.full(len(occupied), -1, dtype=np.intp)
            tgt[ok] = self.index[tx[ok] * self.nb[1] + ty[ok]]
            src = np.flatnonzero(tgt >= 0)
            if len(src):
                self.pairs.setdefault(dy, []).append((dx, src, tgt[src]))

    def _cell(self, pts: FloatArray) -> NDArray[np.intp]:
        ij = np.floor((pts - self.lo) / self.h).astype(np.intp)
        np.clip(ij[:, 0], 0, self.nb[0] - 1, out=ij[:, 0])
        np.clip(ij[:, 1], 0, self.nb[1] - 1, out=ij[:, 1])
        out: NDArray[np.intp] = ij[:, 0] * self.nb[1] + ij[:, 1]
        return out

    def interp(self, pts: FloatArray) -> _Located:
        cell = self._cell(pts)
        box = self.index[cell]
        order = np.argsort(box, kind="stable")
        sbox = box[order]
        starts = np.flatnonzero(np.r_[True, sbox[1:] != sbox[:-1]]) if len(sbox) else \
            np.zeros(0, dtype=np.intp)
        cx, cy = np.divmod(self.cells[sbox], self.nb[1])
        sp = pts[order]
        u = (sp[:, 0] - self.lo[0] - cx * self.h) / self.h * 2.0 - 1.0
        v = (sp[:, 1] - self.lo[1] - cy * self.h) / self.h * 2.0 - 1.0
        np.clip(u, -1.0, 1.0, out=u)
        np.clip(v, -1.0, 1.0, out=v)
        return _Located(order, sbox[starts], np.r_[starts, len(sbox)].astype(np.intp),
                        _interp_matrix(u, self.p), _interp_matrix(v, self.p))

    def spread(self, loc: _Located, q: FloatArray) -> FloatArray:
        """Sources with weights ``q`` (n, k) onto the boxes' nodes and convolved:
        (boxes, k, p, p)."""
        p, k = self.p, q.shape[1]
        qs = q[loc.order]
        coef = np.zeros((len(self.cells), k, p, p))
        st = loc.starts
        for s, b in enumerate(loc.boxes):
            a, e = st[s], st[s + 1]
            wq = (loc.lx[a:e, :, None] * qs[a:e, None, :]).reshape(e - a, p * k)
            coef[b] = (wq.T @ loc.ly[a:e]).reshape(p, k, p).transpose(1, 0, 2)
        return self._convolve(coef)

    def _convolve(self, coef: FloatArray) -> FloatArray:
        p = self.p
        nbox, k = coef.shape[:2]
        flat = coef.reshape(-1, p)
        out = np.zeros((nbox, k, p, p))  # [box, col, y node, x node] until the end
        for dy, items in self.pairs.items():
            # y first, over all boxes: [box, col, x node, y node'] -> swap to [.., y', x]
            u = (flat @ self.kern[dy].T).reshape(nbox, k, p, p).transpose(0, 1, 3, 2)
            u = np.ascontiguousarray(u)
            for dx, src, tgt in items:
                out[tgt] += (u[src].reshape(-1, p) @ self.kern[dx].T).reshape(-1, k, p, p)
        res: FloatArray = np.ascontiguousarray(out.transpose(0, 1, 3, 2))
        return res

    @staticmethod
    def gather(loc: _Located, conv: FloatArray) -> FloatArray:
        """Read convolved nodes (boxes, k, p, p) back at the targets: (n, k)."""
        _, k, p, _ = conv.shape
        out = np.empty((len(loc.order), k))
        st = loc.starts
        for s, b in enumerate(loc.boxes):
            a, e = st[s], st[s + 1]
            g = conv[b].transpose(1, 0, 2).reshape(p, k * p)
            val = (loc.lx[a:e] @ g).reshape(e - a, k, p)
            out[loc.order[a:e]] = np.einsum("ikp,ip->ik", val, loc.ly[a:e])
        return out


def box_work(lo: FloatArray, hi: FloatArray, sigma: float, *sets: FloatArray
             ) -> tuple[int, int] | None:
    """Work of one column of :class:`BoxGrid` over ``sets``, without building it:
    (``p^2``: multiply-adds per point to spread or gather; ``(pairs + rows * boxes) p^3``:
    multiply-adds node to node); None when the grid would be too large."""
    layout = box_layout(lo, hi, sigma)
    if layout is None:
        return None
    h, nb = layout
    cells = []
    for s in sets:
        ij = np.floor((s - lo) / h).astype(np.intp)
        np.clip(ij[:, 0], 0, nb[0] - 1, out=ij[:, 0])
        np.clip(ij[:, 1], 0, nb[1] - 1, out=ij[:, 1])
        cells.append(ij[:, 0] * nb[1] + ij[:, 1])
    occupied = np.unique(np.concatenate(cells))
    if len(occupied) > BOX_MAX_OCCUPIED:
        return None
    bx, by = np.divmod(occupied, nb[1])
    pairs = 0
    offs = _offsets(h, truncation_radius(sigma))
    for dx, dy in offs:
        tx, ty = bx + dx, by + dy
        ok = (tx >= 0) & (tx < nb[0]) & (ty >= 0) & (ty < nb[1])
        flat = tx[ok] * nb[1] + ty[ok]
        pos = np.searchsorted(occupied, flat)
        pos[pos == len(occupied)] = 0
        pairs += int(np.count_nonzero(occupied[pos] == flat))
    rows = len({dy for _, dy in offs})
    p = box_rank(BOX_WIDTHS)
    return p * p, (pairs + rows * len(occupied)) * p**3


def box_gauss_transform(src: FloatArray, q: FloatArray, tgt: FloatArray,
                        sigma: float) -> FloatArray:
    """``sum_j q[j] exp(-|tgt_i - src_j|^2 / (2 sigma^2))`` for every target: (n_tgt, k)."""
    lo, hi = bounding_box(src, tgt)
    grid = BoxGrid(lo, hi, sigma, src, tgt)
    conv = grid.spread(grid.interp(src), q.reshape(len(src), -1))
    return grid.gather(grid.interp(tgt), conv)

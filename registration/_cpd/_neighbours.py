"""All pairs of points closer than a radius, from a cell list (numpy only).

The truncated E-step lists the pairs ``(m, n)`` with ``|t_m - x_n| <= r``, grouped by
centroid ``m``.  ``cKDTree.sparse_distance_matrix`` finds them in 25-130 ns a pair at 8000
points (its record array, then a sort by centroid); this cell list takes 20-25 ns and
needs no sort:

1. the subject points are sorted by the cell of side ``h >= r / 2`` they fall in, cells
   numbered row by row, so each row of cells is a contiguous run of the sorted points;
2. each centroid reads up to five rows, each row only over the cells that the disc of
   radius ``r`` around it reaches in that row (one ``searchsorted`` for each end): 1.3-1.4
   candidates a pair on contours, the circle's area against that of the cells it cuts;
3. the candidates are generated in centroid order (a ragged ``arange``) and kept when the
   distance is within ``r``, a block of centroids at a time so the temporaries stay in cache.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ._fgt import bounding_box
from ._field import FloatArray
from ._switch import compiled as _compiled

#: Candidates handled per block of centroids (their temporaries stay in the CPU cache).
CANDIDATE_BLOCK = 1 << 16
#: Cells per axis are kept below this, so a row-major cell number fits an int64.
_MAX_CELLS_PER_AXIS = 1 << 30
#: Rows of cells a centroid reads: with ``h >= r / 2`` the disc spans at most five.
_ROWS = 5


@dataclass
class NearPairs:
    """Pairs within the radius, grouped by centroid (in centroid order)."""

    counts: NDArray[np.intp]  # (M,) pairs of each centroid
    j: NDArray[np.intp]  # (P,) subject point of each pair
    xj: FloatArray  # (2, P) its coordinates
    dist: FloatArray | None  # (P,) |t_m - x_n|, when asked for

    @property
    def i(self) -> NDArray[np.intp]:
        """The centroid of each pair."""
        out: NDArray[np.intp] = np.repeat(np.arange(len(self.counts)), self.counts)
        return out


def near_pairs(t: FloatArray, x: FloatArray, r: float, cap: int | None = None,
               distances: bool = True) -> NearPairs | None:
    """All pairs ``(m, n)`` with ``|t_m - x_n| <= r``, grouped by ``m``; within a centroid
    the pairs follow the cells row by row.  None if more than ``cap`` pairs (the search
    stops as soon as it knows)."""
    if not (r > 0.0 and math.isfinite(r)):
        raise ValueError(f"near_pairs: the radius must be positive and finite; got {r!r}")
    m = len(t)
    if m == 0 or len(x) == 0:
        return NearPairs(np.zeros(m, dtype=np.intp), np.zeros(0, dtype=np.intp),
                         np.zeros((2, 0)), np.zeros(0) if distances else None)
    lo, hi = bounding_box(x)
    span = float(np.max(hi - lo))
    # the cells are read for a radius a few roundings larger: a point whose distance
    # rounds to r must not sit in a cell whose coordinate rounded the other way
    # (the distance test below, ``d^2 <= r^2``, decides)
    margin = 8.0 * np.finfo(np.float64).eps * float(np.max(np.abs(x)) + np.max(np.abs(t)))
    r_cells = r + margin
    h = max(0.5 * r_cells, span / _MAX_CELLS_PER_AXIS)
    cxy = np.floor((x - lo) / h).astype(np.int64)
    ncx = int(cxy[:, 0].max()) + 1
    ncy = int(cxy[:, 1].max()) + 1
    key = cxy[:, 1] * ncx + cxy[:, 0]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    xs0 = np.ascontiguousarray(x[order, 0])
    xs1 = np.ascontiguousarray(x[order, 1])
    # each centroid's rows of cells, and the columns the disc reaches in each
    rr = r_cells / h
    tx = (t[:, 0] - lo[0]) / h
    ty = (t[:, 1] - lo[1]) / h
    rows = np.floor(ty - rr).astype(np.int64)[:, None] + np.arange(_ROWS)
    gap = np.maximum(np.maximum(rows - ty[:, None], ty[:, None] - (rows + 1)), 0.0)
    half = np.sqrt(np.maximum(rr * rr - gap * gap, 0.0))
    col_lo = np.maximum(np.floor(tx[:, None] - half), 0.0).astype(np.int64)
    col_hi = np.minimum(np.floor(tx[:, None] + half), ncx - 1).astype(np.int64)
    use = (gap <= rr) & (rows >= 0) & (rows < ncy) & (col_lo <= col_hi)
    first = rows * ncx
    starts = np.searchsorted(skey, first + col_lo, "left")
    lens = np.where(use, np.searchsorted(skey, first + col_hi, "right") - starts, 0)
    per_centroid = lens.sum(axis=1)
    ends = np.cumsum(per_centroid)

    r2 = r * r
    if _compiled() is not None:
        return _scan_compiled(t, xs0, xs1, order, starts, lens, r2, cap, distances)
    counts = np.zeros(m, dtype=np.intp)
    j_parts: list[NDArray[np.intp]] = []
    x0_parts: list[FloatArray] = []
    x1_parts: list[FloatArray] = []
    d_parts: list[FloatArray] = []
    total = 0
    a = 0
    while a < m:
        done = int(ends[a - 1]) if a else 0
        b = min(m, max(a + 1, int(np.searchsorted(ends, done + CANDIDATE_BLOCK, "right"))))
        flat_len = lens[a:b].ravel()
        n_cand = int(ends[b - 1]) - done
        if n_cand:
            # a ragged arange: the candidates' positions in the sorted subject
            pos = np.arange(n_cand)
            pos += np.repeat(starts[a:b].ravel() - (np.cumsum(flat_len) - flat_len),
                             flat_len)
            g0 = xs0.take(pos)
            g1 = xs1.take(pos)
            rep = per_centroid[a:b]
            d0 = g0 - np.repeat(t[a:b, 0], rep)
            d1 = g1 - np.repeat(t[a:b, 1], rep)
            d0 *= d0
            d1 *= d1
            d0 += d1
            kept = np.flatnonzero(d0 <= r2)
            bounds = np.searchsorted(kept, ends[a:b] - done)
            counts[a:b] = np.diff(bounds, prepend=0)
            total += len(kept)
            if cap is not None and total > cap:
                return None
            j_parts.append(order.take(pos.take(kept)))
            x0_parts.append(g0.take(kept))
            x1_parts.append(g1.take(kept))
            if distances:
                d_parts.append(np.sqrt(d0.take(kept)))
        a = b
    xj = np.empty((2, total))
    if total:
        np.concatenate(x0_parts, out=xj[0])
        np.concatenate(x1_parts, out=xj[1])
    j = np.concatenate(j_parts) if j_parts else np.zeros(0, dtype=np.intp)
    dist = None
    if distances:
        dist = np.concatenate(d_parts) if d_parts else np.zeros(0)
    return NearPairs(counts, j.astype(np.intp, copy=False), xj, dist)


def _scan_compiled(t: FloatArray, xs0: FloatArray, xs1: FloatArray,
                   order: NDArray[np.intp], starts: NDArray[np.int64],
                   lens: NDArray[np.int64], r2: float, cap: int | None,
                   distances: bool) -> NearPairs | None:
    """The candidates' scan of :func:`near_pairs` by :mod:`._ckernel`: a pass that counts
    each centroid's pairs (stopping once over ``cap``), then one that writes them, in the
    same order as numpy's scan (3-5 ns a candidate against 20-25)."""
    ck = _compiled()
    m = len(t)
    tc = np.ascontiguousarray(t, dtype=np.float64)
    st = np.ascontiguousarray(starts, dtype=np.int64)
    ln = np.ascontiguousarray(lens, dtype=np.int64)
    counts = np.empty(m, dtype=np.int64)
    total = ck.pair_counts(tc, xs0, xs1, st, ln, r2, -1 if cap is None else cap, counts)
    if total < 0:
        return None
    j = np.empty(total, dtype=np.int64)
    xj = np.empty((2, total))
    d2 = np.empty(total) if distances else None
    ck.pair_fill(tc, xs0, xs1, np.ascontiguousarray(order, dtype=np.int64), st, ln, r2, j,
                 xj, d2)
    dist = None
    if d2 is not None:
        dist = np.sqrt(d2, out=d2)
    return NearPairs(counts.astype(np.intp, copy=False), j.astype(np.intp, copy=False), xj,
                     dist)

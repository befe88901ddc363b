"""Preparing an impression for the mould distance: size-normalised and despeckled.

Ink specks on the paper become small isolated clusters of points far from the glyph; they
are removed before anything else (:func:`despeckle`). The distance itself is
:mod:`._outline_field`'s.

History (bench/RESULTS.md section 6): the first distance here was the largest *local*
discrepancy after an affine ICP (median nearest-point distance over a point's neighbours).
CPD, even with a smooth kernel, pulled a recut stroke end halfway onto the other mould's,
so no non-rigid step was ever used; the outline field replaced the ICP distance because it
discounts ink spread, which moved every outline point by about the same amount.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ._points import normalise

FloatArray = NDArray[np.float64]

__all__ = ["Impression", "despeckle", "prepare_impression"]

#: Clusters with fewer than this share of the points and smaller than SPECK_EXTENT of
#: the shape's extent are specks.
SPECK_SHARE = 0.02
SPECK_EXTENT = 0.05


def despeckle(points: FloatArray) -> tuple[FloatArray, int]:
    """Drop small isolated clusters of points (ink specks, dust); returns the points kept
    and how many were dropped.

    Points are linked when closer than 3 median nearest-neighbour spacings; a connected
    cluster is a speck when it holds under 2 % of the points and spans under 5 % of the
    shape's extent (its bounding box's longer side). A separate dot stroke of a glyph spans
    a stroke width or more and stays; never more than half the points are dropped.
    """
    n = len(points)
    if n < 8:
        return points, 0
    tree = cKDTree(points)
    d, _ = tree.query(points, k=2)
    spacing = float(np.median(d[:, 1]))
    if spacing <= 0:
        return points, 0
    pairs = tree.query_pairs(3.0 * spacing, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_comp, lab = connected_components(graph, directed=False)
    if n_comp == 1:
        return points, 0
    extent = float(np.ptp(points, axis=0).max())
    counts = np.bincount(lab, minlength=n_comp)
    lo = np.full((n_comp, 2), np.inf)
    hi = np.full((n_comp, 2), -np.inf)
    np.minimum.at(lo, lab, points)
    np.maximum.at(hi, lab, points)
    span = (hi - lo).max(axis=1)
    speck = (counts < SPECK_SHARE * n) & (span < SPECK_EXTENT * extent)
    keep = ~speck[lab]
    if keep.sum() < max(3, n // 2):
        return points, 0
    return points[keep], int(n - keep.sum())


@dataclass(frozen=True)
class Impression:
    """One instance prepared for the mould distance (size-normalised, despeckled)."""

    points: FloatArray  # every point kept, normalised
    dropped: int  # points removed as specks


def prepare_impression(points: ArrayLike, *, name: str = "shape") -> Impression:
    """Normalise (centroid, unit RMS radius) and despeckle one instance."""
    p, _ = normalise(points, name=name)
    kept, dropped = despeckle(p)
    if dropped:
        kept, _ = normalise(kept, name=name)
    return Impression(points=kept, dropped=dropped)

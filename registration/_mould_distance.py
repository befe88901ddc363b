"""A distance between two impressions that is small when one mould printed both.

Printing noise (ink spread or starvation, blur, a small smooth paper warp, a little
rotation and scale) moves an impression's outline everywhere a little; another mould (a
recut stroke end, another carver) moves it a lot somewhere. So, after an affine map (the
affine ICP of eqs. 2-9, started from the shapes as given, on size-normalised shapes):

1. every point's distance to the nearest point of the other shape, both ways;
2. each point's *local discrepancy*: the median of those distances over the point and its
   nearest neighbours on its own shape (an isolated stray point does not count, a stretch
   of outline that sits elsewhere does);
3. the distance is the largest local discrepancy, in units of the shapes' RMS radius.

No non-rigid step: CPD, even with a smooth kernel (beta 2, lambda 3), pulled a recut stroke
end halfway onto the other mould's and halved the smallest distance between two designs
(0.16 -> 0.08 on 永) while same-mould distances stayed where they were (bench RESULTS).

Ink specks on the paper become small isolated clusters of points far from the glyph; they
are removed before anything else (:func:`despeckle`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ._points import normalise, resample

FloatArray = NDArray[np.float64]

__all__ = ["Impression", "despeckle", "impression_descriptor", "local_discrepancy",
           "prepare_impression"]

#: Clusters with fewer than this share of the points and smaller than SPECK_EXTENT of
#: the shape's extent are specks.
SPECK_SHARE = 0.02
SPECK_EXTENT = 0.05
#: Neighbourhood of the local median: this share of the shape's points, within bounds.
LOCAL_SHARE = 0.004
LOCAL_MIN, LOCAL_MAX = 5, 25
#: Points per shape for the affine ICP (the distance itself uses every point).
ICP_POINTS = 120


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
    coarse: FloatArray  # at most ICP_POINTS of them, for the affine ICP
    neighbours: NDArray[np.intp]  # (n, k) own nearest neighbours, for the local median
    tree: cKDTree
    dropped: int  # points removed as specks

    def local_median(self, d: FloatArray) -> FloatArray:
        return np.asarray(np.median(d[self.neighbours], axis=1), dtype=np.float64)


def prepare_impression(points: ArrayLike, *, name: str = "shape") -> Impression:
    """Normalise (centroid, unit RMS radius), despeckle and index one instance."""
    p, _ = normalise(points, name=name)
    kept, dropped = despeckle(p)
    if dropped:
        kept, _ = normalise(kept, name=name)
    k = int(np.clip(round(LOCAL_SHARE * len(kept)), LOCAL_MIN, LOCAL_MAX))
    k = min(k, len(kept))
    tree = cKDTree(kept)
    _, nb = tree.query(kept, k=k)
    nb = np.asarray(nb, dtype=np.intp).reshape(len(kept), k)
    return Impression(points=kept, coarse=resample(kept, ICP_POINTS), neighbours=nb,
                      tree=tree, dropped=dropped)


def local_discrepancy(x: Impression, y: Impression, A: FloatArray, t: FloatArray) -> float:
    """Largest local discrepancy between ``A x + t`` and ``y`` (both ways), in units of the
    RMS radius."""
    xa = x.points @ np.asarray(A).T + np.asarray(t)
    dx, _ = y.tree.query(xa)
    dy, _ = cKDTree(xa).query(y.points)
    return float(max(x.local_median(dx).max(), y.local_median(dy).max()))


def impression_descriptor(imp: Impression, *, bins: int = 16, extent: float = 2.5
                          ) -> FloatArray:
    """A cheap, pose-dependent descriptor: the normalised shape's point density on a
    ``bins x bins`` grid over ``[-extent, extent]^2``, blurred by one cell, unit L2 norm.
    Impressions of one mould (upright, a little rotated) lie close together."""
    h, _, _ = np.histogram2d(imp.points[:, 0], imp.points[:, 1], bins=bins,
                             range=[[-extent, extent], [-extent, extent]])
    from scipy.ndimage import gaussian_filter

    h = gaussian_filter(h, 1.0)
    norm = float(np.sqrt((h**2).sum()))
    return (h / norm if norm > 0 else h).ravel()

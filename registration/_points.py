"""Point-set validation, size normalisation and resampling."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

__all__ = ["Normalization", "as_points", "normalise", "resample"]


def as_points(points: ArrayLike, *, name: str = "points", min_points: int = 3) -> FloatArray:
    """Validate a 2D point set and return it as a C-contiguous float64 array.

    Parameters
    ----------
    points : array_like, shape (n, 2)
        Point coordinates.
    name : str
        Name used in error messages (for example ``"model"``).
    min_points : int
        Smallest accepted number of points.

    Returns
    -------
    ndarray of float64, shape (n, 2)

    Raises
    ------
    ValueError
        If the input is not numeric, not of shape (n, 2), has fewer than `min_points`
        points, or holds a NaN or infinite coordinate.
    """
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array of shape (n, 2): {exc}") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (n, 2); got {arr.shape}")
    if arr.shape[0] < min_points:
        raise ValueError(f"{name} must have at least {min_points} points; got {arr.shape[0]}")
    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise ValueError(
            f"{name} has a non-finite coordinate at point {bad} ({name} must contain only "
            f"finite values; row {bad} is {arr[bad].tolist()}, {int((~finite).sum())} "
            "non-finite rows)"
        )
    return np.ascontiguousarray(arr)


@dataclass(frozen=True)
class Normalization:
    """A similarity map ``u = (p - center) / scale`` to size-normalised coordinates.

    Attributes
    ----------
    center : tuple of float
        Centroid (x, y) of the shape in the user's coordinates.
    scale : float
        Root-mean-square distance of the points from the centroid, in user units.
    """

    center: tuple[float, float]
    scale: float

    def apply(self, points: ArrayLike) -> FloatArray:
        """Map user coordinates to normalised coordinates."""
        p = np.asarray(points, dtype=np.float64)
        return (p - np.asarray(self.center)) / self.scale

    def invert(self, points: ArrayLike) -> FloatArray:
        """Map normalised coordinates back to user coordinates."""
        p = np.asarray(points, dtype=np.float64)
        return p * self.scale + np.asarray(self.center)

    def to_dict(self) -> dict[str, object]:
        return {"center": [self.center[0], self.center[1]], "scale": self.scale}

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> Normalization:
        c = d["center"]
        assert isinstance(c, list | tuple)
        return cls(center=(float(c[0]), float(c[1])), scale=float(d["scale"]))  # type: ignore[arg-type]


def normalise(points: ArrayLike, *, name: str = "points") -> tuple[FloatArray, Normalization]:
    """Centre a shape on its centroid and scale it to unit RMS radius.

    The paper normalises the size of all shapes before registration so that its
    thresholds and errors do not depend on image size; this is that step.

    Parameters
    ----------
    points : array_like, shape (n, 2)
    name : str
        Name used in error messages.

    Returns
    -------
    normalised : ndarray, shape (n, 2)
        Points with zero mean and unit root-mean-square distance from the origin.
    norm : Normalization
        The map, so results can be reported in the user's coordinates.

    Raises
    ------
    ValueError
        If the points are invalid or all coincide (zero size).
    """
    p = as_points(points, name=name)
    center = p.mean(axis=0)
    centred = p - center
    scale = float(np.sqrt((centred**2).sum(axis=1).mean()))
    if not np.isfinite(scale) or scale <= 1e-12 * max(1.0, float(np.abs(p).max())):
        raise ValueError(f"{name} has zero size: all points coincide")
    norm = Normalization(center=(float(center[0]), float(center[1])), scale=scale)
    return centred / scale, norm


def resample(points: ArrayLike, n: int, *, name: str = "points") -> FloatArray:
    """Uniformly subsample a point set to at most `n` points.

    Evenly spaced indices along the given point order are kept (for an ordered contour
    this is close to uniform arc-length sampling). Sets with at most `n` points are
    returned unchanged. Deterministic.

    Parameters
    ----------
    points : array_like, shape (m, 2)
    n : int
        Target number of points, at least 3.
    name : str
        How `points` is called in error messages.

    Returns
    -------
    ndarray, shape (min(m, n), 2)
    """
    p = as_points(points, name=name)
    if n < 3:
        raise ValueError(f"n must be at least 3; got {n}")
    m = p.shape[0]
    if m <= n:
        return p
    idx = np.floor(np.arange(n) * (m / n)).astype(np.intp)
    return p[idx]


def farthest_point_indices(points: FloatArray, n: int) -> IntArray:
    """Indices (sorted) of a farthest-point subsample of `n` of `points` (all if fewer).

    Deterministic and independent of the order of the points up to ties: it starts at the
    point farthest from the centroid and adds, each time, the point farthest from those
    chosen, so the subsample covers the shape evenly whatever the density of the input
    (scans and edge maps are denser in places).
    """
    m = points.shape[0]
    if m <= n:
        return np.arange(m, dtype=np.intp)
    chosen = np.empty(n, dtype=np.intp)
    chosen[0] = int(np.argmax(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))
    d2 = np.sum((points - points[chosen[0]]) ** 2, axis=1)
    x, y = np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1])
    from ._cpd._switch import compiled  # here: the CPD package imports this module

    ckernel = compiled()
    if ckernel is not None:
        # the same sums and picks, bit for bit, in three passes a pick (400 of 2151 points:
        # 4.3 ms -> 1 ms; the coarse stage subsamples every stored shape, in the calling
        # process, before anything runs in parallel)
        picks = np.empty(n, dtype=np.int64)
        picks[0] = chosen[0]
        ckernel.farthest(x, y, d2, picks)
        return np.sort(picks).astype(np.intp, copy=False)
    # one coordinate at a time into preallocated buffers: the same sums (dx^2 + dy^2) as
    # np.sum over the rows, bit for bit, in a sixth of the time
    dx, dy = np.empty(m), np.empty(m)
    for k in range(1, n):
        nxt = int(d2.argmax())
        chosen[k] = nxt
        np.subtract(x, x[nxt], out=dx)
        np.multiply(dx, dx, out=dx)
        np.subtract(y, y[nxt], out=dy)
        np.multiply(dy, dy, out=dy)
        np.add(dx, dy, out=dx)
        np.minimum(d2, dx, out=d2)
    return np.sort(chosen)


def nearest_distances(points: FloatArray) -> FloatArray:
    """Each point's distance to the nearest other point of the same set."""
    d, _ = cKDTree(points).query(points, k=2)
    return np.asarray(d[:, 1], dtype=np.float64)


def rms_distance(a: FloatArray, b: FloatArray) -> float:
    """RMS distance between corresponding points of two (n, 2) sets (row k of `a` with
    row k of `b`), in their units: how far apart two registrations put a model's points."""
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def mean_spacing2(points: FloatArray) -> float:
    """Mean squared nearest-neighbour spacing h^2 of a shape's points."""
    return float(np.mean(nearest_distances(points) ** 2))


#: :func:`sampling_irregularity` of points drawn independently and uniformly along a curve:
#: 0.293-0.297 at 100, 400 and 10^5 points on an ellipse (0.31 at 30), whatever the curve's
#: length or the number of points; evenly spaced points give 0.
IID_SAMPLING_IRREGULARITY = 0.3


def sampling_irregularity(points: FloatArray) -> float:
    """How unevenly a shape's points sample its outline: 0 evenly spaced, about 1 drawn
    independently at random, more when clustered.

    Each point's spacing (its mean distance to its two nearest neighbours, about the
    outline length it stands for) is compared with its two neighbours' spacings: the mean
    of ``log(w_i / mean(w_j, w_k))^2``, divided by its value for independent uniform
    points (:data:`IID_SAMPLING_IRREGULARITY`). Only the point-to-point variation counts:
    an even sampling later stretched by a smooth deformation stays near 0. Fewer than 4
    points: 0 (nothing to compare)."""
    if len(points) < 4:
        return 0.0
    d, i = cKDTree(points).query(points, k=3)
    return _irregularity(d, i)


def _irregularity(d: FloatArray, i: IntArray) -> float:
    """:func:`sampling_irregularity` from each point's nearest neighbours (a k-d tree
    query of k >= 3, the point itself first)."""
    w = d[:, 1:3].mean(axis=1)
    around = 0.5 * (w[i[:, 1]] + w[i[:, 2]])
    ok = (w > 0) & (around > 0)
    if not ok.any():
        return 0.0
    r = np.log(w[ok] / around[ok])
    return float(np.mean(r * r)) / IID_SAMPLING_IRREGULARITY


#: :func:`sampling_weights`: each point's spacing is its mean distance to this many
#: nearest neighbours ...
SAMPLING_WEIGHT_NEIGHBOURS = 4
#: ... as a multiple of the mean spacing, bounded to this factor either way of 1.
SAMPLING_WEIGHT_MAX = 3.0
#: Below this :func:`sampling_irregularity` the sampling is even and every weight is 1.
#: Evenly sampled outlines measure 0.00-0.05 (bench/bench_groundtruth.py's even and
#: arc-length outlines and generated shapes, also after their smooth warps), drawn at
#: random 0.3-1.8; there the spacings' spread is the outline's geometry (its bends and
#: narrow parts), not a sampling to even out, and weighting it only perturbs each CPD
#: (bench/RESULTS.md 7.33).
SAMPLING_WEIGHT_MIN_IRREGULARITY = 0.1


def sampling_weights(points: FloatArray) -> FloatArray:
    """Mixture weights that even out a shape's sampling: about the outline length each
    point stands for, as a fraction of the mean (mean 1).

    Points drawn independently along an outline cluster and leave gaps. As the centroids
    of CPD's mixture each stands for the same mass, so a cluster pulls the subject's
    points harder than the stretch of outline it covers, and a gap less. Weighting each
    centroid by its spacing (its mean distance to its :data:`SAMPLING_WEIGHT_NEIGHBOURS`
    nearest points, divided by the mean spacing and bounded to
    :data:`SAMPLING_WEIGHT_MAX` either way) gives every stretch of outline about the same
    mass. The weights are moved towards 1 as far as the sampling is even: ``1 + rho (s -
    1)`` with ``rho = min(1, sampling_irregularity(points))``, and are all 1 below
    :data:`SAMPLING_WEIGHT_MIN_IRREGULARITY`. So an even sampling, also one stretched by
    a smooth deformation (whose density then varies alike on every shape of a family and
    so carries correspondence), keeps the uniform mixture, and only the point-to-point
    scatter of random draws is evened out. Fewer than 5 points: all 1.

    Parameters
    ----------
    points : ndarray, shape (M, 2)

    Returns
    -------
    ndarray, shape (M,)
        Positive, mean 1.
    """
    p = np.asarray(points, dtype=np.float64)
    m = len(p)
    k = max(SAMPLING_WEIGHT_NEIGHBOURS, 2)
    if m <= k:
        return np.ones(m)
    # one query serves both: the nearest two (the irregularity) and the nearest four
    d, i = cKDTree(p).query(p, k=k + 1)
    rho = min(1.0, _irregularity(d, i))
    if rho < SAMPLING_WEIGHT_MIN_IRREGULARITY:
        return np.ones(m)
    spacing = d[:, 1:SAMPLING_WEIGHT_NEIGHBOURS + 1].mean(axis=1)
    mean = float(spacing.mean())
    s = spacing / mean if mean > 0 else np.ones(m)
    s = np.clip(s, 1.0 / SAMPLING_WEIGHT_MAX, SAMPLING_WEIGHT_MAX)
    s = 1.0 + rho * (s - 1.0)
    return np.asarray(s / s.mean(), dtype=np.float64)

"""What every format shares: the error type, the limits, and the final checks of the points."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: A shape whose points lie within this fraction of its largest coordinate (at least 1) of
#: their centre is refused as having zero size. The library refuses 1e-12 when a job runs
#: (``registration.normalise``); the upload is 1000 times stricter, so that nothing it
#: accepts can fail a job for that reason.
DEGENERATE_RTOL = 1e-9


class IngestError(ValueError):
    """An upload could not be turned into points. ``str(err)`` is the user-facing detail."""


@dataclass(frozen=True)
class Limits:
    """Bounds on what an upload may contain (the service exposes these as settings)."""

    min_points: int = 3
    max_points: int = 20000
    max_coordinate: float = 1e7  # bound on the absolute value of every coordinate
    max_image_pixels: int = 4096 * 4096

    def __post_init__(self) -> None:
        if self.min_points < 1:
            raise ValueError("min_points must be at least 1")
        if self.max_points < self.min_points:
            raise ValueError("max_points must be >= min_points")
        if not self.max_coordinate > 0:
            raise ValueError("max_coordinate must be positive")
        if self.max_image_pixels < 1:
            raise ValueError("max_image_pixels must be positive")


DEFAULT_LIMITS = Limits()


def fmt_num(v: float) -> str:
    return f"{v:g}"


def check_count(n: int, limits: Limits) -> None:
    if n == 0:
        raise IngestError("no points found")
    if n < limits.min_points:
        raise IngestError(
            f"got {n} point{'s' if n != 1 else ''}; at least {limits.min_points} are required "
            f"(setting min_points)"
        )
    if n > limits.max_points:
        raise IngestError(
            f"got {n} points; at most {limits.max_points} are allowed "
            "(setting max_points_per_shape)"
        )


def too_many(limits: Limits, what: str = "file") -> IngestError:
    return IngestError(
        f"{what} has more than {limits.max_points} points, the limit (setting max_points_per_shape)"
    )


def check_size(points: FloatArray) -> None:
    """Refuse a shape of (numerically) zero size: all points equal, or nearly so.

    The size is the root-mean-square distance of the points from their centroid, the
    scale that ``registration.normalise`` divides by.
    """
    centre = points.mean(axis=0)
    spread = float(np.sqrt(((points - centre) ** 2).sum(axis=1).mean()))
    tolerance = DEGENERATE_RTOL * max(1.0, float(np.abs(points).max()))
    if spread > tolerance:
        return
    at = f"({fmt_num(centre[0])}, {fmt_num(centre[1])})"
    if spread == 0.0:
        raise IngestError(
            f"all {len(points)} points are equal, at {at}: the shape has zero size and "
            "cannot be registered"
        )
    raise IngestError(
        f"the {len(points)} points lie within {spread:.3g} (RMS) of their centre {at}, "
        f"at most {DEGENERATE_RTOL:g} of the largest coordinate: the shape has zero size "
        "and cannot be registered"
    )


def finalise(arr: npt.NDArray[np.generic], limits: Limits) -> FloatArray:
    """Check shape, dtype, count, values and size; return a fresh C-contiguous float64 array."""
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise IngestError(f"expected points of shape (n, 2); got shape {tuple(arr.shape)}")
    if arr.dtype.kind not in "iuf":
        raise IngestError(
            f"expected numeric coordinates (integers or floats); got dtype {arr.dtype}"
        )
    check_count(arr.shape[0], limits)
    out = np.array(arr, dtype=np.float64, order="C", copy=True)
    finite = np.isfinite(out).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise IngestError(
            f"point {i} has a non-finite coordinate ({fmt_num(out[i, 0])}, "
            f"{fmt_num(out[i, 1])}); points are counted from 0"
        )
    inside = (np.abs(out) <= limits.max_coordinate).all(axis=1)
    if not inside.all():
        i = int(np.argmin(inside))
        raise IngestError(
            f"point {i} has a coordinate beyond ±{fmt_num(limits.max_coordinate)} "
            f"({fmt_num(out[i, 0])}, {fmt_num(out[i, 1])}), the limit (setting "
            f"max_coordinate); points are counted from 0"
        )
    check_size(out)
    return out

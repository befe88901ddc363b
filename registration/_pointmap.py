"""Maps of the plane: what a point map is (:class:`PointTransform`), and its Jacobians.

Below the transforms (``registration._transform``), their numerical inverse
(``registration._inverse``) and the checks on a warp (``registration._quality``): each of
them takes any map with ``apply`` (and ``apply_with_jacobian`` when it gives its own).
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._points import as_points

FloatArray = NDArray[np.float64]

__all__ = [
    "PointTransform",
    "central_differences",
    "composed_with_jacobian",
    "jacobian_determinants",
    "jacobian_matrices",
]


class PointTransform(Protocol):
    """Anything that maps (n, 2) points to (n, 2) points and serialises to JSON."""

    def apply(self, points: ArrayLike) -> FloatArray: ...

    def to_dict(self) -> dict[str, Any]: ...


def jacobian_determinants(
    transform: PointTransform, points: ArrayLike, *, h: float = 1e-4
) -> FloatArray:
    """Determinant of the Jacobian of `transform` at each point (central differences).

    A non-positive value means the map folds (or collapses) the plane there.

    Parameters
    ----------
    transform : object with ``apply(points) -> points``
        Any of the library's transforms (affine, CPD non-rigid, chain).
    points : array_like, shape (n, 2)
        Where to evaluate, in the transform's input coordinates.
    h : float
        Step of the central differences.

    Returns
    -------
    ndarray, shape (n,)

    Raises
    ------
    ValueError
        If `points` is not a finite (n, 2) array or `h` is not positive.
    """
    if not h > 0:
        raise ValueError(f"h must be positive; got {h}")
    J = jacobian_matrices(transform, as_points(points, name="points", min_points=1), h=h)
    return J[:, 0, 0] * J[:, 1, 1] - J[:, 1, 0] * J[:, 0, 1]


def composed_with_jacobian(steps: tuple[PointTransform, ...], points: ArrayLike
                           ) -> tuple[FloatArray, FloatArray] | None:
    """`steps` applied one after the other, and the Jacobians of the whole map (chain
    rule), when every step gives its own (``apply_with_jacobian``); else None."""
    if not all(hasattr(s, "apply_with_jacobian") for s in steps):
        return None
    p = np.asarray(points, dtype=np.float64)
    jac = np.broadcast_to(np.eye(2), (len(p), 2, 2)).copy()
    for step in steps:
        p, j = step.apply_with_jacobian(p)  # type: ignore[attr-defined]
        jac = j @ jac
    return p, jac


def jacobian_matrices(transform: PointTransform, points: FloatArray, *, h: float = 1e-4
                      ) -> FloatArray:
    """Jacobian matrices, shape (n, 2, 2), of `transform` at (n, 2) `points`:
    ``J[k, a, b] = d out_a / d x_b`` (no input checks: internal). Exact when the transform
    gives its own (``apply_with_jacobian``: the library's affine, CPD and composed maps),
    else by central differences of step `h`."""
    exact = getattr(transform, "apply_with_jacobian", None)
    if exact is not None:
        out: FloatArray = exact(points)[1]
        return out
    return central_differences(transform, points, h)


def central_differences(transform: PointTransform, points: FloatArray, h: float = 1e-4
                         ) -> FloatArray:
    """Jacobian matrices of `transform` at `points` by central differences of step `h`.
    Where the transform gives a non-finite point (a caller's map blowing up far away), the
    matrix is non-finite, quietly: every caller treats a non-finite Jacobian as no usable
    one (a fold, a point without a preimage)."""
    ex = np.array([h, 0.0])
    ey = np.array([0.0, h])
    out = transform.apply(np.concatenate([points + ex, points - ex, points + ey, points - ey]))
    n = points.shape[0]
    with np.errstate(invalid="ignore", over="ignore"):
        dx = (out[:n] - out[n : 2 * n]) / (2 * h)  # d out / dx
        dy = (out[2 * n : 3 * n] - out[3 * n :]) / (2 * h)  # d out / dy
    return np.stack([dx, dy], axis=2)

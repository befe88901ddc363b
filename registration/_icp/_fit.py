"""The closed-form least-squares affine map (eqs. 6-8), batched for many starts, the
bidirectional distance (eq. 9) and the result of one affine ICP."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from .._points import as_points
from .._transform import AffineTransform

FloatArray = NDArray[np.float64]


_MIN_ABS_DET = 1e-8


@dataclass(frozen=True)
class AffineICPResult:
    """Result of :func:`affine_icp`.

    Attributes
    ----------
    A : ndarray, shape (2, 2)
        Linear part of the final map ``x -> A x + t`` (``A_f`` of eq. 9).
    t : ndarray, shape (2,)
        Translation ``t_f``.
    distance : float
        ``D(X, Y)`` of eq. 9 at the final map.
    iterations : int
        ICP iterations of the refinement on the full point sets.
    converged : bool
        Whether the refinement stopped on its tolerance rather than on `max_iter`.
    """

    A: FloatArray
    t: FloatArray
    distance: float
    iterations: int
    converged: bool

    def apply(self, points: ArrayLike) -> FloatArray:
        """Map points with ``x -> A x + t``."""
        return AffineTransform(self.A, self.t).apply(points)

    def to_dict(self) -> dict[str, object]:
        return {
            "A": self.A.tolist(),
            "t": self.t.tolist(),
            "distance": self.distance,
            "iterations": self.iterations,
            "converged": self.converged,
        }


def fit_affine(r: ArrayLike, s: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Closed-form least-squares affine map of eqs. 6-8.

    Minimises ``sum_l || A r_l + t - s_l ||^2`` over ``A`` and ``t``:
    ``t = mean(s) - A mean(r)`` and ``A = (sum_l b_l a_l^T)(sum_l a_l a_l^T)^{-1}`` with
    ``a_l``, ``b_l`` the centred ``r_l``, ``s_l``.

    Parameters
    ----------
    r, s : array_like, shape (K, 2)
        Paired points (the stacked forward and backward correspondences).

    Returns
    -------
    A : ndarray, shape (2, 2)
    t : ndarray, shape (2,)

    Raises
    ------
    ValueError
        If the inputs differ in shape, or `r` is degenerate (collinear), so that
        ``sum a a^T`` is singular and the affine map is not determined.
    """
    ra = as_points(r, name="r", min_points=1)
    sa = as_points(s, name="s", min_points=1)
    if ra.shape != sa.shape:
        raise ValueError(f"r and s must have the same shape; got {ra.shape} and {sa.shape}")
    A, t = _fit_affine_batch(ra[None], sa[None])
    if not np.isfinite(A).all():
        raise ValueError("r is degenerate (collinear or coincident points): A is not determined")
    return A[0], t[0]


def _fit_affine_batch(r: FloatArray, s: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eq. 8 for a batch of S problems: r, s of shape (S, K, 2).

    Returns A of shape (S, 2, 2) and t of shape (S, 2); problems whose ``sum a a^T`` is
    numerically singular get NaN entries.
    """
    r_mean = r.mean(axis=1)
    s_mean = s.mean(axis=1)
    a = r - r_mean[:, None, :]
    b = s - s_mean[:, None, :]
    ba = np.matmul(b.transpose(0, 2, 1), a)  # sum_l b_l a_l^T
    aa = np.matmul(a.transpose(0, 2, 1), a)  # sum_l a_l a_l^T
    det = aa[:, 0, 0] * aa[:, 1, 1] - aa[:, 0, 1] * aa[:, 1, 0]
    trace = aa[:, 0, 0] + aa[:, 1, 1]
    ok = det > 1e-12 * np.maximum(trace, 1e-300) ** 2
    inv = np.empty_like(aa)
    safe_det = np.where(ok, det, 1.0)
    inv[:, 0, 0] = aa[:, 1, 1] / safe_det
    inv[:, 1, 1] = aa[:, 0, 0] / safe_det
    inv[:, 0, 1] = -aa[:, 0, 1] / safe_det
    inv[:, 1, 0] = -aa[:, 1, 0] / safe_det
    A = ba @ inv
    A[~ok] = np.nan
    t = s_mean - np.einsum("sij,sj->si", A, r_mean)
    return A, t


def bidirectional_distance(transformed_model: ArrayLike, subject: ArrayLike) -> float:
    """``D`` of eq. 9 for a model already mapped by the final affine transform.

    ``D = mean_i ||T(x_i) - y_c(i)||^2 + mean_j ||T(x_d(j)) - y_j||^2`` with nearest-
    neighbour correspondences both ways.

    Parameters
    ----------
    transformed_model : array_like, shape (N, 2)
    subject : array_like, shape (M, 2)

    Returns
    -------
    float
    """
    tx = as_points(transformed_model, name="transformed_model", min_points=1)
    y = as_points(subject, name="subject", min_points=1)
    fwd, _ = cKDTree(y).query(tx)
    bwd, _ = cKDTree(tx).query(y)
    return float(np.mean(fwd**2) + np.mean(bwd**2))

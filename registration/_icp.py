"""Affine ICP with bidirectional distance (Du et al. 2016, eqs. 2-9).

The algorithm alternates two steps until the distance stops decreasing:

1. correspondences both ways by nearest neighbour (eq. 3): ``c(i)`` is the subject point
   nearest to the transformed model point ``A x_i + t`` and ``d(j)`` the model point whose
   image is nearest to ``y_j``;
2. the closed-form least-squares affine map on the stacked pairs (eqs. 6-8).

It converges to a local minimum, so :func:`affine_icp` starts it from several poses: the
principal-axes ("whitening") alignment of the two shapes composed with rotations and
reflections, first on coarse subsamples of both shapes (all starts at once, vectorised),
then refines the best start on the full point sets with KD-trees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from ._points import as_points

FloatArray = NDArray[np.float64]

__all__ = [
    "AffineICPResult",
    "affine_icp",
    "bidirectional_distance",
    "fit_affine",
]

_MIN_ABS_DET = 1e-8
_KEEP_STARTS = 3


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
        p = np.asarray(points, dtype=np.float64)
        return p @ self.A.T + self.t

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


# --------------------------------------------------------------------------- starts


def _principal_frame(p: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean and a 2x2 matrix W with ``W (p - mean)`` whitened (unit covariance)."""
    mean = p.mean(axis=0)
    c = p - mean
    cov = c.T @ c / p.shape[0]
    evals, evecs = np.linalg.eigh(cov)
    evals = np.maximum(evals, 1e-12 * max(float(evals.max()), 1e-300))
    whiten = (evecs / np.sqrt(evals)).T  # rows: scaled principal axes
    return mean, whiten


def _initial_poses(
    model: FloatArray, subject: FloatArray, n_rotations: int, allow_reflection: bool
) -> tuple[FloatArray, FloatArray]:
    """Starting maps ``A0 = W_Y^{-1} R W_X`` (R: rotations, optionally reflections).

    Whitening both shapes makes any affine map between them an orthogonal map between the
    whitened shapes, so rotations (and reflections) in the whitened frame cover all
    poses; the principal-axes sign flips are the rotations by 0 and 180 degrees and the
    two reflections.
    """
    mx, wx = _principal_frame(model)
    my, wy = _principal_frame(subject)
    wy_inv = np.linalg.inv(wy)
    angles = np.arange(n_rotations) * (2.0 * np.pi / n_rotations)
    cos, sin = np.cos(angles), np.sin(angles)
    rots = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
    if allow_reflection:
        flip = np.diag([1.0, -1.0])
        rots = np.concatenate([rots, rots @ flip], axis=0)
    A0 = wy_inv[None] @ rots @ wx[None]
    t0 = my[None, :] - np.einsum("sij,j->si", A0, mx)
    return A0, t0


def _coarse(p: FloatArray, n: int) -> FloatArray:
    if p.shape[0] <= n:
        return p
    idx = np.floor(np.arange(n) * (p.shape[0] / n)).astype(np.intp)
    return p[idx]


def _batch_distances(
    x: FloatArray, y: FloatArray, y2: FloatArray, A: FloatArray, t: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Transformed model (S, n, 2) and squared distances (S, n, m) for S maps at once."""
    tx = np.matmul(x[None], A.transpose(0, 2, 1)) + t[:, None, :]
    d2 = np.matmul(tx, -2.0 * y.T)
    d2 += (tx * tx).sum(axis=2)[:, :, None]
    d2 += y2[None, None, :]
    np.maximum(d2, 0.0, out=d2)
    return tx, d2


def _batch_icp(
    x: FloatArray, y: FloatArray, A: FloatArray, t: FloatArray, iterations: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Run affine ICP for S starts at once on small sets by dense distances.

    Returns the final A (S, 2, 2), t (S, 2) and eq. 9 distance (S,) of every start.
    """
    y2 = (y * y).sum(axis=1)
    n_starts = A.shape[0]
    x_b = np.broadcast_to(x, (n_starts, *x.shape))
    y_b = np.broadcast_to(y, (n_starts, *y.shape))
    for _ in range(iterations):
        _, d2 = _batch_distances(x, y, y2, A, t)
        c = d2.argmin(axis=2)  # (S, n): subject index for each model point (eq. 3)
        d = d2.argmin(axis=1)  # (S, m): model index for each subject point
        r = np.concatenate([x_b, x[d]], axis=1)
        s = np.concatenate([y[c], y_b], axis=1)
        A_new, t_new = _fit_affine_batch(r, s)
        good = np.asarray(np.isfinite(A_new).all(axis=(1, 2)))
        det = np.linalg.det(np.where(good[:, None, None], A_new, np.eye(2)))
        good &= np.abs(det) > _MIN_ABS_DET
        A = np.where(good[:, None, None], A_new, A)
        t = np.where(good[:, None], t_new, t)
    _, d2 = _batch_distances(x, y, y2, A, t)
    dist = d2.min(axis=2).mean(axis=1) + d2.min(axis=1).mean(axis=1)
    return A, t, dist


def _refine(
    x: FloatArray,
    y: FloatArray,
    y_tree: cKDTree,
    A: FloatArray,
    t: FloatArray,
    max_iter: int,
    tol: float,
) -> tuple[FloatArray, FloatArray, float, int, bool]:
    """Affine ICP on the full sets from one start (eqs. 3-4 iterated, eq. 9 returned).

    Keeps the best map seen, so the returned D never exceeds the start's.
    """

    def evaluate(A: FloatArray, t: FloatArray) -> tuple[float, FloatArray, FloatArray]:
        tx = x @ A.T + t
        fwd, c = y_tree.query(tx)
        bwd, d = cKDTree(tx).query(y)
        return float(np.mean(fwd**2) + np.mean(bwd**2)), c, d

    dist, c, d = evaluate(A, t)
    converged = False
    iterations = 0
    for iterations in range(1, max_iter + 1):  # noqa: B007
        r = np.concatenate([x, x[d]])
        s = np.concatenate([y[c], y])
        A_new, t_new = _fit_affine_batch(r[None], s[None])
        if not np.isfinite(A_new).all() or abs(np.linalg.det(A_new[0])) <= _MIN_ABS_DET:
            converged = True  # degenerate correspondences: det(A) must stay away from 0
            break
        dist_new, c, d = evaluate(A_new[0], t_new[0])
        if dist_new > dist:
            converged = True  # the eq. 5 step did not lower eq. 9 (N != M weighting)
            break
        decrease = dist - dist_new
        A, t, dist = A_new[0], t_new[0], dist_new
        if decrease <= tol * max(dist, 1e-300):
            converged = True
            break
    return A, t, dist, iterations, converged


def affine_icp(
    model: ArrayLike,
    subject: ArrayLike,
    *,
    init: tuple[ArrayLike, ArrayLike] | None = None,
    n_rotations: int = 8,
    allow_reflection: bool = True,
    coarse_points: int = 64,
    coarse_iterations: int = 20,
    max_iter: int = 100,
    tol: float = 1e-6,
    subject_tree: cKDTree | None = None,
) -> AffineICPResult:
    """Affine ICP with bidirectional distance; returns the map and ``D(X, Y)`` (eq. 9).

    Parameters
    ----------
    model : array_like, shape (N, 2)
        X, the point set that is moved.
    subject : array_like, shape (M, 2)
        Y, the fixed point set.
    init : (A, t), optional
        A single starting map. When omitted, ``n_rotations`` rotations of the principal-
        axes alignment (times two with reflections) are run on coarse subsamples and the
        best is refined on the full sets.
    n_rotations : int
        Rotations tried in the whitened frame (8 = every 45 degrees).
    allow_reflection : bool
        Also try reflected starts. The paper only requires ``det(A) != 0``, so a
        reflection is a valid affine map; set False where mirror images must differ.
    coarse_points : int
        Points per shape in the multi-start stage.
    coarse_iterations : int
        ICP iterations of every start in the multi-start stage.
    max_iter : int
        Largest number of refinement iterations on the full sets.
    tol : float
        Stop when the relative decrease of D is at most `tol`.
    subject_tree : scipy.spatial.cKDTree, optional
        A KD-tree of `subject`, to reuse across calls.

    Returns
    -------
    AffineICPResult

    Raises
    ------
    ValueError
        On invalid point sets or options.

    Notes
    -----
    The result never has ``|det(A)|`` below 1e-8: an update that would make the map
    singular stops the iteration at the previous map.
    """
    x = as_points(model, name="model")
    y = as_points(subject, name="subject")
    if n_rotations < 1:
        raise ValueError(f"n_rotations must be at least 1; got {n_rotations}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be at least 1; got {max_iter}")
    if not tol > 0:
        raise ValueError(f"tol must be positive; got {tol}")
    if coarse_points < 3:
        raise ValueError(f"coarse_points must be at least 3; got {coarse_points}")
    if init is not None:
        A0 = np.asarray(init[0], dtype=np.float64)
        t0 = np.asarray(init[1], dtype=np.float64)
        if A0.shape != (2, 2) or t0.shape != (2,):
            raise ValueError(f"init must be (A (2, 2), t (2,)); got {A0.shape} and {t0.shape}")
        if not (np.isfinite(A0).all() and np.isfinite(t0).all()):
            raise ValueError("init has non-finite entries")
        if abs(np.linalg.det(A0)) <= _MIN_ABS_DET:
            raise ValueError("init A is singular: the paper requires det(A) != 0")
    else:
        A_s, t_s = _initial_poses(x, y, n_rotations, allow_reflection)
        xc, yc = _coarse(x, coarse_points), _coarse(y, coarse_points)
        # every start for a few iterations, then only the most promising ones
        first = max(1, coarse_iterations // 4)
        A_s, t_s, d_s = _batch_icp(xc, yc, A_s, t_s, first)
        keep = np.argsort(d_s, kind="stable")[:_KEEP_STARTS]
        A_s, t_s, d_s = _batch_icp(xc, yc, A_s[keep], t_s[keep], coarse_iterations - first)
        best = int(np.argmin(d_s))
        A0, t0 = A_s[best], t_s[best]
    tree = subject_tree if subject_tree is not None else cKDTree(y)
    A, t, dist, iterations, converged = _refine(x, y, tree, A0, t0, max_iter, tol)
    return AffineICPResult(A=A, t=t, distance=dist, iterations=iterations, converged=converged)

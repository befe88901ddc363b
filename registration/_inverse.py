"""Inverting the library's point maps numerically: the subject onto the model.

A CPD warp ``x -> x + G(x, C) W`` has no closed-form inverse; where it does not fold (the
tree accepts only such warps, see ``registration._quality``) every point of the subject's
region has one preimage, found here by damped Newton iterations on ``f(z) = y`` with the
map's own Jacobians (central differences of a map without them). An affine step is
inverted by the same iteration in one Newton step (its Jacobian is constant).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from ._pointmap import PointTransform, central_differences

FloatArray = NDArray[np.float64]

__all__ = ["invert_points"]

_HALVINGS = 12
#: Points evaluated at once by a Newton iteration's halved trial steps (see `_newton`).
_TRIAL_ROWS = 256


def invert_points(
    transform: PointTransform,
    points: ArrayLike,
    *,
    tol: float = 1e-12,
    max_iter: int = 60,
    h: float = 1e-6,
    seeds: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Preimages of ``points`` under ``transform``: ``z`` with ``transform.apply(z) ~ points``.

    Parameters
    ----------
    transform : object with ``apply(points) -> points``
        A one-to-one map of the plane near the points (an affine step, a CPD warp...).
    points : array_like, shape (n, 2)
        Points in the transform's output coordinates.
    tol : float
        Stop a point once ``|transform.apply(z) - y|`` is at most this (output units).
    max_iter : int
        Newton iterations at most.
    h : float
        Step of the central-difference Jacobian (input units).
    seeds : array_like, shape (k, 2), optional
        Input points to start again from where the first start stalls: each such point
        restarts from the seed whose image is nearest to it. By default a CPD warp's kernel
        centres (its model points), when the transform has them.

    Returns
    -------
    z : ndarray, shape (n, 2)
        The preimages found (the last iterate where a point did not converge).
    residual : ndarray, shape (n,)
        ``|transform.apply(z) - points|`` per point: the accuracy reached.

    Notes
    -----
    Started from ``2 y - f(y)`` (exact for a translation, first order for a small
    displacement); each Newton step is halved until the residual decreases (at most 12
    times). Where the map folds a point may have several preimages, and far from the model's
    region none that this iteration reaches: check ``residual``.
    """
    y = np.asarray(points, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] != 2:
        raise ValueError(f"points must have shape (n, 2); got {y.shape}")
    if not np.isfinite(y).all():
        raise ValueError("points must be finite")
    if not (tol > 0 and h > 0 and max_iter >= 1):
        raise ValueError(f"tol and h must be > 0 and max_iter >= 1; got {tol}, {h}, {max_iter}")
    z, res = _newton(transform, y, 2.0 * y - transform.apply(y), tol, max_iter, h)
    stalled = np.flatnonzero(~(res <= tol))
    starts = _seeds(transform) if seeds is None else np.asarray(seeds, dtype=np.float64)
    if stalled.size and starts is not None and len(starts):
        images = transform.apply(starts)
        usable = np.flatnonzero(np.isfinite(images).all(axis=1))
        # a query too far away for finite distances (|y| ~ 1e200) finds no neighbour: the
        # tree answers with index len(usable), and such a point keeps its first result
        nearest = cKDTree(images[usable]).query(y[stalled])[1] if usable.size else None
        if nearest is not None:
            found = nearest < usable.size
            stalled, nearest = stalled[found], usable[nearest[found]]
            z2, res2 = _newton(transform, y[stalled], starts[nearest].copy(), tol, max_iter, h)
            better = res2 < res[stalled]
            z[stalled[better]] = z2[better]
            res[stalled[better]] = res2[better]
    return z, res


def _seeds(transform: PointTransform) -> FloatArray | None:
    """A CPD warp's kernel centres in its input coordinates, else None."""
    centres = getattr(transform, "control_points", None)
    if centres is None:
        return None
    shift = np.asarray(getattr(transform, "model_shift", np.zeros(2)), dtype=np.float64)
    scale = float(getattr(transform, "model_scale", 1.0))
    seeds: FloatArray = np.asarray(centres, dtype=np.float64) * scale + shift
    return seeds


def _newton(
    transform: PointTransform, y: FloatArray, z: FloatArray, tol: float, max_iter: int, h: float
) -> tuple[FloatArray, FloatArray]:
    """Damped Newton iterations on ``f(z) = y`` from ``z``; returns ``z`` and ``|f(z) - y|``.

    A point whose step, halved :data:`_HALVINGS` times, never lowers its residual has
    stalled and is not iterated again: its next iteration would take the same step from
    the same ``z`` (unless another point's singular Jacobian turned that iteration into
    gradient steps). Iterating it while other points still moved cost a tenth of the
    symmetric finish's inversions on 40 永 glyphs at full resolution (2.1 -> 1.9 s).

    A map that gives its own Jacobian (``apply_with_jacobian``: CPD's field, affine and
    composed maps) is evaluated once per trial point, the Jacobian with the image, so an
    accepted step already holds the next iteration's Jacobian: one kernel product per
    point and step instead of two. With the kernel product's faster box
    (:func:`registration._cpd._fgt.bounding_box`), the 144 inversions of the symmetric
    finishes of the 73 永 edge glyphs (400 points, and full resolution) took 6.0 s instead
    of 7.8."""
    exact = getattr(transform, "apply_with_jacobian", None)

    def image(p: FloatArray) -> tuple[FloatArray, FloatArray | None]:
        if exact is None:
            return transform.apply(p), None
        out, jac = exact(p)
        return out, jac

    f, J = image(z)
    r = f - y
    res = np.linalg.norm(r, axis=1)
    res[~np.isfinite(res)] = np.inf
    stalled = np.zeros(len(y), dtype=bool)
    for _ in range(max_iter):
        active = np.flatnonzero((res > tol) & ~stalled)
        if active.size == 0:
            break
        Ja = central_differences(transform, z[active], h) if J is None else J[active]
        try:
            dz = np.linalg.solve(Ja, r[active][:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # a singular Jacobian: a gradient step instead
            dz = np.einsum("kji,kj->ki", Ja, r[active])
        # the step, halved until it lowers the residual (12 trials at most: 1, 1/2, ...,
        # 1/2^11); the first trial for every active point, the halved ones of the points
        # still without one in as few evaluations as _TRIAL_ROWS allows (the same trials
        # and the same choice, the largest step that lowers the residual, as one
        # evaluation per halving, whose fixed cost made most of an inversion's time)
        pending = np.arange(active.size)
        first = 0
        while pending.size and first < _HALVINGS:
            n_try = max(1, min(_HALVINGS - first, _TRIAL_ROWS // pending.size))
            idx = active[pending]
            steps = 0.5 ** np.arange(first, first + n_try)
            cand = (z[idx][None] - steps[:, None, None] * dz[pending][None]).reshape(-1, 2)
            cand_f, cand_J = image(cand)
            cand_r = cand_f - np.tile(y[idx], (n_try, 1))
            cand_res = np.linalg.norm(cand_r, axis=1)
            ok = (np.isfinite(cand_res) & (cand_res < np.tile(res[idx], n_try))).reshape(
                n_try, idx.size)
            found = ok.any(axis=0)
            pick = ok.argmax(axis=0)[found] * idx.size + np.flatnonzero(found)
            won = idx[found]
            z[won] = cand[pick]
            r[won] = cand_r[pick]
            res[won] = cand_res[pick]
            if J is not None and cand_J is not None:
                J[won] = cand_J[pick]
            pending = pending[~found]
            first += n_try
        stalled[active[pending]] = True
    return z, res

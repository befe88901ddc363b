"""affine_icp: the public single-pair affine ICP."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .._pose import PoseSpec
from ._fit import _MIN_ABS_DET, AffineICPResult
from ._pairwise import _refine, pairwise_affine_icp, prepare_shape


def affine_icp(
    model: ArrayLike,
    subject: ArrayLike,
    *,
    init: tuple[ArrayLike, ArrayLike] | None = None,
    pose: str | None = None,
    max_rotation: float | None = None,
    n_rotations: int = 8,
    allow_reflection: bool | None = None,
    coarse_points: int = 48,
    coarse_iterations: int = 12,
    max_iter: int = 100,
    tol: float = 1e-6,
) -> AffineICPResult:
    """Affine ICP with bidirectional distance; returns the map and ``D(X, Y)`` (eq. 9).

    Parameters
    ----------
    model : array_like, shape (N, 2)
        X, the point set that is moved.
    subject : array_like, shape (M, 2)
        Y, the fixed point set.
    init : (A, t), optional
        A single starting map. When omitted, the pose as given and the starts of `pose`
        are run on coarse subsamples, the best few continued, and the best of those
        refined on the full sets.
    pose : {"rotation", "as_given", "upright", "affine"}, optional
        Which poses the starts cover (see :mod:`registration._pose`): any rotation
        (default), only the shapes as given, rotations within +-`max_rotation` of them,
        or any affine map including reflections (the paper's ``det(A) != 0``). Outside
        "affine" the map keeps ``det(A) > 0``: it never mirrors.
    max_rotation : float, optional
        Half-width in degrees of the "upright" mode (default 30); given alone, it
        selects that mode.
    n_rotations : int
        Rotations tried in the whitened frame (8 = every 45 degrees).
    allow_reflection : bool, optional
        Deprecated spelling of the pose: True means ``pose="affine"``.
    coarse_points : int
        Points per shape in the multi-start stage.
    coarse_iterations : int
        ICP iterations of the multi-start stage.
    max_iter : int
        Largest number of refinement iterations on the full sets.
    tol : float
        Stop when the relative decrease of D is at most `tol`.

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
    if n_rotations < 1:
        raise ValueError(f"n_rotations must be at least 1; got {n_rotations}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be at least 1; got {max_iter}")
    if not tol > 0:
        raise ValueError(f"tol must be positive; got {tol}")
    if coarse_iterations < 1:
        raise ValueError(f"coarse_iterations must be at least 1; got {coarse_iterations}")
    if allow_reflection:
        if pose not in (None, "affine"):
            raise ValueError(f"allow_reflection=True contradicts pose={pose!r}")
        pose = "affine"
    spec = PoseSpec.resolve(pose, max_rotation)
    px = prepare_shape(model, coarse_points=coarse_points, name="model")
    py = prepare_shape(subject, coarse_points=coarse_points, name="subject")
    if init is not None:
        A0 = np.asarray(init[0], dtype=np.float64)
        t0 = np.asarray(init[1], dtype=np.float64)
        if A0.shape != (2, 2) or t0.shape != (2,):
            raise ValueError(f"init must be (A (2, 2), t (2,)); got {A0.shape} and {t0.shape}")
        if not (np.isfinite(A0).all() and np.isfinite(t0).all()):
            raise ValueError("init has non-finite entries")
        if abs(np.linalg.det(A0)) <= _MIN_ABS_DET:
            raise ValueError("init A is singular: the paper requires det(A) != 0")
        if not spec.allow_reflection and np.linalg.det(A0) < 0:
            raise ValueError(
                f"init A is a reflection (det(A) < 0), which pose={spec.mode!r} excludes; "
                "use pose='affine' to allow mirror images"
            )
    else:
        res = pairwise_affine_icp(
            {0: px, 1: py}, [(0, 1)], n_rotations=n_rotations, pose=spec,
            coarse_iterations=coarse_iterations,
        )[0]
        A0, t0 = res.A, res.t
    A, t, dist, it, conv = _refine(px.points, py.points, py.tree, A0, t0, max_iter, tol,
                                   proper=not spec.allow_reflection)
    return AffineICPResult(A=A, t=t, distance=dist, iterations=it, converged=conv)

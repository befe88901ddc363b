"""Affine ICP between one pair of prepared shapes from many start poses: principal-axes
frames composed with rotations, all starts at once on coarse subsamples, the best refined
on the full point sets with KD-trees."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from .._cpd._switch import compiled as _compiled
from .._points import as_points
from .._pose import PoseSpec
from ._fit import _MIN_ABS_DET, _fit_affine_batch

FloatArray = NDArray[np.float64]

_KEEP_STARTS = 3  # coarse starts refined further
_UPRIGHT_STEP_DEG = 15.0  # rotation step of the upright mode's starts


def _principal_frame(p: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean and a 2x2 matrix W with ``W (p - mean)`` whitened (unit covariance)."""
    mean = p.mean(axis=0)
    c = p - mean
    cov = c.T @ c / p.shape[0]
    evals, evecs = np.linalg.eigh(cov)
    evals = np.maximum(evals, 1e-12 * max(float(evals.max()), 1e-300))
    if np.linalg.det(evecs) < 0:  # a proper frame: starts built on it keep det(A) > 0
        evecs = evecs * np.array([1.0, -1.0])
    whiten = (evecs / np.sqrt(evals)).T  # rows: scaled principal axes
    return mean, whiten


def _coarse(p: FloatArray, n: int) -> FloatArray:
    """Exactly `n` points at evenly spaced indices (repeating points of smaller sets), so
    that subsamples of different shapes stack into one batch."""
    idx = np.floor(np.arange(n) * (p.shape[0] / n)).astype(np.intp)
    return p[idx]


def _as_components(p: NDArray[np.floating], n_b: int) -> tuple[FloatArray, FloatArray]:
    """The x and y coordinates of (B, n, 2) or (n, 2) points as contiguous (B, n) arrays."""
    if p.ndim == 2:
        p = np.broadcast_to(p, (n_b, *p.shape))
    return np.ascontiguousarray(p[..., 0]), np.ascontiguousarray(p[..., 1])


def _rows(p0: FloatArray, p1: FloatArray) -> NDArray[np.float32]:
    """``[p, 1]`` per point, float32, shape (B, n, 3)."""
    out = np.empty((*p0.shape, 3), dtype=np.float32)
    out[..., 0] = p0
    out[..., 1] = p1
    out[..., 2] = 1.0
    return out


def _cols(p0: FloatArray, p1: FloatArray) -> NDArray[np.float32]:
    """``[-2 p, |p|^2]`` per point as columns, float32, shape (B, 3, n).

    ``[x, 1] . [-2 y, |y|^2] = |x - y|^2 - |x|^2``: one (B, n, 3) x (B, 3, m) product
    gives every row's squared distances up to a constant per row, which is all an argmin
    along the row needs, in one pass over the (B, n, m) array.
    """
    out = np.empty((p0.shape[0], 3, p0.shape[1]), dtype=np.float32)
    out[:, 0] = -2.0 * p0
    out[:, 1] = -2.0 * p1
    out[:, 2] = p0 * p0 + p1 * p1
    return out


def _batch_icp(
    x: FloatArray, y: FloatArray, A: FloatArray, t: FloatArray, iterations: int,
    tol: float = 0.0, proper: bool = False, rigid: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Affine ICP for B problems at once by dense distances (small point sets).

    x : (B, n, 2) or (n, 2); y : (B, m, 2) or (m, 2); A : (B, 2, 2); t : (B, 2).
    Returns the final A, t and eq. 9 distance (B,) of every problem. Problems whose D
    stops decreasing by more than `tol` (relative) are frozen; the loop ends early when
    all are. Nearest neighbours are found by the compiled pass (:mod:`registration._cpd.
    _ckernel`, exact squared distances, both directions at once), or without it in
    float32 (half the memory traffic; ties aside, the same neighbours); D and the eq. 8
    fit are computed in float64 from moment sums of the coordinates, centred per
    problem so that the sums keep their precision in any user coordinates. With
    `proper`, an update that would give ``det(A) <= 0`` (a reflection) freezes the
    problem at its previous map. With `rigid`, each update is the rotation (no scale, no
    reflection) that best fits the same stacked pairs (Procrustes), as in
    :func:`rigid_turns`.
    """
    n_b = A.shape[0]
    x0, x1 = _as_components(x, n_b)
    y0, y1 = _as_components(y, n_b)
    n, m = x0.shape[1], y0.shape[1]
    # centre every problem: x' = x - cx, y' = y - cy, t' = t + A cx - cy
    cx = np.stack([x0.mean(axis=1), x1.mean(axis=1)], axis=1)
    cy = np.stack([y0.mean(axis=1), y1.mean(axis=1)], axis=1)
    x0, x1 = x0 - cx[:, :1], x1 - cx[:, 1:]
    y0, y1 = y0 - cy[:, :1], y1 - cy[:, 1:]
    A = A.copy()
    t = t + np.einsum("bij,bj->bi", A, cx) - cy
    compiled = _compiled()  # nearest neighbours in one compiled pass (see below)
    if compiled is None:
        y_rows, y_cols = _rows(y0, y1), _cols(y0, y1)
    # the model half of eq. 8's stacked pairs is fixed: its moments once
    x00, x01, x11 = (x0 * x0).sum(axis=1), (x0 * x1).sum(axis=1), (x1 * x1).sum(axis=1)
    A_prev, t_prev = A.copy(), t.copy()
    dist = np.full(n_b, np.inf)
    idx = np.arange(n_b)  # problems still iterating: only they are computed
    for it in range(iterations + 1):
        X0, X1, Y0, Y1 = x0[idx], x1[idx], y0[idx], y1[idx]
        Ai, ti = A[idx], t[idx]
        tx0 = Ai[:, 0, :1] * X0 + Ai[:, 0, 1:] * X1 + ti[:, :1]
        tx1 = Ai[:, 1, :1] * X0 + Ai[:, 1, 1:] * X1 + ti[:, 1:]
        if compiled is not None:
            # both directions from one pass over the pairs, exact squared distances in
            # float64 (the whole batch in 0.83x the time of numpy's two float32
            # products and argmins)
            c = np.empty((idx.size, n), dtype=np.int64)
            d = np.empty((idx.size, m), dtype=np.int64)
            compiled.nearest(np.ascontiguousarray(tx0), np.ascontiguousarray(tx1),
                             np.ascontiguousarray(Y0), np.ascontiguousarray(Y1), n, m, c,
                             None, d, None)
        else:
            c = np.matmul(_rows(tx0, tx1), y_cols[idx]).argmin(axis=2)  # eq. 3, forward
            d = np.matmul(y_rows[idx], _cols(tx0, tx1)).argmin(axis=2)  # and backward
        yc0, yc1 = np.take_along_axis(Y0, c, axis=1), np.take_along_axis(Y1, c, axis=1)
        txd0, txd1 = np.take_along_axis(tx0, d, axis=1), np.take_along_axis(tx1, d, axis=1)
        new = ((tx0 - yc0) ** 2 + (tx1 - yc1) ** 2).mean(axis=1) + (
            (txd0 - Y0) ** 2 + (txd1 - Y1) ** 2
        ).mean(axis=1)
        old = dist[idx]
        worse = new > old  # the last step raised eq. 9: undo it and freeze
        if worse.any():
            back = idx[worse]
            A[back], t[back] = A_prev[back], t_prev[back]
            new[worse] = old[worse]
        dist[idx] = new
        going = ~worse & (old - new > tol * new)
        if it == iterations or not going.any():
            break
        g = idx[going]
        X0, X1, Y0, Y1 = X0[going], X1[going], Y0[going], Y1[going]
        yc0, yc1, dg = yc0[going], yc1[going], d[going]
        xd0, xd1 = np.take_along_axis(X0, dg, axis=1), np.take_along_axis(X1, dg, axis=1)
        # eq. 8 on the stacked pairs (x_i, y_c(i)) and (x_d(j), y_j), from moment sums
        k = float(n + m)
        r0 = (X0.sum(axis=1) + xd0.sum(axis=1)) / k
        r1 = (X1.sum(axis=1) + xd1.sum(axis=1)) / k
        s0 = (yc0.sum(axis=1) + Y0.sum(axis=1)) / k
        s1 = (yc1.sum(axis=1) + Y1.sum(axis=1)) / k
        aa00 = x00[g] + (xd0 * xd0).sum(axis=1) - k * r0 * r0
        aa01 = x01[g] + (xd0 * xd1).sum(axis=1) - k * r0 * r1
        aa11 = x11[g] + (xd1 * xd1).sum(axis=1) - k * r1 * r1
        ba00 = (yc0 * X0).sum(axis=1) + (Y0 * xd0).sum(axis=1) - k * s0 * r0
        ba01 = (yc0 * X1).sum(axis=1) + (Y0 * xd1).sum(axis=1) - k * s0 * r1
        ba10 = (yc1 * X0).sum(axis=1) + (Y1 * xd0).sum(axis=1) - k * s1 * r0
        ba11 = (yc1 * X1).sum(axis=1) + (Y1 * xd1).sum(axis=1) - k * s1 * r1
        A_new = np.empty((g.size, 2, 2))
        if rigid:
            # the rotation maximising trace(R^T H), H = sum (s - s_mean)(r - r_mean)^T
            ok = (aa00 + aa11) > 0
            theta = np.arctan2(ba10 - ba01, ba00 + ba11)
            cos, sin = np.cos(theta), np.sin(theta)
            A_new[:, 0, 0], A_new[:, 0, 1] = cos, -sin
            A_new[:, 1, 0], A_new[:, 1, 1] = sin, cos
        else:
            det_aa = aa00 * aa11 - aa01 * aa01
            ok = det_aa > 1e-12 * (aa00 + aa11) ** 2
            det_aa = np.where(ok, det_aa, 1.0)
            A_new[:, 0, 0] = (ba00 * aa11 - ba01 * aa01) / det_aa
            A_new[:, 0, 1] = (ba01 * aa00 - ba00 * aa01) / det_aa
            A_new[:, 1, 0] = (ba10 * aa11 - ba11 * aa01) / det_aa
            A_new[:, 1, 1] = (ba11 * aa00 - ba10 * aa01) / det_aa
        t_new = np.stack([s0, s1], axis=1) - np.einsum("bij,bj->bi", A_new,
                                                        np.stack([r0, r1], axis=1))
        det = A_new[:, 0, 0] * A_new[:, 1, 1] - A_new[:, 0, 1] * A_new[:, 1, 0]
        good = ok & np.isfinite(det) & ((det if proper else np.abs(det)) > _MIN_ABS_DET)
        idx = g[good]
        A_prev[idx], t_prev[idx] = A[idx], t[idx]
        A[idx], t[idx] = A_new[good], t_new[good]
        if idx.size == 0:
            break
    # back to the problems' own coordinates: t = t' - A cx + cy
    t = t - np.einsum("bij,bj->bi", A, cx) + cy
    return A, t, dist


class PairPose(NamedTuple):
    """Affine ICP of one (model i, subject j) pair: the best pose and the pose as given.

    ``D, A, t``: the map with the smallest D (eq. 9) over every start the pose mode
    allows. ``D_given, A_given, t_given``: the local optimum reached from the shapes as
    given (the identity on size-normalised shapes), always computed so that a rotated
    pose can be weighed against it.
    """

    i: int
    j: int
    D: float
    A: FloatArray
    t: FloatArray
    D_given: float
    A_given: FloatArray
    t_given: FloatArray


def _start_rotations(pose: PoseSpec, n_rotations: int) -> FloatArray:
    """Rotation (and reflection) matrices of the starts other than the pose as given."""
    if pose.mode == "as_given":
        return np.zeros((0, 2, 2))
    if pose.mode == "upright":
        assert pose.max_rotation is not None
        k = int(np.ceil(pose.max_rotation / _UPRIGHT_STEP_DEG))
        angles = np.deg2rad(np.linspace(-pose.max_rotation, pose.max_rotation, 2 * k + 1))
        angles = angles[np.abs(angles) > 1e-12]  # 0 is the pose as given, start 0
    else:
        angles = np.arange(n_rotations) * (2.0 * np.pi / n_rotations)
    cos, sin = np.cos(angles), np.sin(angles)
    rots = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
    if pose.allow_reflection:
        rots = np.concatenate([rots, rots @ np.diag([1.0, -1.0])], axis=0)
    return rots


def pairwise_affine_icp(
    shapes: dict[int, PreparedShape],
    pairs: list[tuple[int, int]],
    *,
    n_rotations: int = 8,
    pose: PoseSpec | None = None,
    coarse_iterations: int = 12,
    refine_iterations: int = 40,
    tol: float = 1e-4,
) -> list[PairPose]:
    """Affine ICP for many (model, subject) pairs at once.

    All pairs go through the same vectorised stages: every start of every pair on the
    coarse subsamples, the best few starts per pair (and always the pose as given)
    continued, refined on the mid subsamples; the best of them and the pose as given are
    refined on the medium subsamples, and D (eq. 9) evaluated on the full point sets.
    When both (i, j) and (j, i) are asked for, the second starts from the inverses of the
    first's maps instead of a multi-start search.

    Starts: start 0 is the pose as given (isotropic scale from the covariances, no
    rotation); the others depend on `pose` (see :mod:`registration._pose`): rotations
    within +-max_rotation of it ("upright"), `n_rotations` rotations of the principal-axes
    alignment ("rotation"), and their reflections too ("affine"). Outside "affine", ICP
    keeps ``det(A) > 0``.
    """
    if not pairs:
        return []
    pose = pose if pose is not None else PoseSpec()
    proper = not pose.allow_reflection
    pair_set = set(pairs)
    forward = [p for p in pairs if (p[1], p[0]) not in pair_set or p[0] < p[1]]
    fwd_set = set(forward)
    reverse = [p for p in pairs if p not in fwd_set]
    rots = _start_rotations(pose, n_rotations)
    n_s = 1 + rots.shape[0]
    nf = len(forward)
    # stage 1: every start of every forward pair; start 0 is the pose as given
    A_l, t_l, xs, ys = [], [], [], []
    for i, j in forward:
        x, y = shapes[i], shapes[j]
        scale = np.sqrt(abs(np.linalg.det(x.whiten) / np.linalg.det(y.whiten)))
        if pose.any_rotation:
            A_rot = np.linalg.inv(y.whiten)[None] @ rots @ x.whiten[None]
        else:  # isotropic scale from the covariances, then the rotation
            A_rot = scale * rots
        A_s = np.concatenate([scale * np.eye(2)[None], A_rot])
        A_l.append(A_s)
        t_l.append(y.mean[None, :] - np.einsum("sij,j->si", A_s, x.mean))
        xs.append(np.broadcast_to(x.coarse, (n_s, *x.coarse.shape)))
        ys.append(np.broadcast_to(y.coarse, (n_s, *y.coarse.shape)))
    xc, yc = np.concatenate(xs), np.concatenate(ys)
    first = max(1, coarse_iterations // 4)
    A_b, t_b, d_b = _batch_icp(xc, yc, np.concatenate(A_l), np.concatenate(t_l), first,
                               proper=proper)
    # stage 2: the pose as given and the best other starts of each pair
    others = d_b.reshape(nf, n_s)[:, 1:]
    best = 1 + np.argsort(others, axis=1, kind="stable")[:, :_KEEP_STARTS]
    keep = np.concatenate([np.zeros((nf, 1), dtype=np.intp), best], axis=1)
    n_keep = keep.shape[1]
    sel = (keep + n_s * np.arange(nf)[:, None]).ravel()
    A_b, t_b, d_b = _batch_icp(xc[sel], yc[sel], A_b[sel], t_b[sel],
                               max(1, coarse_iterations - first), proper=proper)
    # stage 3: the surviving starts on finer subsamples; then, on finer still, each
    # pair's best and its pose as given (column 0)
    A_f, t_f, d_f = _batch_icp(
        np.stack([shapes[i].mid for i, _ in forward for _ in range(n_keep)]),
        np.stack([shapes[j].mid for _, j in forward for _ in range(n_keep)]),
        A_b, t_b, refine_iterations, tol, proper=proper,
    )
    base = n_keep * np.arange(nf)
    pick = np.stack([d_f.reshape(nf, n_keep).argmin(axis=1) + base, base], axis=1).ravel()
    A_f, t_f = _batch_icp(
        np.stack([shapes[i].medium for i, _ in forward for _ in range(2)]),
        np.stack([shapes[j].medium for _, j in forward for _ in range(2)]),
        A_f[pick], t_f[pick], refine_iterations, tol, proper=proper,
    )[:2]
    found = {p: (A_f[2 * k], t_f[2 * k], A_f[2 * k + 1], t_f[2 * k + 1])
             for k, p in enumerate(forward)}
    if reverse:
        inv = [np.linalg.inv(found[(j, i)][a]) for i, j in reverse for a in (0, 2)]
        A_r = np.stack(inv)
        t_r = -np.einsum("sij,sj->si", A_r,
                         np.stack([found[(j, i)][a] for i, j in reverse for a in (1, 3)]))
        A_r, t_r = _batch_icp(
            np.stack([shapes[i].medium for i, _ in reverse for _ in range(2)]),
            np.stack([shapes[j].medium for _, j in reverse for _ in range(2)]),
            A_r, t_r, refine_iterations, tol, proper=proper,
        )[:2]
        found.update({p: (A_r[2 * k], t_r[2 * k], A_r[2 * k + 1], t_r[2 * k + 1])
                      for k, p in enumerate(reverse)})
    # stage 4: D of eq. 9 on the full point sets, for the best map and the pose as given
    out = []
    for i, j in pairs:
        A, t, A_g, t_g = (np.array(v) for v in found[(i, j)])
        d = _full_distance(shapes[i], shapes[j], A, t)
        same = np.allclose(A, A_g, atol=1e-9) and np.allclose(t, t_g, atol=1e-9)
        d_g = d if same else _full_distance(shapes[i], shapes[j], A_g, t_g)
        if d_g <= d:  # the pose as given is also the best: one map
            A, t, d = A_g, t_g, d_g
        out.append(PairPose(i, j, d, A, t, d_g, A_g, t_g))
    return out


def rigid_turns(
    x: FloatArray, y: FloatArray, *, n_starts: int = 12, keep: int = _KEEP_STARTS,
    coarse_points: int = 96, points: int = 192, iterations: int = 20, tol: float = 1e-4,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rigid ICP (eq. 9's bidirectional closest points, each step the best rotation:
    no scale, no reflection) of the points `x` onto `y` from `n_starts` turns evenly
    spaced from 0, the translation of each putting the centroids together. As
    :func:`pairwise_affine_icp`'s starts: all on evenly spaced subsamples of
    `coarse_points` first, then the pose as given (start 0) and the `keep` best others
    on subsamples of `points`. Returns their rotations (k, 2, 2), translations (k, 2)
    and D (k,), the pose as given's first.

    For two shapes of one size (the similarity's normalised shapes) the rotation alone
    says which way round one lies on the other. Affine ICP's shear and scale fit a glyph
    of many parallel strokes about as well at several turns, so its D ranks turns poorly:
    over 1390 pairs of glyphs turned apart (5 characters x 2 fonts), the turn other than
    the pose as given that rigid D ranks first was the true one on 84% of them
    (bench/RESULTS.md 7.46).
    """
    if n_starts < 1:
        raise ValueError(f"n_starts must be at least 1; got {n_starts}")
    angles = np.arange(n_starts) * (2.0 * np.pi / n_starts)
    cos, sin = np.cos(angles), np.sin(angles)
    R = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
    xc, yc = _coarse(x, min(coarse_points, len(x))), _coarse(y, min(coarse_points, len(y)))
    t = yc.mean(axis=0)[None] - R @ xc.mean(axis=0)
    R, t, D = _batch_icp(xc, yc, R, t, max(1, iterations // 3), tol, proper=True, rigid=True)
    pick = np.concatenate([[0], 1 + np.argsort(D[1:], kind="stable")[:keep]])
    xs, ys = _coarse(x, min(points, len(x))), _coarse(y, min(points, len(y)))
    return _batch_icp(xs, ys, R[pick], t[pick], iterations, tol, proper=True, rigid=True)


# Largest n * m for which D on the full sets comes from one dense float32 product (4 bytes
# per entry, in blocks); above it, KD-trees (O(n log m) but ~0.5 us per query here).
_DENSE_FULL_MAX = 2_000_000


def _full_distance(x: PreparedShape, y: PreparedShape, A: FloatArray, t: FloatArray) -> float:
    """D of eq. 9 between ``A x + t`` and ``y`` on all points.

    Pairs up to ``_DENSE_FULL_MAX`` entries use one dense float32 product of augmented
    points, ``[tx, |tx|^2, 1] . [-2 y, 1, |y|^2] = |tx - y|^2`` (coordinates centred on
    the subject's centroid), and take the minimum along rows and columns; about 2.5x
    faster than two KD-tree queries at 1000 x 1000 points. The product runs as a stack of
    blocks of at most 64 rows, each small enough that OpenBLAS keeps it on one thread (no
    oversubscription in a process-pool worker). Float32 rounding bounds the error of D by
    about 1e-6 times the squared radius of the shapes (1e-6 on size-normalised shapes).
    Larger pairs use KD-trees.
    """
    tx = x.points @ A.T + t
    n, m = tx.shape[0], y.points.shape[0]
    if n * m > _DENSE_FULL_MAX:
        fwd_d, _ = y.tree.query(tx)
        bwd_d, _ = cKDTree(tx).query(y.points)
        return float(np.mean(fwd_d**2) + np.mean(bwd_d**2))
    centre = y.mean
    tc, yc = tx - centre, y.points - centre
    # 64-row blocks, fewer for large m: each block's product stays <= 256 kB (in cache) and
    # below OpenBLAS's threading threshold (m * k * n < 2^18)
    size = max(8, min(64, 65536 // m))
    blocks = -(-n // size)
    rows = np.empty((blocks * size, 4), dtype=np.float32)
    rows[:n, :2] = tc
    rows[:n, 2] = (tc * tc).sum(axis=1)
    rows[:, 3] = 1.0
    rows[n:] = rows[n - 1]  # padding repeats the last point: no effect on minima
    cols = np.empty((4, m), dtype=np.float32)
    cols[:2] = -2.0 * yc.T
    cols[2] = 1.0
    cols[3] = (yc * yc).sum(axis=1)
    d2 = np.matmul(rows.reshape(blocks, size, 4), cols)  # (blocks, size, m)
    fwd2 = d2.min(axis=2).ravel()[:n]
    bwd2 = d2.min(axis=1).min(axis=0)
    return float(np.maximum(fwd2, 0.0).mean(dtype=np.float64)
                 + np.maximum(bwd2, 0.0).mean(dtype=np.float64))


def fit_rigid(r: FloatArray, s: FloatArray, mirror: bool = False
              ) -> tuple[FloatArray, FloatArray]:
    """The isometry ``(R, t)`` minimising ``sum_l || R r_l + t - s_l ||^2``: a rotation,
    or with `mirror` a rotation-reflection (Procrustes)."""
    mu_r, mu_s = r.mean(axis=0), s.mean(axis=0)
    u, _, vt = np.linalg.svd((s - mu_s).T @ (r - mu_r))
    if (np.linalg.det(u @ vt) < 0) != mirror:
        u[:, -1] = -u[:, -1]
    R = u @ vt
    return np.asarray(R, dtype=np.float64), np.asarray(mu_s - R @ mu_r, dtype=np.float64)


def _refine(
    x: FloatArray,
    y: FloatArray,
    y_tree: cKDTree,
    A: FloatArray,
    t: FloatArray,
    max_iter: int,
    tol: float,
    proper: bool = False,
    rigid: bool = False,
) -> tuple[FloatArray, FloatArray, float, int, bool]:
    """Affine ICP on the full sets from one start (eqs. 3-4 iterated, eq. 9 returned).

    Keeps the best map seen, so the returned D never exceeds the start's. With `proper`,
    an update with ``det(A) <= 0`` stops the iteration at the previous map. With
    `rigid`, each step is the best isometry of the start's handedness instead of the
    best affine map (Procrustes; :func:`fit_rigid`).
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
        if rigid:
            R, tr = fit_rigid(r, s, mirror=bool(np.linalg.det(A) < 0))
            A_new, t_new = R[None], tr[None]
        else:
            A_new, t_new = _fit_affine_batch(r[None], s[None])
        det = float(np.linalg.det(A_new[0])) if np.isfinite(A_new).all() else 0.0
        if (det if proper else abs(det)) <= _MIN_ABS_DET:
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


@dataclass(frozen=True)
class PreparedShape:
    """A shape with what affine ICP reuses across pairs: principal frame, three
    subsamples (coarse for the multi-start search, mid and medium for refinement) and a
    KD-tree of all points. Build once per shape with :func:`prepare_shape` when registering a shape
    against many others (the similarity of a collection)."""

    points: FloatArray
    coarse: FloatArray
    mid: FloatArray
    medium: FloatArray
    mean: FloatArray
    whiten: FloatArray

    @cached_property
    def tree(self) -> cKDTree:
        """KD-tree of all points, built on first use (dense products serve small sets)."""
        return cKDTree(self.points)


def prepare_shape(
    points: ArrayLike, *, coarse_points: int = 48, medium_points: int = 192, name: str = "points"
) -> PreparedShape:
    """Precompute the parts of affine ICP that depend on one shape only."""
    p = as_points(points, name=name)
    if coarse_points < 3 or medium_points < 3:
        raise ValueError(
            f"coarse_points and medium_points must be at least 3; got {coarse_points}, "
            f"{medium_points}"
        )
    mean, whiten = _principal_frame(p)
    return PreparedShape(
        points=p, coarse=_coarse(p, coarse_points),
        mid=_coarse(p, (coarse_points + medium_points) // 2),
        medium=_coarse(p, medium_points), mean=mean, whiten=whiten,
    )

"""The outline-field mould distance: signed distance fields, a uniform ink shift apart.

Each instance (already normalised: centroid, unit RMS radius, despeckled) becomes a signed
distance field of its outline on a common grid: positive inside the ink, negative outside,
the sign from the parity of the regions the outline encloses (a counter inside a stroke is
outside again). Printing noise acts on that field in two ways:

- ink spread or starvation moves the whole outline along its normal by about the same
  amount, which adds a near-constant offset to the field: the offset (the median
  difference near the outlines) is taken out of the local comparison and counted once,
  ``1 / INK_WEIGHT``, on its own;
- rotation, scale and a little paper warp: every field is aligned by an affine map
  (Gauss-Newton on the fields, robust weights, ink offset as a seventh parameter) to the
  collection's median field, then each pair of near instances once more to each other.

What is left is local: the largest local mean of ``|difference - offset|`` near either
outline (a Gaussian window of about a stroke width). A recut stroke end or another carver's
junction leaves a patch of large difference; noise leaves small differences everywhere.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]

__all__ = ["OutlineField", "align_fields", "field_distance", "grid_centres",
           "local_difference", "outline_field", "pair_distances", "screen", "warp"]

#: Half-width of the common grid (units: RMS radius) and its cells per side; the sign is
#: found on a grid FINE times finer.
EXTENT = 2.5
GRID = 96
FINE = 2
#: Differences count near either outline only: within BAND (RMS radius) of it.
BAND = 0.25
#: Far from the outline the field is clipped: it says "far", not how far.
CLIP = 0.5
#: Window of the local mean (cells, Gaussian sigma).
WINDOW = 1.5
#: The ink offset counts 1 / INK_WEIGHT. Counted in full: the weight variants of one design
#: (Medium and Bold) differ mostly by such an offset, and counting it half merged them at
#: cuts just above 2 x the noise level (measured, bench/RESULTS.md sections 6.1 and 6.2).
INK_WEIGHT = 1.0
_ITERATIONS = 8


@dataclass(frozen=True)
class OutlineField:
    """One instance's signed distance field on the common grid."""

    field: FloatArray  # (GRID, GRID), rows = y
    inside_found: bool  # the outline enclosed at least one region


def _grid(n: int) -> FloatArray:
    return np.asarray(-EXTENT + (np.arange(n) + 0.5) * (2 * EXTENT / n), dtype=np.float64)


def _inside(outline: NDArray[np.bool_], reach: int) -> NDArray[np.bool_]:
    """Regions the outline encloses an odd number of times.

    A region's depth is its parent's plus one along the maximum spanning tree of the
    regions' contacts (pixels of one within the outline's width of the other), rooted at
    the regions touching the border. Along the strongest contact, not the shortest path:
    where a counter's wall is thinner than the rasterised outline (ink spread closed a
    gap by a neck of a pixel or two) the counter touches the outside across one band for
    a few pixels, but the ink along its whole boundary.
    """
    lab, n = ndimage.label(~outline)  # 4-connected: an 8-connected outline is a wall
    if n <= 1:
        return np.zeros_like(outline)
    border = np.unique(np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]])
    border = border[border > 0]
    objects = ndimage.find_objects(lab)
    # contact[k, m]: pixels of m within the outline's width of region k; node 0 = border
    contact = np.zeros((n + 1, n + 1))
    step = 2 * reach + 2
    for k, sl in enumerate(objects, start=1):
        if sl is None:
            continue
        # across the outline: a band 2 reach + 1 pixels wide
        grown = tuple(slice(max(s.start - step, 0), s.stop + step) for s in sl)
        mask = ndimage.binary_dilation(lab[grown] == k, iterations=step)
        counts = np.bincount(lab[grown][mask], minlength=n + 1)
        counts[[0, k]] = 0
        contact[k] += counts
    contact = contact + contact.T
    contact[0, border] = contact[border, 0] = contact.max() * 2 + 1.0  # the border: depth 0
    # maximum spanning tree = minimum spanning tree of (big - contact) over the contacts
    weight = np.where(contact > 0, contact.max() + 1.0 - contact, 0.0)
    tree = minimum_spanning_tree(csr_matrix(weight))
    order, pred = breadth_first_order(tree, 0, directed=False, return_predecessors=True)
    depth = np.full(n + 1, -1)
    depth[0] = -1
    for v in order[1:]:
        depth[v] = depth[pred[v]] + 1
    depth[0] = -2
    return np.asarray((depth[lab] % 2 == 1) & (lab > 0))


def outline_field(points: FloatArray) -> OutlineField:
    """Signed distance field of the outline through `points` (normalised coordinates)."""
    nf = GRID * FINE
    cell = 2 * EXTENT / nf
    ij = np.floor((points + EXTENT) / cell).astype(np.intp)
    ok = ((ij >= 0) & (ij < nf)).all(axis=1)
    outline = np.zeros((nf, nf), dtype=bool)
    outline[ij[ok, 1], ij[ok, 0]] = True
    # close the outline between sampled points
    if len(points) > 1:
        # on a curve a point's two nearest are its neighbours either side: the gap
        # to close is the farther one's distance (a high quantile, not the largest)
        d, _ = cKDTree(points).query(points, k=min(3, len(points)))
        gap = float(np.quantile(d[:, -1], 0.95))
        reach = int(np.clip(np.ceil((gap / cell - 1) / 2), 0, 4))
    else:
        reach = 0
    if reach:
        outline = ndimage.binary_dilation(outline, iterations=reach)
    inside = _inside(outline, reach)
    dist = ndimage.distance_transform_edt(~outline) * cell
    sdf = np.where(inside, dist, -dist)
    coarse = sdf.reshape(GRID, FINE, GRID, FINE).mean(axis=(1, 3))
    return OutlineField(field=np.clip(coarse, -CLIP, CLIP), inside_found=bool(inside.any()))


@lru_cache(maxsize=1)
def _mesh() -> tuple[FloatArray, FloatArray]:
    g = _grid(GRID)
    X, Y = np.meshgrid(g, g)
    return X, Y


def grid_centres() -> FloatArray:
    """Coordinates of the grid's cell centres along either axis (normalised units)."""
    return _grid(GRID)


def warp(f: FloatArray, p: FloatArray) -> FloatArray:
    """``f`` sampled at ``A x + t`` for every grid point x (p = a11 a12 a21 a22 tx ty)."""
    return _warp(f, p)


def _warp(f: FloatArray, p: FloatArray) -> FloatArray:
    """``f`` sampled at ``A x + t`` for every grid point x (p = a11 a12 a21 a22 tx ty)."""
    X, Y = _mesh()
    xs = p[0] * X + p[1] * Y + p[4]
    ys = p[2] * X + p[3] * Y + p[5]
    scale = GRID / (2 * EXTENT)
    coords = np.stack([(ys + EXTENT) * scale - 0.5, (xs + EXTENT) * scale - 0.5])
    return np.asarray(ndimage.map_coordinates(f, coords, order=1, mode="nearest"),
                      dtype=np.float64)


_IDENTITY = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0])


def align_fields(moving: FloatArray, target: FloatArray,
                 start: FloatArray | None = None, iterations: int = _ITERATIONS
                 ) -> FloatArray:
    """Affine parameters p (a11 a12 a21 a22 tx ty) with ``moving(A x + t) + c ~ target(x)``
    near the outlines, by Gauss-Newton with Tukey weights (a recut patch is not pulled
    onto the other mould); the ink offset c is fitted along and dropped."""
    p = (_IDENTITY if start is None else start).copy()
    X, Y = _mesh()
    h = 2 * EXTENT / GRID
    near_target = np.abs(target) < BAND
    best, best_p = np.inf, p
    for _ in range(iterations):
        w_f = _warp(moving, p)
        band = near_target | (np.abs(w_f) < BAND)
        if band.sum() < 12:
            break
        r = (target - w_f)[band]
        r_c = r - np.median(r)
        # keep the best iterate: Gauss-Newton on thin shapes can walk off (a step that
        # slides a thin stroke onto its neighbour) and must not end worse than it began
        fit = float(np.mean(np.abs(r_c)))
        if fit < best:
            best, best_p = fit, p
        # gradient of the moving field at A x + t from the warped field's: A^-T grad
        wy, wx = (np.asarray(g, dtype=np.float64) for g in np.gradient(w_f, h))
        A = p[:4].reshape(2, 2)
        if abs(np.linalg.det(A)) < 1e-3:
            break
        gx, gy = np.linalg.solve(A.T, np.stack([wx[band], wy[band]]))
        s = 4.685 * max(1.4826 * float(np.median(np.abs(r_c))), 1e-3)
        w = np.clip(1 - (r_c / s) ** 2, 0, None) ** 2
        x, y = X[band], Y[band]
        J = np.stack([gx * x, gx * y, gy * x, gy * y, gx, gy, np.ones_like(x)], axis=1)
        JW = J * w[:, None]
        step = np.linalg.solve(JW.T @ J + 1e-6 * np.eye(7), JW.T @ r)
        p = p + step[:6]
        if np.abs(step[:6]).max() < 1e-3:
            break
    return p if _residual(moving, target, p) <= best else best_p


def local_difference(a: FloatArray, b: FloatArray) -> tuple[FloatArray, float]:
    """The local mean of ``|b - a - c|`` near either outline (0 elsewhere) and the ink
    offset c (the median difference there)."""
    band = (np.abs(a) < BAND) | (np.abs(b) < BAND)
    if not band.any():
        return np.full(a.shape, float(CLIP)), 0.0
    r = b - a
    c = float(np.median(r[band]))
    e = np.abs(r - c) * band
    num = ndimage.gaussian_filter(e, WINDOW)
    den = ndimage.gaussian_filter(band.astype(np.float64), WINDOW)
    return np.where(band & (den > 0.2), num / np.maximum(den, 1e-9), 0.0), c


def field_distance(a: FloatArray, b: FloatArray) -> float:
    """Largest local mean of the difference near either outline with the ink offset taken
    out, plus the ink offset / INK_WEIGHT (units: RMS radius)."""
    local, c = local_difference(a, b)
    return float(local.max() + abs(c) / INK_WEIGHT)


def _residual(moving: FloatArray, target: FloatArray, p: FloatArray) -> float:
    w = _warp(moving, p)
    band = (np.abs(w) < BAND) | (np.abs(target) < BAND)
    r = (target - w)[band]
    return float(np.mean(np.abs(r - np.median(r)))) if r.size else float(CLIP)


def _rotation(deg: float) -> FloatArray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([c, -s, s, c, 0.0, 0.0])


def common_frame(fields: Sequence[FloatArray], *, rounds: int = 2,
                 max_rotation: float | None = None,
                 progress: Callable[[int, int], None] | None = None) -> list[FloatArray]:
    """Every field aligned to the collection's median field (itself re-estimated once);
    with `max_rotation`, the first round also starts from rotations in 10 degree steps
    up to it and keeps the best."""
    out = list(fields)
    starts = [_IDENTITY]
    if max_rotation is not None:
        steps = np.arange(10.0, max_rotation + 1e-9, 10.0)
        starts += [_rotation(s * d) for d in steps for s in (1, -1)]
    params = [_IDENTITY] * len(fields)
    total = rounds * len(fields)
    if progress is not None:
        progress(0, total)
    for rnd in range(rounds):
        template = np.median(np.stack(out), axis=0)
        for k, f in enumerate(fields):
            if rnd == 0 and len(starts) > 1:
                tries = [align_fields(f, template, start=s0, iterations=3) for s0 in starts]
                best = min(tries, key=lambda p: _residual(f, template, p))
                params[k] = align_fields(f, template, start=best)
            else:
                params[k] = align_fields(f, template, start=params[k])
            if progress is not None:
                progress(rnd * len(fields) + k + 1, total)
        out = [_warp(f, p) for f, p in zip(fields, params, strict=True)]
    return out


def pair_distances(fields: Sequence[FloatArray], pairs: Sequence[tuple[int, int]],
                   progress: Callable[[int, int], None] | None = None) -> list[float]:
    """Distances of the given pairs (i, j) after aligning field i onto field j."""
    out = []
    for k, (i, j) in enumerate(pairs):
        fi, fj = fields[i], fields[j]
        out.append(field_distance(_warp(fi, align_fields(fi, fj)), fj))
        if progress is not None and (k % 20 == 19 or k == len(pairs) - 1):
            progress(k + 1, len(pairs))
    return out


def screen(fields: Sequence[FloatArray]) -> FloatArray:
    """A cheap all-pairs stand-in: RMS field difference with the mean offset removed."""
    V = np.stack([f.ravel() for f in fields])
    m = V.shape[1]
    sq = (V**2).sum(axis=1)
    s = V.sum(axis=1)
    G = V @ V.T
    ms = (sq[:, None] + sq[None, :] - 2 * G) / m - ((s[:, None] - s[None, :]) / m) ** 2
    return np.asarray(np.sqrt(np.clip(ms, 0, None)), dtype=np.float64)

"""Simulated impressions of printing moulds, for developing and checking glyph grouping.

A *mould* is the physical type or block that printed a character, given here as a binary
image (True = ink). Every print of one mould differs from the others by printing noise
only, which :func:`simulate_impressions` reproduces on a grey scan:

* ink spread and erosion: the mould's signed distance map thresholded at an offset of a
  pixel or so, globally and with a smooth variation across the glyph (uneven inking), which
  is a morphological dilation or erosion by a disc;
* blur (ink bleed and the scanner's optics) before the scanner's grey levels, and grey
  noise after them; the service's ingestion then thresholds the scan again;
* speckle: small ink specks on the paper and small ink-starved holes in the strokes;
* a small smooth paper warp, a small rotation and scale;
* different scan resolutions (the output image size varies).

Moulds that differ in one stroke only (a recut stroke end) are made by
:func:`recut_stroke_end`; designs that render identically are found by
:func:`identical_moulds`, so that a benchmark counts them as one mould.

Pure numpy/scipy: images are returned as arrays. Turning them into points is left to the
caller (the service's image ingestion, for example), so that the points of a simulation go
through exactly the path a user's scans go through.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from ._points import as_points

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "PrintVariation",
    "Recut",
    "draw_strokes",
    "identical_moulds",
    "impression_set",
    "mould_from_points",
    "recut_stroke_end",
    "simulate_impressions",
    "stroke_width",
]


@dataclass(frozen=True)
class PrintVariation:
    """How much impressions of one mould vary. Lengths are in mould pixels unless stated.

    Attributes
    ----------
    ink : float
        Largest global ink spread (+) or erosion (-): the boundary moves by a uniform draw
        in ``[-ink, ink]``.
    ink_local : float
        Largest extra spread or erosion varying smoothly across the glyph (uneven inking).
    blur : (float, float)
        Range of the Gaussian blur's sigma (ink bleed and scanner optics), in output pixels.
    speckle : float
        Expected number of ink specks and of starved holes per 10 000 mould pixels.
    speckle_radius : float
        Largest radius of a speck or hole.
    warp : float
        Largest displacement of the smooth paper warp, as a fraction of the mould's size
        (its longer side).
    rotation : float
        Largest rotation in degrees (uniform in ``[-rotation, rotation]``).
    scale : float
        Largest relative change of size (uniform in ``[-scale, scale]``).
    resolution : (float, float)
        Range of output pixels per mould pixel (scan resolution), drawn log-uniformly.
    noise : float
        Standard deviation of the scanner's grey-level noise (0-255 scale).
    """

    ink: float = 1.0
    ink_local: float = 0.6
    blur: tuple[float, float] = (0.5, 1.2)
    speckle: float = 1.5
    speckle_radius: float = 1.5
    warp: float = 0.006
    rotation: float = 2.0
    scale: float = 0.04
    resolution: tuple[float, float] = (0.8, 1.5)
    noise: float = 6.0

    def __post_init__(self) -> None:
        for name in ("ink", "ink_local", "speckle", "speckle_radius", "warp", "rotation",
                     "scale", "noise"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0; got {v!r}")
        if self.scale >= 0.5:
            raise ValueError(f"scale must be below 0.5; got {self.scale}")
        for name in ("blur", "resolution"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi):
                raise ValueError(f"{name} must be a range (lo, hi) with 0 <= lo <= hi; "
                                 f"got {(lo, hi)}")
        if self.resolution[0] <= 0:
            raise ValueError(f"resolution must be positive; got {self.resolution}")

    def to_dict(self) -> dict[str, object]:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def _as_mould(mould: ArrayLike, name: str = "mould") -> BoolArray:
    m = np.asarray(mould)
    if m.ndim != 2:
        raise ValueError(f"{name} must be a 2D binary image; got shape {m.shape}")
    if m.dtype != np.bool_:
        if not np.issubdtype(m.dtype, np.number):
            raise ValueError(f"{name} must be a numeric or boolean image; got {m.dtype}")
        m = m > 0
    if min(m.shape) < 8:
        raise ValueError(f"{name} must be at least 8 x 8 pixels; got {m.shape}")
    if not m.any():
        raise ValueError(f"{name} has no ink: every pixel is False")
    if m.all():
        raise ValueError(f"{name} is ink everywhere: there is no shape")
    return m


def _signed_distance(mould: BoolArray, pad: int) -> FloatArray:
    """Distance to the boundary, positive in the ink, negative outside (pixels)."""
    m = np.pad(mould, pad)
    inside = ndimage.distance_transform_edt(m)
    outside = ndimage.distance_transform_edt(~m)
    return np.asarray(inside - outside - 0.5 * (m.astype(np.float64) * 2 - 1), dtype=np.float64)


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> FloatArray:
    """A smooth random field with values in about [-1, 1]: bicubic upsampling of a
    ``cells x cells`` grid of uniform draws."""
    grid = rng.uniform(-1.0, 1.0, size=(cells, cells))
    zoom = (shape[0] / cells, shape[1] / cells)
    f = ndimage.zoom(grid, zoom, order=3, mode="nearest", grid_mode=True)
    out = np.zeros(shape)
    out[: f.shape[0], : f.shape[1]] = f[: shape[0], : shape[1]]
    return np.clip(out, -1.5, 1.5)


def stroke_width(mould: ArrayLike) -> float:
    """Typical stroke width of a binary glyph in pixels: twice the median of the distance
    map on its ridge (the pixels whose distance to the background is a local maximum)."""
    m = _as_mould(mould)
    d = ndimage.distance_transform_edt(np.pad(m, 1))
    ridge = (d > 0) & (d >= ndimage.maximum_filter(d, size=3))
    return float(2.0 * np.median(d[ridge]))


def simulate_impressions(
    mould: ArrayLike,
    n: int,
    *,
    variation: PrintVariation | None = None,
    seed: int | np.random.Generator | None = None,
) -> list[NDArray[np.uint8]]:
    """Grey scans of ``n`` prints of one mould.

    Parameters
    ----------
    mould : array_like of bool, shape (h, w)
        The mould's ink (True / nonzero), as printed: a character reads as it should.
    n : int
        Number of impressions, at least 1.
    variation : PrintVariation, optional
        How much the prints vary; default :class:`PrintVariation()`.
    seed : int or numpy Generator, optional
        Random state; the same seed gives the same scans.

    Returns
    -------
    list of ndarray of uint8
        Dark ink on light paper, each of its own size (the scan resolution varies).

    Raises
    ------
    ValueError
        If the mould is not a usable binary image or ``n < 1``.
    """
    m = _as_mould(mould)
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ValueError(f"n must be an integer >= 1; got {n!r}")
    v = PrintVariation() if variation is None else variation
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    size = float(max(m.shape))
    pad = int(np.ceil(size * (v.warp + v.scale + np.radians(v.rotation)) + 4 * v.ink + 8))
    sdf = _signed_distance(m, pad)
    return [_impression(sdf, pad, size, v, rng) for _ in range(int(n))]


def _impression(sdf: FloatArray, pad: int, size: float, v: PrintVariation,
                rng: np.random.Generator) -> NDArray[np.uint8]:
    hp, wp = sdf.shape
    res = float(np.exp(rng.uniform(np.log(v.resolution[0]), np.log(v.resolution[1]))))
    out_h, out_w = max(8, round(hp * res)), max(8, round(wp * res))
    # Output pixel centre -> mould pixel (row, col): inverse similarity about the centre,
    # then the paper warp (in mould pixels).
    rr, cc = np.mgrid[0:out_h, 0:out_w].astype(np.float64)
    rr = (rr + 0.5) / res - 0.5
    cc = (cc + 0.5) / res - 0.5
    cy, cx = (hp - 1) / 2.0, (wp - 1) / 2.0
    theta = np.radians(rng.uniform(-v.rotation, v.rotation))
    s = 1.0 + rng.uniform(-v.scale, v.scale)
    y, x = rr - cy, cc - cx
    cos, sin = np.cos(theta), np.sin(theta)
    src_r = (cos * y - sin * x) / s + cy
    src_c = (sin * y + cos * x) / s + cx
    if v.warp > 0:
        amp = v.warp * size
        src_r = src_r + amp * _smooth_field(rng, (out_h, out_w), 4)
        src_c = src_c + amp * _smooth_field(rng, (out_h, out_w), 4)
    level = ndimage.map_coordinates(sdf, [src_r, src_c], order=1, mode="nearest")
    # Ink spread (+) and erosion (-), in mould pixels: global and smoothly varying.
    level = level + rng.uniform(-v.ink, v.ink)
    if v.ink_local > 0:
        level = level + v.ink_local * _smooth_field(rng, (out_h, out_w), 5)
    # Coverage with the boundary anti-aliased over one output pixel.
    cover = np.clip(0.5 + level * res, 0.0, 1.0)
    cover = _speckle(cover, size, res, v, rng)
    lo, hi = v.blur
    sigma = rng.uniform(lo, hi)
    if sigma > 0:
        cover = ndimage.gaussian_filter(cover, sigma)
    paper = rng.uniform(215.0, 250.0)
    ink = rng.uniform(10.0, 60.0)
    grey = paper - (paper - ink) * cover + rng.normal(0.0, v.noise, cover.shape)
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8)


def _speckle(cover: FloatArray, size: float, res: float, v: PrintVariation,
             rng: np.random.Generator) -> FloatArray:
    """Ink specks on the paper and starved holes in the ink, as small discs."""
    if v.speckle <= 0 or v.speckle_radius <= 0:
        return cover
    h, w = cover.shape
    area = h * w / res**2  # in mould pixels
    k = rng.poisson(v.speckle * area / 1e4)
    if k == 0:
        return cover
    rows = rng.uniform(0, h, k)
    cols = rng.uniform(0, w, k)
    radii = rng.uniform(0.5, v.speckle_radius, k) * res
    out = cover.copy()
    for r0, c0, rad in zip(rows, cols, radii, strict=True):
        r_lo, r_hi = max(0, int(r0 - rad - 1)), min(h, int(r0 + rad + 2))
        c_lo, c_hi = max(0, int(c0 - rad - 1)), min(w, int(c0 + rad + 2))
        yy, xx = np.mgrid[r_lo:r_hi, c_lo:c_hi]
        disc = np.clip(rad + 0.5 - np.hypot(yy - r0, xx - c0), 0.0, 1.0)
        patch = out[r_lo:r_hi, c_lo:c_hi]
        # a speck where the paper is blank, a hole where there is ink
        inked = cover[int(min(r0, h - 1)), int(min(c0, w - 1))] >= 0.5
        out[r_lo:r_hi, c_lo:c_hi] = patch * (1 - disc) if inked else np.maximum(patch, disc)
    return out


def mould_from_points(
    points: ArrayLike,
    *,
    kind: str = "edge",
    size: int = 256,
    stroke: float | None = None,
) -> BoolArray:
    """A binary mould rasterised from a glyph's points (pixel units, y down).

    Parameters
    ----------
    points : array_like, shape (n, 2)
        ``"edge"``: points on the outline of the ink (Canny edges, contours); the closed
        outline is filled. Enclosed counters (the inside of 口) are filled too: points alone
        do not tell ink from an enclosed hole. ``"skeleton"``: points on the strokes'
        centre lines, thickened to `stroke` pixels.
    kind : {"edge", "skeleton"}
    size : int
        Longer side of the mould in pixels; the points are scaled to fit with a margin.
    stroke : float, optional
        Stroke width for ``"skeleton"``, in mould pixels; default ``size / 16``.

    Returns
    -------
    ndarray of bool, shape about (size, size)
    """
    p = as_points(points)
    if kind not in ("edge", "skeleton"):
        raise ValueError(f"kind must be 'edge' or 'skeleton'; got {kind!r}")
    if not isinstance(size, int | np.integer) or size < 16:
        raise ValueError(f"size must be an integer >= 16; got {size!r}")
    lo = p.min(axis=0)
    ext = float((p.max(axis=0) - lo).max())
    if ext <= 0:
        raise ValueError("points has zero size: all points coincide")
    margin = max(2, size // 16)
    q = (p - lo) * ((size - 2 * margin - 1) / ext) + margin
    img = np.zeros((size, size), dtype=bool)
    img[np.rint(q[:, 1]).astype(int), np.rint(q[:, 0]).astype(int)] = True
    if kind == "skeleton":
        w = size / 16.0 if stroke is None else float(stroke)
        if not w > 0:
            raise ValueError(f"stroke must be positive; got {stroke}")
        return np.asarray(ndimage.distance_transform_edt(~img) <= w / 2.0)
    # Join the sampled outline (gaps up to a few pixels), fill it, undo the joining.
    gap = max(1, round(size / 128))
    joined = ndimage.binary_dilation(img, iterations=gap)
    return np.asarray(ndimage.binary_erosion(ndimage.binary_fill_holes(joined),
                                             iterations=gap))


@dataclass(frozen=True)
class Recut:
    """A mould whose one stroke end was recut, made by :func:`recut_stroke_end`.

    Attributes
    ----------
    mould : ndarray of bool
        The recut mould, same shape as the original.
    tip : (float, float)
        (x, y) of the original stroke end, in mould pixels.
    direction : (float, float)
        Unit vector pointing out of the stroke at the tip, (x, y).
    change : {"shorten", "extend"}
    length : float
        How far the end moved, in mould pixels.
    pixels_changed : int
        Number of mould pixels that differ from the original.
    """

    mould: BoolArray
    tip: tuple[float, float]
    direction: tuple[float, float]
    change: str
    length: float
    pixels_changed: int


def _stroke_ends(m: BoolArray, radius: float) -> NDArray[np.intp]:
    """(row, col) of boundary pixels at stroke ends, most end-like first.

    A pixel at the end of a stroke sees the least ink within `radius` of all boundary
    pixels around it: only the stroke behind it, where a pixel on a stroke's side also
    sees the stroke continuing on both sides."""
    r = int(np.ceil(radius))
    yy, xx = np.mgrid[-r: r + 1, -r: r + 1]
    disc = (np.hypot(yy, xx) <= radius).astype(np.float64)
    share = ndimage.convolve(m.astype(np.float64), disc / disc.sum(), mode="constant")
    boundary = m & ~ndimage.binary_erosion(m)
    score = np.where(boundary, share, np.inf)
    local_min = boundary & (score <= ndimage.minimum_filter(score, footprint=disc > 0))
    cand = np.argwhere(local_min)
    vals = score[local_min]
    # keep clear ends: less ink around than a third of the disc (a straight side sees
    # about half, minus the stroke's thinness)
    keep = vals < np.median(share[boundary])
    order = np.argsort(vals[keep], kind="stable")
    return cand[keep][order]


def recut_stroke_end(
    mould: ArrayLike,
    *,
    change: str | None = None,
    length: float = 1.0,
    seed: int | np.random.Generator | None = None,
) -> Recut:
    """A second mould that differs from `mould` at one stroke end only.

    A stroke end is found where a boundary pixel sees the least ink around it (within 1.5
    stroke widths). The end is cut back (``"shorten"``: the ink within `length` stroke
    widths of the tip, along the stroke, is erased) or carved longer (``"extend"``: the
    stroke is continued straight by `length` stroke widths at its local width).

    Parameters
    ----------
    mould : array_like of bool, shape (h, w)
    change : {"shorten", "extend"}, optional
        Default: drawn at random.
    length : float
        How far the end moves, in stroke widths (see :func:`stroke_width`); > 0.
    seed : int or numpy Generator, optional
        Picks the stroke end (among the clearest ends) and, if not given, the change.

    Returns
    -------
    Recut

    Raises
    ------
    ValueError
        On a bad mould or option, or when the glyph has no stroke end that can be recut
        without erasing most of a stroke.
    """
    m = _as_mould(mould)
    if change not in (None, "shorten", "extend"):
        raise ValueError(f"change must be 'shorten' or 'extend'; got {change!r}")
    if not (isinstance(length, int | float) and np.isfinite(length) and length > 0):
        raise ValueError(f"length must be a positive number of stroke widths; got {length!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    kind = change if change is not None else str(rng.choice(["shorten", "extend"]))
    w = stroke_width(m)
    radius = max(2.0, 1.5 * w)
    ends = _stroke_ends(m, radius)
    labels, _ = ndimage.label(m)
    sizes = np.bincount(labels.ravel())
    rr, cc = np.mgrid[0: m.shape[0], 0: m.shape[1]]
    dist_in = ndimage.distance_transform_edt(m)
    options: list[tuple[BoolArray, tuple[int, int], FloatArray]] = []
    for r0, c0 in ends[: max(1, min(len(ends), 8))]:
        near = (np.hypot(rr - r0, cc - c0) <= radius) & m
        inward = np.array([cc[near].mean() - c0, rr[near].mean() - r0])
        norm = float(np.hypot(*inward))
        if norm < 1e-9:
            continue
        d = inward / norm  # (x, y), pointing into the stroke
        along = (cc - c0) * d[0] + (rr - r0) * d[1]
        across = np.abs(-(cc - c0) * d[1] + (rr - r0) * d[0])
        L = length * w
        if kind == "shorten":
            box = m & (along <= L) & (across <= radius)
            lab, _ = ndimage.label(box)
            piece = box & (lab == lab[r0, c0])
            if piece.sum() > 0.5 * sizes[labels[r0, c0]]:
                continue  # would erase most of the stroke
            new = m & ~piece
        else:
            inside = (round(r0 + d[1] * w), round(c0 + d[0] * w))
            half = w / 2.0
            if 0 <= inside[0] < m.shape[0] and 0 <= inside[1] < m.shape[1]:
                half = max(1.0, float(dist_in[inside]))
            grow = (along >= -L) & (along <= 0.5 * w) & (across <= half)
            # the new end must stay clear of other strokes: ink bridging a gap would print
            # differently with every inking, which is not a recut
            others = m & (np.hypot(rr - r0, cc - c0) > radius + L)
            if (ndimage.distance_transform_edt(~others)[grow & ~m] <= w).any():
                continue
            new = m | grow
        options.append((np.asarray(new), (int(r0), int(c0)), d))
    if not options:
        raise ValueError("the mould has no stroke end that can be recut without erasing "
                         "most of a stroke")
    new, (r0, c0), d = options[int(rng.integers(len(options)))]
    return Recut(mould=new, tip=(float(c0), float(r0)), direction=(-float(d[0]), -float(d[1])),
                 change=kind, length=float(length * w),
                 pixels_changed=int((new ^ m).sum()))


def identical_moulds(
    moulds: list[ArrayLike], *, tol: float = 0.02, shift: int = 2
) -> list[list[int]]:
    """Group designs that render identically (up to a shift), so they count as one mould.

    Two binary glyphs are identical when, cropped to their ink's bounding boxes, the boxes
    differ by at most `shift` pixels per side and, at the best relative shift of at most
    `shift` pixels, at most `tol` of the smaller ink area differs.

    Measured on the 73 distinct 永 designs of ``glyphs_yong`` (256 px): the closest two
    (MMCedar and Motoya Maruberi) differ by 10 % of their ink, weight variants of one
    family (Noto Sans CJK Medium / Bold) by 25 %; a re-render of one design by 0 %.

    Returns
    -------
    list of list of int
        Groups of indices into `moulds` (each group sorted, groups by first index); a
        design identical to none is a group of one.
    """
    if not 0 <= tol < 1:
        raise ValueError(f"tol must be in [0, 1); got {tol}")
    if isinstance(shift, bool) or not isinstance(shift, int) or shift < 0:
        raise ValueError(f"shift must be an integer >= 0; got {shift!r}")
    crops: list[BoolArray] = []
    for k, mo in enumerate(moulds):
        m = _as_mould(mo, name=f"moulds[{k}]")
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        crops.append(m[rows[0]: rows[-1] + 1, cols[0]: cols[-1] + 1])
    parent = list(range(len(crops)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(len(crops)):
        for j in range(i + 1, len(crops)):
            if _differing_share(crops[i], crops[j], shift) <= tol:
                parent[find(j)] = find(i)
    groups: dict[int, list[int]] = {}
    for i in range(len(crops)):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values())


def _differing_share(a: BoolArray, b: BoolArray, shift: int) -> float:
    """Smallest share of the smaller ink area that differs over shifts of up to `shift`
    pixels (inf when the bounding boxes differ by more than `shift`)."""
    if abs(a.shape[0] - b.shape[0]) > shift or abs(a.shape[1] - b.shape[1]) > shift:
        return float("inf")
    h = max(a.shape[0], b.shape[0]) + 2 * shift
    w = max(a.shape[1], b.shape[1]) + 2 * shift
    pa = np.zeros((h, w), bool)
    pa[shift: shift + a.shape[0], shift: shift + a.shape[1]] = a
    best = np.inf
    for dy in range(2 * shift + 1):
        for dx in range(2 * shift + 1):
            pb = np.zeros((h, w), bool)
            pb[dy: dy + b.shape[0], dx: dx + b.shape[1]] = b
            best = min(best, float((pa ^ pb).sum()))
    return best / float(min(a.sum(), b.sum()))


def draw_strokes(
    strokes: ArrayLike, *, size: int = 128, width: float | ArrayLike = 0.08
) -> BoolArray:
    """A binary glyph drawn from straight strokes with round ends (a mould for tests).

    Parameters
    ----------
    strokes : array_like, shape (k, 4)
        ``(x0, y0, x1, y1)`` of each stroke in [0, 1] (y down), scaled to the image.
    size : int
        Side of the square image in pixels.
    width : float or array_like of shape (k,)
        Stroke width as a fraction of `size`.
    """
    s = np.asarray(strokes, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 4 or len(s) == 0 or not np.isfinite(s).all():
        raise ValueError(f"strokes must be a finite array of shape (k, 4), k >= 1; "
                         f"got shape {s.shape}")
    if not isinstance(size, int | np.integer) or size < 16:
        raise ValueError(f"size must be an integer >= 16; got {size!r}")
    w = np.broadcast_to(np.asarray(width, dtype=np.float64), (len(s),))
    if not (np.isfinite(w).all() and (w > 0).all()):
        raise ValueError(f"width must be positive; got {width!r}")
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5) / size
    img = np.zeros((size, size), dtype=bool)
    for (x0, y0, x1, y1), wk in zip(s, w, strict=True):
        dx, dy = x1 - x0, y1 - y0
        L2 = dx * dx + dy * dy
        u = np.clip(((xx - x0) * dx + (yy - y0) * dy) / L2, 0, 1) if L2 > 0 else 0.0
        img |= np.hypot(xx - (x0 + u * dx), yy - (y0 + u * dy)) <= wk / 2
    if not img.any():
        raise ValueError("the strokes draw no pixel: widen them or enlarge the image")
    return img


def impression_set(
    moulds: Sequence[ArrayLike],
    n: int,
    *,
    to_points: Callable[[NDArray[np.uint8]], ArrayLike],
    variation: PrintVariation | None = None,
    seed: int | np.random.Generator | None = None,
) -> tuple[list[FloatArray], NDArray[np.intp]]:
    """``n`` impressions of every mould, as points, with the true mould of each.

    `to_points` turns a grey scan into points (for example the service's image ingestion
    of the scan encoded as PNG). Returns the point sets, mould by mould, and the mould
    index of each."""
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    shapes: list[FloatArray] = []
    truth: list[int] = []
    for k, m in enumerate(moulds):
        for img in simulate_impressions(m, n, variation=variation, seed=rng):
            shapes.append(as_points(to_points(img), name=f"points of mould {k}"))
            truth.append(k)
    return shapes, np.asarray(truth, dtype=np.intp)

"""Points from images of shapes: contour, edge or skeleton points of a picture.

A notebook user turns glyph scans or outline drawings into point sets without a server::

    from registration.images import points_from_image
    shapes = [points_from_image(p, mode="contour", target_points=300) for p in paths]

The service's uploads call the same function, so a shape made here and one uploaded as an
image are the same points.

This module needs Pillow and scikit-image (``pip install 'regtree[images]'``); they are
imported when a function is called, so ``import registration`` works without them.

Coordinates are pixel units with ``x`` = column and ``y`` = row (``y`` pointing down), pixel
centres at integers.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal, get_args

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from PIL import Image

__all__ = [
    "IMAGE_MODES",
    "ImageMode",
    "ImageTooLarge",
    "grey_levels",
    "points_from_image",
]

FloatArray = npt.NDArray[np.float64]
ImageMode = Literal["contour", "edges", "skeleton"]
IMAGE_MODES: tuple[str, ...] = get_args(ImageMode)

MIN_CONTRAST = 16  # grey levels between background and foreground below which nothing is there
MIN_CONTOUR_LENGTH = 6.0  # px; drops specks of a few pixels (JPEG noise)
MIN_CONTOUR_FRACTION = 0.01  # of the longest contour's length; drops relative specks


class ImageTooLarge(ValueError):
    """The image has more pixels than allowed (checked before its pixels are decoded).

    Attributes
    ----------
    size : tuple of int or None
        ``(width, height)`` as the file declares it; None when Pillow's own
        decompression-bomb guard refused the file before its size was known.
    limit : int or None
        The ``max_pixels`` that was passed.
    """

    def __init__(self, message: str, *, size: tuple[int, int] | None, limit: int | None):
        super().__init__(message)
        self.size = size
        self.limit = limit


def _pillow() -> Any:
    try:
        from PIL import Image
    except ImportError as e:  # pragma: no cover - Pillow is installed with the service
        raise ImportError(
            "registration.images needs Pillow and scikit-image: pip install 'regtree[images]'"
        ) from e
    return Image


def _check_size(w: int, h: int, max_pixels: int | None) -> None:
    if max_pixels is not None and w * h > max_pixels:
        raise ImageTooLarge(
            f"image too large: {w}x{h} = {w * h} pixels; the limit is {max_pixels} pixels "
            "(max_pixels)",
            size=(w, h),
            limit=max_pixels,
        )
    if w == 0 or h == 0:
        raise ValueError("could not decode image: it has no pixels")


def _open(
    source: bytes | str | os.PathLike[str],
    max_pixels: int | None,
    formats: Sequence[str] | None,
) -> Image.Image:
    """Open an encoded image, checking its declared size before decoding any pixel."""
    pil = _pillow()
    from PIL import ImageOps, UnidentifiedImageError

    if isinstance(source, bytes | bytearray | memoryview):
        if not len(source):
            raise ValueError("could not decode image: the data is empty")
        fp: Any = io.BytesIO(bytes(source))
    else:
        fp = os.fspath(source)
    try:
        im: Image.Image = pil.open(fp, formats=tuple(formats) if formats else None)
    except pil.DecompressionBombError as e:
        # Pillow's own guard (2 * Image.MAX_IMAGE_PIXELS) fires while reading the header.
        raise ImageTooLarge(
            "image too large: its declared size is beyond Pillow's decompression-bomb guard"
            + (f"; the limit is {max_pixels} pixels (max_pixels)" if max_pixels else ""),
            size=None,
            limit=max_pixels,
        ) from e
    except UnidentifiedImageError as e:
        wanted = " or ".join(formats) if formats else "a known image"
        raise ValueError(
            f"could not decode image: not a {wanted} file"
            + (" (other image formats are not supported)" if formats else "")
        ) from e
    except (MemoryError, FileNotFoundError, IsADirectoryError, PermissionError):
        raise
    except Exception as e:  # Pillow raises many exception types on corrupt data
        raise ValueError(f"could not decode image: {e}") from e
    width, height = im.size
    _check_size(width, height, max_pixels)
    try:
        im.load()
        im = ImageOps.exif_transpose(im)
    except MemoryError:
        raise
    except Exception as e:
        raise ValueError(f"could not decode image: {e}") from e
    return im


def _from_array(a: np.ndarray, max_pixels: int | None) -> Image.Image:
    pil = _pillow()
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise ValueError(
            f"image array must have shape (h, w), (h, w, 3) or (h, w, 4); got {a.shape}"
        )
    _check_size(a.shape[1], a.shape[0], max_pixels)
    if a.dtype == np.bool_:
        a = np.where(a, 255, 0).astype(np.uint8)
    elif a.dtype == np.uint16 and a.ndim == 2:
        a = np.rint(a / 257.0).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise ValueError(f"image array must be uint8, uint16 (greyscale) or bool; got {a.dtype}")
    return pil.fromarray(np.ascontiguousarray(a))


def _to_grey(im: Image.Image) -> npt.NDArray[np.uint8]:
    """Greyscale uint8 array; alpha composited over white, 16-bit scaled to 8-bit."""
    pil = _pillow()
    if im.mode.startswith("I;16"):
        a = np.asarray(im, dtype=np.float64) / 257.0
        return np.clip(np.rint(a), 0, 255).astype(np.uint8)
    if im.mode in ("I", "F"):
        a = np.asarray(im, dtype=np.float64)
        if a.size and np.nanmax(a) > 255:  # 16-bit data in a 32-bit mode
            a = a / 257.0
        return np.clip(np.rint(np.nan_to_num(a)), 0, 255).astype(np.uint8)
    has_alpha = im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    if has_alpha:
        rgba = im.convert("RGBA")
        white = pil.new("RGBA", rgba.size, (255, 255, 255, 255))
        grey = np.asarray(pil.alpha_composite(white, rgba).convert("L"))
        alpha = np.asarray(rgba.getchannel("A"))
        if int(grey.max()) - int(grey.min()) < MIN_CONTRAST <= int(alpha.max()) - int(alpha.min()):
            # A light shape on a transparent background vanishes over white: the shape is
            # then given by the alpha channel alone.
            return np.asarray(255 - alpha, dtype=np.uint8)
        return np.asarray(grey, dtype=np.uint8)
    if im.mode not in ("L", "RGB", "1", "P"):
        im = im.convert("RGB")
    return np.asarray(im.convert("L"), dtype=np.uint8)


def grey_levels(
    image: bytes | str | os.PathLike[str] | Image.Image | np.ndarray,
    *,
    max_pixels: int | None = None,
    formats: Sequence[str] | None = None,
) -> npt.NDArray[np.uint8]:
    """An image as a greyscale ``uint8`` array of shape ``(height, width)``.

    Parameters
    ----------
    image : bytes, path, PIL image or ndarray
        Encoded image bytes, a file path, a ``PIL.Image.Image``, or an array of shape
        ``(h, w)``, ``(h, w, 3)`` or ``(h, w, 4)`` (uint8; also uint16 or bool greyscale).
    max_pixels : int, optional
        Refuse images of more pixels, before their pixels are decoded (a guard against
        decompression bombs). Default: only Pillow's own guard.
    formats : sequence of str, optional
        Pillow format names tried when decoding bytes or a file, e.g. ``("PNG", "JPEG")``;
        default: every format Pillow knows.

    Returns
    -------
    ndarray of uint8, shape (height, width)
        Alpha is composited over white (a light shape on a transparent background is read
        from the alpha channel); 16-bit data is scaled to 8 bits; the EXIF orientation of
        a decoded file is applied.

    Raises
    ------
    ImageTooLarge
        If the image has more than ``max_pixels`` pixels.
    ValueError
        If the image cannot be decoded.
    """
    pil = _pillow()
    if isinstance(image, np.ndarray):
        im = _from_array(image, max_pixels)
    elif isinstance(image, pil.Image):
        width, height = image.size
        _check_size(width, height, max_pixels)
        im = image
    else:
        im = _open(image, max_pixels, formats)  # type: ignore[arg-type]
    return _to_grey(im)


def _no_foreground(why: str) -> ValueError:
    return ValueError(
        f"image has no foreground pixels: {why}; expected a dark shape on a light background "
        f"or a light shape on a dark background"
    )


def _median_level(hist: npt.NDArray[np.int64]) -> float:
    c = np.cumsum(hist)
    total = int(c[-1])
    lo_i = int(np.searchsorted(c, (total + 1) // 2))
    hi_i = int(np.searchsorted(c, total // 2 + 1))
    return (lo_i + hi_i) / 2.0


def _foreground(grey: npt.NDArray[np.uint8]) -> tuple[npt.NDArray[np.bool_], bool]:
    """Binary mask of the shape, and whether the shape is the dark class.

    Threshold: Otsu splits the grey levels into two classes; the cut is placed halfway
    between the two classes' median grey levels, which for anti-aliased renders is the 50 %
    coverage level (127.5 for black on white) and so the geometrically right boundary.

    Polarity: the background is the class holding the clear majority (>= 75 %) of the
    border pixels; if the border is mixed (a shape cut by the frame), the foreground is the
    minority class of the whole image (ties: dark is foreground).
    """
    from skimage.filters import threshold_otsu

    lo, hi = int(grey.min()), int(grey.max())
    if hi - lo < MIN_CONTRAST:
        raise _no_foreground(
            "it is a single uniform colour"
            if hi == lo
            else f"contrast too low ({hi - lo} grey levels)"
        )
    hist = np.bincount(grey.ravel(), minlength=256)
    t_otsu = float(threshold_otsu(grey))
    dark_hist = np.where(np.arange(256) <= t_otsu, hist, 0)
    m_dark, m_bright = _median_level(dark_hist), _median_level(hist - dark_hist)
    if m_bright - m_dark < MIN_CONTRAST:
        raise _no_foreground(f"contrast too low ({m_bright - m_dark:g} grey levels)")
    t = (m_dark + m_bright) / 2.0
    dark = grey < t
    bright = grey > t
    border = np.concatenate([dark[0, :], dark[-1, :], dark[:, 0], dark[:, -1]])
    frac_dark = float(border.mean())
    if frac_dark <= 0.25:
        fg_dark = True
    elif frac_dark >= 0.75:
        fg_dark = False
    else:
        fg_dark = int(dark.sum()) <= int(bright.sum())
    fg = dark if fg_dark else bright
    if not fg.any():
        raise _no_foreground("nothing differs from the background")
    return fg, fg_dark


def _pixels_xy(mask: npt.NDArray[np.bool_]) -> FloatArray:
    rows, cols = np.nonzero(mask)  # raster order: by row, then column
    return np.column_stack([cols, rows]).astype(np.float64)


def _closed_length(c: FloatArray) -> float:
    return float(np.hypot(*(np.roll(c, -1, axis=0) - c).T).sum())


def _contours(fg: npt.NDArray[np.bool_]) -> list[FloatArray]:
    from skimage.measure import find_contours

    padded = np.pad(fg, 1).astype(np.float64)  # shapes touching the frame close too
    out: list[FloatArray] = []
    for c in find_contours(padded, 0.5):
        xy = np.column_stack([c[:, 1], c[:, 0]]) - 1.0
        if len(xy) > 1 and np.array_equal(xy[0], xy[-1]):
            xy = xy[:-1]  # closed: do not repeat the first point
        out.append(np.ascontiguousarray(xy, dtype=np.float64))
    return out


def _resample_closed(c: FloatArray, k: int) -> FloatArray:
    """``k`` points evenly spaced by arc length along closed polyline ``c``, from c[0]."""
    closed = np.vstack([c, c[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    at = np.arange(k) * (s[-1] / k)
    return np.column_stack([np.interp(at, s, closed[:, 0]), np.interp(at, s, closed[:, 1])])


def _allocate(lengths: FloatArray, k: int) -> npt.NDArray[np.int64]:
    """Split ``k`` points over contours proportionally to length (largest remainder)."""
    share = lengths / lengths.sum() * k
    n = np.floor(share).astype(np.int64)
    rest = k - int(n.sum())
    if rest:
        order = np.argsort(-(share - n), kind="stable")
        n[order[:rest]] += 1
    return n


def _contour_points(fg: npt.NDArray[np.bool_], target: int | None) -> FloatArray:
    contours = _contours(fg)
    lengths = np.array([_closed_length(c) for c in contours], dtype=np.float64)
    keep = lengths >= max(MIN_CONTOUR_LENGTH, MIN_CONTOUR_FRACTION * float(lengths.max()))
    order = [i for i in np.argsort(-lengths, kind="stable") if keep[i]]
    contours = [contours[i] for i in order]
    if not contours:
        raise _no_foreground("only specks of a few pixels")
    if target is not None and sum(len(c) for c in contours) > target:
        counts = _allocate(lengths[order], target)
        contours = [
            _resample_closed(c, int(k)) for c, k in zip(contours, counts, strict=True) if k > 0
        ]
    return np.ascontiguousarray(np.concatenate(contours, axis=0), dtype=np.float64)


def _edge_points(grey: npt.NDArray[np.uint8], fg_dark: bool) -> FloatArray:
    from skimage.feature import canny

    # Canny's non-maximum suppression is not symmetric under inversion: run it with the
    # shape bright, so both polarities give the same edges. Its thresholds are absolute:
    # stretch the grey range to 0..255 so faint scans give the edges of crisp ones.
    # (uint8 rather than float keeps the peak memory of a 4096 x 4096 image lower.)
    lo, hi = int(grey.min()), int(grey.max())
    if (lo, hi) != (0, 255):
        lut = np.rint((np.arange(256) - lo).clip(0, hi - lo) * (255.0 / (hi - lo)))
        grey = lut.astype(np.uint8)[grey]
    pts = _pixels_xy(canny(255 - grey if fg_dark else grey, sigma=1.0))
    if len(pts) == 0:
        raise _no_foreground("no edges found")
    return pts


def _subsample_raster(pts: FloatArray, target: int | None) -> FloatArray:
    if target is not None and len(pts) > target:
        pts = pts[np.rint(np.linspace(0, len(pts) - 1, target)).astype(np.int64)]
    return np.ascontiguousarray(pts)


def points_from_image(
    image: bytes | str | os.PathLike[str] | Image.Image | np.ndarray,
    *,
    mode: ImageMode = "contour",
    target_points: int | None = None,
    max_pixels: int | None = None,
    formats: Sequence[str] | None = None,
) -> FloatArray:
    """Points of the shape in an image: its contour, its edges or its skeleton.

    The shape is told from the background by Otsu's threshold (placed halfway between the
    two classes' median grey levels) and by which class holds the image border, so a dark
    shape on a light background and a light shape on a dark background give the same points.

    Parameters
    ----------
    image : bytes, path, PIL image or ndarray
        Encoded image bytes (PNG, JPEG, ...), a file path, a ``PIL.Image.Image``, or a
        ``(h, w)``, ``(h, w, 3)`` or ``(h, w, 4)`` uint8 array (see :func:`grey_levels`).
    mode : {"contour", "edges", "skeleton"}
        * ``contour``: the boundaries (outer and holes) of the thresholded shape, from
          ``skimage.measure.find_contours`` at level 0.5 on the binary mask, so they lie on
          the pixel edges between shape and background. Every contour at least 6 px and 1 %
          of the longest contour long is kept (specks dropped); contours are concatenated
          longest first, each closed contour starting at its first vertex, not repeated.
        * ``edges``: Canny edges (``skimage.feature.canny``, sigma 1, default thresholds) of
          the grey image, as in Du et al. 2016, computed with the shape made bright and the
          grey range stretched to 0..255 (both polarities and faint scans give the edges of
          crisp black on white); edge pixels in raster order (by row, then column).
        * ``skeleton``: ``skimage.morphology.skeletonize`` of the thresholded shape;
          skeleton pixels in raster order.
    target_points : int, optional
        Upper bound on the number of points. Contours are resampled at equal arc-length
        steps, the points split over the contours in proportion to their lengths (largest
        remainder; a contour whose share rounds to 0 is dropped). Edges and skeletons keep
        evenly spaced indices of the raster ordering, ``round(linspace(0, n - 1, k))``.
        Fewer points are never padded. Default: every point.
    max_pixels, formats
        Passed to :func:`grey_levels`.

    Returns
    -------
    ndarray of float64, shape (n, 2)
        ``(x, y)`` = (column, row) in pixels, C-contiguous. Deterministic.

    Raises
    ------
    ImageTooLarge
        If the image has more than ``max_pixels`` pixels.
    ValueError
        On an unknown mode, a bad ``target_points``, an image that cannot be decoded, or
        one without a shape (uniform, too little contrast, only specks).
    """
    if mode not in IMAGE_MODES:
        raise ValueError(f"unknown image mode {mode!r}; expected one of {', '.join(IMAGE_MODES)}")
    if target_points is not None and (
        isinstance(target_points, bool)
        or not isinstance(target_points, int | np.integer)
        or target_points < 1
    ):
        raise ValueError(f"target_points must be a positive integer; got {target_points!r}")
    target = None if target_points is None else int(target_points)
    grey = grey_levels(image, max_pixels=max_pixels, formats=formats)
    fg, fg_dark = _foreground(grey)
    if mode == "edges":
        return _subsample_raster(_edge_points(grey, fg_dark), target)
    if mode == "skeleton":
        from skimage.morphology import skeletonize

        return _subsample_raster(_pixels_xy(skeletonize(fg)), target)
    return _contour_points(fg, target)

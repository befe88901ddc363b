"""Decode uploaded shapes into ``(n, 2)`` point arrays.

Pure functions, no web framework: the API layer calls :func:`decode_points` (or one of the
format-specific functions) and turns an :class:`IngestError` into a 4xx problem+json
response whose ``detail`` is the error message. Every message is meant to be read by the
person who uploaded the file, so it says what was wrong, where, and which setting applies.

Accepted inputs
---------------
* JSON: ``[[x, y], ...]`` or ``{"points": [[x, y], ...]}``.
* Text (CSV/TXT/TSV): one point per line, ``x y``, ``x,y``, ``x;y`` or tab separated; blank
  lines and ``#`` comments are skipped, as is one optional header line such as ``x,y``.
  With ``;`` as separator a decimal comma is accepted (``1,5;2,25``).
* NPY: a numeric ``(n, 2)`` array written by ``numpy.save``. Loaded with
  ``allow_pickle=False``; object (pickled) arrays are refused.
* Images: PNG (greyscale, RGB, palette, with or without alpha: alpha is composited over
  white) and JPEG (EXIF orientation applied). A dark shape on a light background or a light
  shape on a dark background; see :func:`points_from_image` for the modes.

Output
------
Always a C-contiguous float64 array of shape ``(n, 2)`` with finite values, ``min_points <= n
<= max_points`` and ``|coordinate| <= max_coordinate``. Columns are ``(x, y)``; for images,
pixel units with ``x`` = column, ``y`` = row (y pointing down), pixel centres at integers.

Indices in messages: "point i" counts from 0 (the position in the uploaded array); "line i"
counts from 1 (as a text editor shows it).
"""

from __future__ import annotations

import io
import json
import math
import re
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import numpy.typing as npt
from PIL import Image, ImageOps, UnidentifiedImageError

__all__ = [
    "ImageMode",
    "IngestError",
    "Limits",
    "decode_points",
    "detect_format",
    "points_from_image",
    "points_from_json",
    "points_from_npy",
    "points_from_text",
]

FloatArray = npt.NDArray[np.float64]
Format = Literal["json", "text", "npy", "image"]
ImageMode = Literal["contour", "edges", "skeleton"]
IMAGE_MODES: tuple[str, ...] = get_args(ImageMode)


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


# --------------------------------------------------------------------------- shared checks


def _fmt_num(v: float) -> str:
    return f"{v:g}"


def _check_count(n: int, limits: Limits) -> None:
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


def _too_many(limits: Limits, what: str = "file") -> IngestError:
    return IngestError(
        f"{what} has more than {limits.max_points} points, the limit (setting max_points_per_shape)"
    )


def _finalise(arr: npt.NDArray[np.generic], limits: Limits) -> FloatArray:
    """Check shape, dtype, count and values; return a fresh C-contiguous float64 array."""
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise IngestError(f"expected points of shape (n, 2); got shape {tuple(arr.shape)}")
    if arr.dtype.kind not in "iuf":
        raise IngestError(
            f"expected numeric coordinates (integers or floats); got dtype {arr.dtype}"
        )
    _check_count(arr.shape[0], limits)
    out = np.array(arr, dtype=np.float64, order="C", copy=True)
    finite = np.isfinite(out).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise IngestError(
            f"point {i} has a non-finite coordinate ({_fmt_num(out[i, 0])}, "
            f"{_fmt_num(out[i, 1])}); points are counted from 0"
        )
    inside = (np.abs(out) <= limits.max_coordinate).all(axis=1)
    if not inside.all():
        i = int(np.argmin(inside))
        raise IngestError(
            f"point {i} has a coordinate beyond ±{_fmt_num(limits.max_coordinate)} "
            f"({_fmt_num(out[i, 0])}, {_fmt_num(out[i, 1])}), the limit (setting "
            f"max_coordinate); points are counted from 0"
        )
    return out


# --------------------------------------------------------------------------- format detection

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_MAGIC = b"\xff\xd8\xff"
_NPY_MAGIC = b"\x93NUMPY"
# Other image formats: recognised so that the user gets "upload PNG or JPEG" rather than a
# text parse error, but not decoded.
_OTHER_IMAGE_MAGIC = (b"GIF87a", b"GIF89a", b"II*\x00", b"MM\x00*")

_EXTENSIONS: dict[str, Format] = {
    "json": "json",
    "geojson": "json",
    "csv": "text",
    "txt": "text",
    "tsv": "text",
    "tab": "text",
    "dat": "text",
    "xy": "text",
    "pts": "text",
    "npy": "npy",
    "png": "image",
    "jpg": "image",
    "jpeg": "image",
    "jpe": "image",
}

_CONTENT_TYPES: dict[str, Format] = {
    "application/json": "json",
    "text/json": "json",
    "text/csv": "text",
    "text/plain": "text",
    "text/tab-separated-values": "text",
    "application/csv": "text",
    "application/x-npy": "npy",
    "application/npy": "npy",
    "image/png": "image",
    "image/jpeg": "image",
    "image/jpg": "image",
    "image/pjpeg": "image",
}

_UTF_BOMS = (b"\xef\xbb\xbf", b"\xff\xfe", b"\xfe\xff")


def _looks_like_json(data: bytes) -> bool:
    head = data[:64]
    if head.startswith(b"\xef\xbb\xbf"):
        head = head[3:]
    head = head.lstrip(b" \t\r\n")
    return head[:1] in (b"[", b"{")


_CONTROL_BYTES = bytes(set(range(32)) - {9, 10, 12, 13})


def _looks_like_text(head: bytes) -> bool:
    """No control bytes other than tab, newlines and form feed (any 8-bit encoding)."""
    return len(head.translate(None, delete=_CONTROL_BYTES)) == len(head)


def detect_format(filename: str | None, content_type: str | None, data: bytes) -> Format:
    """Guess the upload's format.

    Magic bytes win (``\\x93NUMPY``, PNG/JPEG signatures, a leading ``[`` or ``{``), then the
    file name's extension, then the content type (parameters such as ``charset`` ignored,
    ``*/*+json`` counts as JSON, other ``text/*`` as text). Failing all of these, data with a
    UTF BOM or without control bytes (other than tab, newlines, form feed) in its first 4 KiB
    is treated as text. GIF, TIFF and WebP signatures are reported as "image" so that
    :func:`points_from_image` can say that only PNG and JPEG are decoded. Raises
    :class:`IngestError` for an empty file, a zip/npz archive, or an unrecognised format.
    """
    if not data:
        raise IngestError("empty file")
    if data.startswith(_NPY_MAGIC):
        return "npy"
    if data.startswith(_PNG_MAGIC) or data.startswith(_JPEG_MAGIC):
        return "image"
    if any(data.startswith(m) for m in _OTHER_IMAGE_MAGIC) or (
        data[:4] == b"RIFF" and data[8:12] == b"WEBP"
    ):
        return "image"
    if _looks_like_json(data):
        return "json"
    if data.startswith(b"PK\x03\x04"):
        raise IngestError(
            "zip archives (including .npz) are not supported; upload one shape as JSON, "
            "CSV/TXT, NPY, PNG or JPEG"
        )
    if filename:
        ext = filename.rsplit(".", 1)[-1].lower() if "." in filename else ""
        if ext in _EXTENSIONS:
            return _EXTENSIONS[ext]
    if content_type:
        ctype = content_type.split(";", 1)[0].strip().lower()
        if ctype in _CONTENT_TYPES:
            return _CONTENT_TYPES[ctype]
        if ctype.endswith("+json"):
            return "json"
        if ctype.startswith("text/"):
            return "text"
    if data.startswith(_UTF_BOMS) or _looks_like_text(data[:4096]):
        return "text"
    raise IngestError("could not recognise the file format; upload JSON, CSV/TXT, NPY, PNG or JPEG")


def decode_points(
    data: bytes,
    *,
    filename: str | None = None,
    content_type: str | None = None,
    mode: ImageMode = "contour",
    target_points: int | None = None,
    limits: Limits = Limits(),
) -> FloatArray:
    """Decode an uploaded file (any supported format) into an ``(n, 2)`` float64 array.

    ``mode`` and ``target_points`` apply to images only (see :func:`points_from_image`);
    ``mode`` is validated for every upload so that a bad request parameter is reported even
    when the file is not an image.
    """
    if mode not in IMAGE_MODES:
        raise IngestError(f"unknown image mode {mode!r}; expected one of {', '.join(IMAGE_MODES)}")
    if not data:
        raise IngestError("empty file")
    fmt = detect_format(filename, content_type, data)
    if fmt == "npy":
        return points_from_npy(data, limits=limits)
    if fmt == "image":
        return points_from_image(data, mode=mode, target_points=target_points, limits=limits)
    if fmt == "json":
        try:
            obj = json.loads(data)
        except json.JSONDecodeError as e:
            raise IngestError(f"invalid JSON: {e.msg} at line {e.lineno} column {e.colno}") from e
        except UnicodeDecodeError as e:
            raise IngestError("invalid JSON: the file is not UTF-8 text") from e
        except RecursionError as e:
            raise IngestError("invalid JSON: nested too deeply") from e
        return points_from_json(obj, limits=limits)
    return points_from_text(_decode_text(data), limits=limits)


# --------------------------------------------------------------------------- JSON


def _json_type(v: object) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, str):
        return f"the string {json.dumps(v[:40])}"
    if isinstance(v, dict):
        return "an object"
    if isinstance(v, list | tuple):
        return "an array"
    if isinstance(v, int | float):
        return "a number"
    return type(v).__name__


def points_from_json(
    obj: object,
    *,
    limits: Limits = Limits(),
) -> FloatArray:
    """Points from parsed JSON: ``[[x, y], ...]`` or ``{"points": [[x, y], ...]}``.

    Coordinates must be JSON numbers (strings such as ``"3"`` and booleans are refused).
    """
    if isinstance(obj, dict):
        if "points" not in obj:
            raise IngestError(
                'expected a JSON array of [x, y] pairs or an object with a "points" array; '
                'the object has no "points" key'
            )
        obj = obj["points"]
        if not isinstance(obj, list):
            raise IngestError(f'"points" must be an array of [x, y] pairs; got {_json_type(obj)}')
    if not isinstance(obj, list | tuple):
        raise IngestError(f"expected a JSON array of [x, y] pairs; got {_json_type(obj)}")
    n = len(obj)
    if n > limits.max_points:
        _check_count(n, limits)
    lengths = set()
    for i, p in enumerate(obj):
        if not isinstance(p, list | tuple):
            raise IngestError(f"point {i}: expected a pair [x, y]; got {_json_type(p)}")
        lengths.add(len(p))
    if lengths and lengths != {2}:
        if len(lengths) == 1:
            (k,) = lengths
            raise IngestError(f"expected points of shape (n, 2); got shape ({n}, {k})")
        i = next(i for i, p in enumerate(obj) if len(p) != 2)
        raise IngestError(f"point {i} has {len(obj[i])} coordinates; expected 2 (x, y)")
    out = np.empty((n, 2), dtype=np.float64)
    for i, p in enumerate(obj):
        for j, v in enumerate(p):
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise IngestError(f"point {i}: coordinates must be numbers; got {_json_type(v)}")
            try:
                out[i, j] = float(v)
            except OverflowError as e:  # an integer with hundreds of digits
                raise IngestError(
                    f"point {i} has a coordinate beyond ±{_fmt_num(limits.max_coordinate)}, "
                    f"the limit (setting max_coordinate); points are counted from 0"
                ) from e
    return _finalise(out, limits)


# --------------------------------------------------------------------------- text


def _decode_text(data: bytes) -> str:
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        try:
            return data.decode("utf-16")
        except UnicodeDecodeError as e:
            raise IngestError("could not decode the file as UTF-16 text") from e
    if b"\x00" in data:
        raise IngestError("the file is not text (it contains NUL bytes)")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        # Numbers are ASCII; a legacy-encoded comment must not make the file unreadable.
        return data.decode("latin-1")


_SPACE_SPLIT = re.compile(r"\s+")
_NUMBER = re.compile(
    r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:nan|inf|infinity)", re.IGNORECASE
)


def _split_fields(line: str) -> list[str]:
    if ";" in line:
        fields = [f.strip() for f in line.split(";")]
        # ';' is the separator of locales whose decimal mark is ',' ("1,5;2,25").
        fields = [f.replace(",", ".") if f.count(",") == 1 and "." not in f else f for f in fields]
    elif "," in line:
        fields = [f.strip() for f in line.split(",")]
    else:
        fields = _SPACE_SPLIT.split(line.strip())
    while len(fields) > 2 and fields[-1] == "":  # "1,2," from spreadsheet exports
        fields.pop()
    return [f.strip().strip("\"'") for f in fields]


def _is_number(field: str) -> bool:
    return _NUMBER.fullmatch(field) is not None


def points_from_text(
    text: str,
    *,
    limits: Limits = Limits(),
) -> FloatArray:
    """Points from CSV/TXT text, one ``x y`` pair per line.

    Separators: whitespace (spaces or tabs), ``,`` or ``;`` (with ``;`` a decimal comma is
    accepted). Blank lines and ``#`` comments (whole-line or trailing) are skipped. The first
    non-comment line is skipped as a header if it has two fields and neither is a number
    (``x,y``, ``X;Y``, ``"x" "y"``). Any other line that is not exactly two numbers is an
    error naming the line (counted from 1).
    """
    rows: list[tuple[float, float]] = []
    first = True
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = _split_fields(line)
        if first:
            first = False
            if len(fields) == 2 and not any(_is_number(f) for f in fields):
                continue  # header
        shown = raw.strip()
        if len(shown) > 60:
            shown = shown[:57] + "..."
        if len(fields) != 2 or not all(_is_number(f) for f in fields):
            raise IngestError(f"line {lineno}: expected two numbers, got {shown!r}")
        x, y = float(fields[0]), float(fields[1])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise IngestError(f"line {lineno}: non-finite coordinate in {shown!r}")
        if abs(x) > limits.max_coordinate or abs(y) > limits.max_coordinate:
            raise IngestError(
                f"line {lineno}: coordinate beyond ±{_fmt_num(limits.max_coordinate)} in "
                f"{shown!r}, the limit (setting max_coordinate)"
            )
        rows.append((x, y))
        if len(rows) > limits.max_points:
            raise _too_many(limits)
    if not rows:
        raise IngestError("no points found: the file has only blank lines, comments or a header")
    return _finalise(np.asarray(rows, dtype=np.float64).reshape(-1, 2), limits)


# --------------------------------------------------------------------------- npy


def points_from_npy(
    data: bytes,
    *,
    limits: Limits = Limits(),
) -> FloatArray:
    """Points from an ``.npy`` file: a numeric (integer or float) ``(n, 2)`` array.

    The header is checked before any data is read, so a header declaring a huge shape cannot
    make the loader allocate memory; the data is then read with ``allow_pickle=False``, so
    object arrays (which would need unpickling, i.e. running code) are refused.
    """
    if not data:
        raise IngestError("empty file")
    fp = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, _fortran, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, _fortran, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            raise IngestError(
                f"unsupported npy format version {version[0]}.{version[1]}; "
                f"save a plain numeric array with numpy.save"
            )
    except IngestError:
        raise
    except (ValueError, SyntaxError, EOFError, TypeError) as e:
        raise IngestError(f"not a valid npy file: {e}") from e
    if dtype.hasobject:
        raise IngestError(
            "the npy file holds Python objects (pickled data), which are refused for safety; "
            "save a numeric array, e.g. numpy.save(f, points.astype(float))"
        )
    if dtype.fields is not None or dtype.kind not in "iuf":
        raise IngestError(f"expected numeric coordinates (integers or floats); got dtype {dtype}")
    if len(shape) != 2 or shape[1] != 2:
        raise IngestError(f"expected points of shape (n, 2); got shape {tuple(shape)}")
    _check_count(int(shape[0]), limits)
    try:
        arr = np.load(io.BytesIO(data), allow_pickle=False)
    except ValueError as e:
        raise IngestError(f"could not read the npy file: {e}") from e
    except (OSError, EOFError) as e:
        raise IngestError(f"could not read the npy file: {e}") from e
    if not isinstance(arr, np.ndarray):  # pragma: no cover - magic already checked
        raise IngestError("not a valid npy file")
    return _finalise(arr, limits)


# --------------------------------------------------------------------------- images

MIN_CONTRAST = 16  # grey levels between background and foreground below which nothing is there
MIN_CONTOUR_LENGTH = 6.0  # px; drops specks of a few pixels (JPEG noise)
MIN_CONTOUR_FRACTION = 0.01  # of the longest contour's length; drops relative specks


def _open_image(data: bytes, limits: Limits) -> Image.Image:
    if not data:
        raise IngestError("empty file")
    try:
        im: Image.Image = Image.open(io.BytesIO(data), formats=("PNG", "JPEG"))
    except Image.DecompressionBombError as e:
        # Pillow's own guard (2 * Image.MAX_IMAGE_PIXELS) fires while reading the header of
        # images far beyond any sensible max_image_pixels.
        raise IngestError(
            f"image too large: its declared size is beyond Pillow's decompression-bomb "
            f"guard; the limit is {limits.max_image_pixels} pixels (setting max_image_pixels)"
        ) from e
    except UnidentifiedImageError as e:
        raise IngestError(
            "could not decode image: not a PNG or JPEG file (other image formats are not supported)"
        ) from e
    except MemoryError:
        raise
    except Exception as e:  # Pillow raises many exception types on corrupt data
        raise IngestError(f"could not decode image: {e}") from e
    w, h = im.size
    # Decompression-bomb guard: only the header has been read so far.
    if w * h > limits.max_image_pixels:
        raise IngestError(
            f"image too large: {w}x{h} = {w * h} pixels; the limit is "
            f"{limits.max_image_pixels} pixels (setting max_image_pixels)"
        )
    if w == 0 or h == 0:
        raise IngestError("could not decode image: it has no pixels")
    try:
        im.load()
        im = ImageOps.exif_transpose(im)
    except MemoryError:
        raise
    except Exception as e:
        raise IngestError(f"could not decode image: {e}") from e
    return im


def _to_grey(im: Image.Image) -> npt.NDArray[np.uint8]:
    """Greyscale uint8 array; alpha composited over white, 16-bit scaled to 8-bit."""
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
        white = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
        grey = np.asarray(Image.alpha_composite(white, rgba).convert("L"))
        alpha = np.asarray(rgba.getchannel("A"))
        if int(grey.max()) - int(grey.min()) < MIN_CONTRAST <= int(alpha.max()) - int(alpha.min()):
            # A light shape on a transparent background vanishes over white: the shape is
            # then given by the alpha channel alone.
            return np.asarray(255 - alpha, dtype=np.uint8)
        return np.asarray(grey, dtype=np.uint8)
    if im.mode not in ("L", "RGB", "1", "P"):
        im = im.convert("RGB")
    return np.asarray(im.convert("L"), dtype=np.uint8)


def _no_foreground(why: str) -> IngestError:
    return IngestError(
        f"image has no foreground pixels: {why}; expected a dark shape on a light background "
        f"or a light shape on a dark background"
    )


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
    levels = np.arange(256)
    dark_hist = np.where(levels <= t_otsu, hist, 0)
    bright_hist = hist - dark_hist

    def median(h: npt.NDArray[np.int64]) -> float:
        c = np.cumsum(h)
        total = int(c[-1])
        lo_i = int(np.searchsorted(c, (total + 1) // 2))
        hi_i = int(np.searchsorted(c, total // 2 + 1))
        return (lo_i + hi_i) / 2.0

    m_dark, m_bright = median(dark_hist), median(bright_hist)
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
    found = find_contours(padded, 0.5)
    out: list[FloatArray] = []
    for c in found:
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


def points_from_image(
    data: bytes,
    *,
    mode: ImageMode,
    target_points: int | None = None,
    limits: Limits = Limits(),
) -> FloatArray:
    """Points from a PNG or JPEG image of a shape.

    Modes (coordinates: x = column, y = row, pixel centres at integers):

    * ``contour``: the boundaries (outer and holes) of the thresholded shape, from
      ``skimage.measure.find_contours`` at level 0.5 on the binary mask, so they lie on the
      pixel edges between shape and background. Every contour at least 6 px and 1 % of the
      longest contour long is kept (specks dropped); contours are concatenated longest
      first, each closed contour starting at its first vertex, without repeating it.
    * ``edges``: Canny edges (``skimage.feature.canny``, sigma 1, default thresholds) of the
      grey image, as in Du et al. 2016, computed with the shape made bright and the grey
      range stretched to 0..255 (so both polarities and faint scans give the same edges as
      crisp black on white); edge pixels in raster order (by row, then column).
    * ``skeleton``: ``skimage.morphology.skeletonize`` of the thresholded shape; skeleton
      pixels in raster order.

    ``target_points`` is an upper bound: if the mode yields more points, they are reduced
    deterministically. Contours are resampled at equal arc-length steps, the points split
    over the contours in proportion to their lengths (largest remainder; a contour whose
    share rounds to 0 is dropped). Edges and skeletons are subsampled at evenly spaced
    indices of the raster ordering, ``round(linspace(0, n - 1, target_points))``, which keeps
    the density along the curves roughly uniform. Fewer points are never padded.
    Without ``target_points``, an image yielding more than ``max_points`` points is an error.
    """
    if mode not in IMAGE_MODES:
        raise IngestError(f"unknown image mode {mode!r}; expected one of {', '.join(IMAGE_MODES)}")
    if target_points is not None:
        if (
            isinstance(target_points, bool)
            or not isinstance(target_points, int | np.integer)
            or not limits.min_points <= target_points <= limits.max_points
        ):
            raise IngestError(
                f"target_points must be an integer between {limits.min_points} and "
                f"{limits.max_points} (settings min_points and max_points_per_shape); "
                f"got {target_points!r}"
            )
        target_points = int(target_points)
    im = _open_image(data, limits)
    grey = _to_grey(im)

    fg, fg_dark = _foreground(grey)
    if mode == "edges":
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
        return _reduce_raster(pts, target_points, limits)

    if mode == "skeleton":
        from skimage.morphology import skeletonize

        pts = _pixels_xy(skeletonize(fg))
        return _reduce_raster(pts, target_points, limits)

    contours = _contours(fg)
    lengths = np.array([_closed_length(c) for c in contours], dtype=np.float64)
    keep = lengths >= max(MIN_CONTOUR_LENGTH, MIN_CONTOUR_FRACTION * float(lengths.max()))
    order = [i for i in np.argsort(-lengths, kind="stable") if keep[i]]
    contours = [contours[i] for i in order]
    lengths = lengths[order]
    if not contours:
        raise _no_foreground("only specks of a few pixels")
    total = sum(len(c) for c in contours)
    if target_points is not None and total > target_points:
        counts = _allocate(lengths, target_points)
        contours = [
            _resample_closed(c, int(k)) for c, k in zip(contours, counts, strict=True) if k > 0
        ]
    elif total > limits.max_points:
        raise _image_too_many(total, limits)
    return _finalise(np.concatenate(contours, axis=0), limits)


def _image_too_many(n: int, limits: Limits) -> IngestError:
    return IngestError(
        f"the image yields {n} points; at most {limits.max_points} are allowed (setting "
        f"max_points_per_shape); ask for fewer with target_points"
    )


def _reduce_raster(pts: FloatArray, target: int | None, limits: Limits) -> FloatArray:
    n = len(pts)
    if target is not None and n > target:
        idx = np.rint(np.linspace(0, n - 1, target)).astype(np.int64)
        pts = pts[idx]
    elif n > limits.max_points:
        raise _image_too_many(n, limits)
    return _finalise(pts, limits)

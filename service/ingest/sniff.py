"""Which format an upload is, decided once, and its decoding by that format.

:func:`decode_upload` sniffs the bytes (magic bytes, then the file name's extension, then
the content type, then a text heuristic), decodes them with the matching format module, and
returns the points with the ``source_format`` the service stores: the route never looks at
the bytes again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from service.ingest._base import DEFAULT_LIMITS, FloatArray, IngestError, Limits
from service.ingest.points_image import ImageMode, check_mode, points_from_image
from service.ingest.points_json import parse_json, points_from_json
from service.ingest.points_npy import points_from_npy
from service.ingest.points_text import decode_text, points_from_text

Format = Literal["json", "text", "npy", "image"]

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


@dataclass(frozen=True)
class Decoded:
    """An upload's points and how they were made (``Shape.source_format``).

    ``source_format`` is ``json``, ``csv``, ``txt``, ``npy``, or ``png:MODE`` /
    ``jpeg:MODE`` for images (``MODE`` the image mode).
    """

    points: FloatArray
    source_format: str


def _text_kind(filename: str | None, content_type: str | None) -> str:
    ext = filename.rsplit(".", 1)[-1].lower() if filename and "." in filename else ""
    ctype = (content_type or "").split(";", 1)[0].strip().lower()
    return "csv" if ext == "csv" or ctype == "text/csv" else "txt"


def decode_upload(
    data: bytes,
    *,
    filename: str | None = None,
    content_type: str | None = None,
    mode: ImageMode = "contour",
    target_points: int | None = None,
    limits: Limits = DEFAULT_LIMITS,
) -> Decoded:
    """Decode an uploaded file (any supported format), sniffing its format once.

    ``mode`` and ``target_points`` apply to images only (see :func:`points_from_image`);
    ``mode`` is validated for every upload so that a bad request parameter is reported even
    when the file is not an image.
    """
    check_mode(mode)
    fmt = detect_format(filename, content_type, data)
    if fmt == "npy":
        return Decoded(points_from_npy(data, limits=limits), "npy")
    if fmt == "image":
        points = points_from_image(data, mode=mode, target_points=target_points, limits=limits)
        kind = "png" if data.startswith(_PNG_MAGIC) else "jpeg"  # the only decoded formats
        return Decoded(points, f"{kind}:{mode}")
    if fmt == "json":
        return Decoded(points_from_json(parse_json(data), limits=limits), "json")
    points = points_from_text(decode_text(data), limits=limits)
    return Decoded(points, _text_kind(filename, content_type))


def decode_points(data: bytes, **options: Any) -> FloatArray:
    """The points of :func:`decode_upload` (same keyword options), an ``(n, 2)`` array."""
    return decode_upload(data, **options).points

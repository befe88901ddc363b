"""Decode uploaded shapes into ``(n, 2)`` point arrays, one module per format.

Pure functions, no web framework: the API layer calls :func:`decode_upload` (which sniffs
the format once and returns the points with their ``source_format``) or one of the
format-specific functions, and turns an :class:`IngestError` into a 4xx problem+json
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
  shape on a dark background. The image work is the library's
  (:func:`registration.images.points_from_image`, usable without a server); see it for the
  modes.

Modules: ``sniff`` (format detection and :func:`decode_upload`), ``points_json``,
``points_text``, ``points_npy``, ``points_image``; ``_base`` holds the limits and the checks
every format ends with.

Output
------
Always a C-contiguous float64 array of shape ``(n, 2)`` with finite values, ``min_points <= n
<= max_points``, ``|coordinate| <= max_coordinate``, and a size (RMS distance of the points
from their centroid) above ``DEGENERATE_RTOL`` times the largest coordinate (at least 1):
all points equal, or nearly so, is refused, since such a shape cannot be registered.
Columns are ``(x, y)``; for images, pixel units with ``x`` = column, ``y`` = row (y pointing
down), pixel centres at integers.

Indices in messages: "point i" counts from 0 (the position in the uploaded array); "line i"
counts from 1 (as a text editor shows it).
"""

from __future__ import annotations

from service.ingest._base import DEGENERATE_RTOL, IngestError, Limits
from service.ingest.points_image import IMAGE_MODES, ImageMode, points_from_image
from service.ingest.points_json import points_from_json
from service.ingest.points_npy import points_from_npy
from service.ingest.points_text import points_from_text
from service.ingest.sniff import Decoded, Format, decode_points, decode_upload, detect_format

__all__ = [
    "DEGENERATE_RTOL",
    "IMAGE_MODES",
    "Decoded",
    "Format",
    "ImageMode",
    "IngestError",
    "Limits",
    "decode_points",
    "decode_upload",
    "detect_format",
    "points_from_image",
    "points_from_json",
    "points_from_npy",
    "points_from_text",
]

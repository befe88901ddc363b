"""PNG and JPEG uploads: points from :func:`registration.images.points_from_image`.

The library function does the image work (a notebook user calls it without a server); this
adapter adds what is the service's: only PNG and JPEG are decoded (Pillow is not asked to
try its other decoders on uploaded bytes), the settings' limits, and messages that name the
setting that rules.
"""

from __future__ import annotations

import numpy as np

from registration import images
from registration.images import IMAGE_MODES, ImageMode
from service.ingest._base import DEFAULT_LIMITS, FloatArray, IngestError, Limits, finalise

#: Pillow formats an upload may be decoded as.
DECODED_FORMATS = ("PNG", "JPEG")


def check_mode(mode: str) -> None:
    if mode not in IMAGE_MODES:
        raise IngestError(f"unknown image mode {mode!r}; expected one of {', '.join(IMAGE_MODES)}")


def _check_target(target_points: object, limits: Limits) -> int | None:
    if target_points is None:
        return None
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
    return int(target_points)


def _too_large(e: images.ImageTooLarge, limits: Limits) -> IngestError:
    if e.size is None:
        return IngestError(
            "image too large: its declared size is beyond Pillow's decompression-bomb "
            f"guard; the limit is {limits.max_image_pixels} pixels (setting max_image_pixels)"
        )
    w, h = e.size
    return IngestError(
        f"image too large: {w}x{h} = {w * h} pixels; the limit is "
        f"{limits.max_image_pixels} pixels (setting max_image_pixels)"
    )


def points_from_image(
    data: bytes,
    *,
    mode: ImageMode,
    target_points: int | None = None,
    limits: Limits = DEFAULT_LIMITS,
) -> FloatArray:
    """Points from a PNG or JPEG upload; see :func:`registration.images.points_from_image`.

    ``target_points`` must lie within the limits' point bounds. Without it, an image
    yielding more than ``max_points`` points is an error that suggests it.
    """
    check_mode(mode)
    target = _check_target(target_points, limits)
    if not data:
        raise IngestError("empty file")
    try:
        points = images.points_from_image(
            data,
            mode=mode,
            target_points=target,
            max_pixels=limits.max_image_pixels,
            formats=DECODED_FORMATS,
        )
    except images.ImageTooLarge as e:
        raise _too_large(e, limits) from e
    except ValueError as e:
        raise IngestError(str(e)) from e
    if len(points) > limits.max_points:
        raise IngestError(
            f"the image yields {len(points)} points; at most {limits.max_points} are allowed "
            "(setting max_points_per_shape); ask for fewer with target_points"
        )
    return finalise(points, limits)

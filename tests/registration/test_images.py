"""registration.images: points from pictures without a server, as the service makes them."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageDraw

from registration.images import ImageTooLarge, grey_levels, points_from_image


def ellipse(fg: int = 0, bg: int = 255) -> Image.Image:
    image = Image.new("L", (120, 90), bg)
    ImageDraw.Draw(image).ellipse((20, 15, 99, 74), fill=fg)
    return image


def encoded(image: Image.Image, fmt: str = "PNG") -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, fmt)
    return buffer.getvalue()


@pytest.mark.parametrize("mode", ["contour", "edges", "skeleton"])
def test_every_input_kind_gives_the_same_points(mode: str, tmp_path: Path) -> None:
    image = ellipse()
    path = tmp_path / "glyph.png"
    image.save(path)
    reference = points_from_image(encoded(image), mode=mode)  # type: ignore[arg-type]
    assert reference.dtype == np.float64 and reference.shape[1] == 2
    for source in (path, str(path), image, np.asarray(image), np.asarray(image.convert("RGB"))):
        np.testing.assert_array_equal(points_from_image(source, mode=mode), reference)  # type: ignore[arg-type]
    mask = np.asarray(image) < 128  # a boolean mask: the shape is True, drawn dark
    np.testing.assert_array_equal(points_from_image(~mask, mode=mode), reference)  # type: ignore[arg-type]


def test_the_service_stores_the_library_points() -> None:
    from service.ingest import decode_upload

    data = encoded(ellipse())
    upload = decode_upload(data, filename="e.png", mode="edges", target_points=50)
    assert upload.source_format == "png:edges"
    np.testing.assert_array_equal(
        upload.points, points_from_image(data, mode="edges", target_points=50)
    )


def test_contour_lies_on_the_ellipse_and_target_points_bounds_it() -> None:
    p = points_from_image(ellipse(), target_points=100)
    assert p.shape == (100, 2)
    cx, cy, a, b = 59.5, 44.5, 39.5, 29.5
    radius = np.hypot((p[:, 0] - cx) / a, (p[:, 1] - cy) / b)
    assert np.abs(radius - 1).max() < 0.05


def test_errors_are_value_errors_with_the_reason() -> None:
    with pytest.raises(ValueError, match="no foreground pixels: it is a single uniform colour"):
        points_from_image(Image.new("L", (20, 20), 255))
    with pytest.raises(ValueError, match="unknown image mode 'canny'"):
        points_from_image(ellipse(), mode="canny")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="target_points must be a positive integer"):
        points_from_image(ellipse(), target_points=0)
    with pytest.raises(ValueError, match="image array must be uint8"):
        points_from_image(np.zeros((10, 10), dtype=np.float32))
    with pytest.raises(ValueError, match=r"not a PNG or JPEG file"):
        points_from_image(encoded(ellipse(), "GIF"), formats=("PNG", "JPEG"))
    assert len(points_from_image(encoded(ellipse(), "GIF"))) > 0  # any format Pillow knows
    with pytest.raises(ImageTooLarge, match=r"120x90 = 10800 pixels; the limit is 10000") as e:
        grey_levels(encoded(ellipse()), max_pixels=10_000)
    assert e.value.size == (120, 90) and e.value.limit == 10_000


def test_registration_does_not_import_pillow() -> None:
    import subprocess
    import sys

    code = "import sys, registration; print('PIL' in sys.modules, 'skimage' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]

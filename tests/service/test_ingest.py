"""Tests for service.ingest: every input format, every error message, image geometry.

All fixtures are generated here (Pillow drawings, numpy.save); nothing is read from disk.
"""

from __future__ import annotations

import io
import json
import struct
import zlib

import numpy as np
import pytest
from PIL import Image, ImageDraw

from service.ingest import (
    IngestError,
    Limits,
    decode_points,
    detect_format,
    points_from_image,
    points_from_json,
    points_from_npy,
    points_from_text,
)

SQUARE = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
SQUARE_ARR = np.array(SQUARE)


# --------------------------------------------------------------------------- fixtures


def encode(im: Image.Image, fmt: str = "PNG", **kw: object) -> bytes:
    buf = io.BytesIO()
    im.save(buf, fmt, **kw)
    return buf.getvalue()


def npy(arr: np.ndarray, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=allow_pickle)
    return buf.getvalue()


# A filled ellipse; Pillow fills the ellipse inscribed in the inclusive pixel box.
W, H = 160, 120
BOX = (30, 20, 129, 99)
CX, CY = (BOX[0] + BOX[2]) / 2, (BOX[1] + BOX[3]) / 2
A, B = (BOX[2] - BOX[0]) / 2, (BOX[3] - BOX[1]) / 2


def ellipse_image(fg: int = 0, bg: int = 255, mode: str = "L") -> Image.Image:
    im = Image.new("L", (W, H), bg)
    ImageDraw.Draw(im).ellipse(BOX, fill=fg)
    return im.convert(mode) if mode != "L" else im


def ring_image(width: int = 12) -> Image.Image:
    im = Image.new("L", (W, H), 255)
    ImageDraw.Draw(im).ellipse(BOX, outline=0, width=width)
    return im


def bar_image(fg: int = 0, bg: int = 255) -> Image.Image:
    """A thick horizontal bar, rows 50..69 (centre line y = 59.5), columns 20..139."""
    im = Image.new("L", (W, H), bg)
    ImageDraw.Draw(im).rectangle((20, 50, 139, 69), fill=fg)
    return im


# A letter-like "T": horizontal bar rows 20..35, cols 30..129; stem cols 72..87, rows 36..99.
T_BAR = (30, 20, 129, 35)
T_STEM = (72, 36, 87, 99)


def t_image() -> Image.Image:
    im = Image.new("L", (W, H), 255)
    d = ImageDraw.Draw(im)
    d.rectangle(T_BAR, fill=0)
    d.rectangle(T_STEM, fill=0)
    return im


def dist_to_ellipse(pts: np.ndarray, a: float = A, b: float = B) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    curve = np.column_stack([CX + a * np.cos(t), CY + b * np.sin(t)])
    d = np.hypot(pts[:, None, 0] - curve[None, :, 0], pts[:, None, 1] - curve[None, :, 1])
    return d.min(axis=1)


def assert_points(p: np.ndarray, n: int | None = None) -> None:
    assert p.dtype == np.float64
    assert p.ndim == 2 and p.shape[1] == 2
    assert p.flags.c_contiguous
    assert np.isfinite(p).all()
    if n is not None:
        assert p.shape[0] == n


# --------------------------------------------------------------------------- JSON


@pytest.mark.parametrize(
    "obj",
    [
        SQUARE,
        {"points": SQUARE},
        {"points": SQUARE, "name": "glyph 12"},
        [[0, 0], [1, 0], [1, 1], [0, 1]],
        [[0, 0.0], [1, 0], [1.0, 1], [0, 1]],
    ],
)
def test_json_accepted(obj: object) -> None:
    p = points_from_json(obj)
    assert_points(p, 4)
    np.testing.assert_array_equal(p, SQUARE_ARR)
    q = decode_points(json.dumps(obj).encode())
    np.testing.assert_array_equal(q, SQUARE_ARR)


def test_json_bytes_with_bom_and_whitespace() -> None:
    data = b"\xef\xbb\xbf \n" + json.dumps(SQUARE).encode()
    np.testing.assert_array_equal(decode_points(data), SQUARE_ARR)


@pytest.mark.parametrize(
    ("obj", "match"),
    [
        (
            [[0, 0, 0], [1, 0, 0], [1, 1, 0]],
            r"expected points of shape \(n, 2\); got shape \(3, 3\)",
        ),
        ([0, 1, 2, 3], r"point 0: expected a pair \[x, y\]; got a number"),
        ([[0, 0], [1, 0], [1, 1, 5]], r"point 2 has 3 coordinates; expected 2"),
        ([[0, 0], [1, "3"], [1, 1]], r'point 1: coordinates must be numbers; got the string "3"'),
        ([[0, 0], [1, True], [1, 1]], r"point 1: coordinates must be numbers; got a boolean"),
        ([[0, 0], [1, None], [1, 1]], r"point 1: coordinates must be numbers; got null"),
        ([[0, 0], [float("nan"), 1], [1, 1]], r"point 1 has a non-finite coordinate"),
        ([[0, 0], [1, float("inf")], [1, 1]], r"point 1 has a non-finite coordinate"),
        ([[0, 0], [1, 2e7], [1, 1]], r"point 1 has a coordinate beyond ±1e\+07.*max_coordinate"),
        ([[0, 0], [10**400, 1], [1, 1]], r"point 1 has a coordinate beyond ±1e\+07"),
        ([[0, 0], [1, 1]], r"got 2 points; at least 3 are required \(setting min_points\)"),
        ([], r"no points found"),
        ({"pts": SQUARE}, r'object with a "points" array; the object has no "points" key'),
        ({"points": "0 0 1 1"}, r'"points" must be an array of \[x, y\] pairs; got the string'),
        ("0 0 1 1", r"expected a JSON array of \[x, y\] pairs; got the string"),
        (None, r"expected a JSON array of \[x, y\] pairs; got null"),
    ],
)
def test_json_errors(obj: object, match: str) -> None:
    with pytest.raises(IngestError, match=match):
        points_from_json(obj)


def test_json_too_many_points() -> None:
    obj = [[i, i] for i in range(11)]
    with pytest.raises(
        IngestError,
        match=r"got 11 points; at most 10 are allowed \(setting max_points_per_shape\)",
    ):
        points_from_json(obj, limits=Limits(max_points=10))
    assert points_from_json(obj[:10], limits=Limits(max_points=10)).shape == (10, 2)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"[[0, 0], [1, 0],", r"invalid JSON: Expecting value at line 1 column 17"),
        (b'{"points": [[0, 0]]', r"invalid JSON: .* at line 1"),
        (b"[" * 100000 + b"]" * 100000, r"invalid JSON: nested too deeply"),
        (b"[\xff\xfe\x00]", r"invalid JSON"),
    ],
)
def test_json_decode_errors(data: bytes, match: str) -> None:
    with pytest.raises(IngestError, match=match):
        decode_points(data)


# --------------------------------------------------------------------------- text


@pytest.mark.parametrize(
    "text",
    [
        "0 0\n1 0\n1 1\n0 1\n",
        "0,0\n1,0\n1,1\n0,1",
        "0;0\n1;0\n1;1\n0;1\n",
        "0\t0\n1\t0\n1\t1\n0\t1\n",
        "0, 0\n1 ,0\n  1,  1  \n0 ,  1\n",
        "0   0\r\n1 0\r\n1 1\r\n0 1\r\n",
        "x,y\n0,0\n1,0\n1,1\n0,1\n",
        "X Y\n0 0\n1 0\n1 1\n0 1\n",
        '"x";"y"\n0;0\n1;0\n1;1\n0;1\n',
        "# outline of glyph 7\n\nx,y\n0,0\n\n1,0  # corner\n# another comment\n1,1\n0,1\n\n",
        "0.0e0 0\n1.0 0.\n1 1\n.0 1\n",
        "+0 -0\n1 0\n1 1\n0 1\n",
        "0,0,\n1,0,\n1,1,\n0,1,\n",
        "0,0;0,0\n1,0;0\n1;1,0\n0;1\n",
        '"0","0"\n"1","0"\n"1","1"\n"0","1"\n',
    ],
)
def test_text_accepted(text: str) -> None:
    p = points_from_text(text)
    assert_points(p, 4)
    np.testing.assert_array_equal(np.abs(p), SQUARE_ARR)
    q = decode_points(text.encode(), filename="shape.csv")
    np.testing.assert_array_equal(q, p)


def test_text_decimal_comma_with_semicolon() -> None:
    p = points_from_text("1,5;2,25\n3;4,75\n-0,5;0\n")
    np.testing.assert_array_equal(p, [[1.5, 2.25], [3, 4.75], [-0.5, 0]])


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        ("0 0\n1 0\n1 1\n0 1\n".encode("utf-16"), SQUARE_ARR),
        ("# Präparat Nr. 3\n0 0\n1 0\n1 1\n0 1\n".encode("latin-1"), SQUARE_ARR),
        ("# Präparat Nr. 3\n0 0\n1 0\n1 1\n0 1\n".encode("utf-8-sig"), SQUARE_ARR),
    ],
)
def test_text_encodings(data: bytes, expected: np.ndarray) -> None:
    np.testing.assert_array_equal(decode_points(data, filename="p.txt"), expected)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "# header comment\nx,y\n0 0\n1 0\n\n1 1\nabc 3\n0 1\n",
            r"^line 7: expected two numbers, got 'abc 3'$",
        ),
        ("0 0\n1 0\n1 1 1\n", r"^line 3: expected two numbers, got '1 1 1'$"),
        ("0 0\n1\n1 1\n", r"^line 2: expected two numbers, got '1'$"),
        ("0 0\n1 0\n1;1;1\n", r"line 3: expected two numbers, got '1;1;1'"),
        ("0 0\n1 0\n1,5 2\n", r"line 3: expected two numbers, got '1,5 2'"),
        ("x,y\nu,v\n0 0\n", r"^line 2: expected two numbers, got 'u,v'$"),
        ("abc 3\n0 0\n1 1\n", r"^line 1: expected two numbers, got 'abc 3'$"),
        ("0 0\n1 " + "9" * 100 + "x\n", r"line 2: expected two numbers, got '1 9{55}\.\.\.'$"),
        ("0 0\nnan 1\n1 1\n", r"^line 2: non-finite coordinate in 'nan 1'$"),
        ("0 0\n1 inf\n1 1\n", r"^line 2: non-finite coordinate in '1 inf'$"),
        ("0 0\n1 1e400\n1 1\n", r"^line 2: non-finite coordinate"),
        ("0 0\n1 2e7\n1 1\n", r"^line 2: coordinate beyond ±1e\+07 in '1 2e7'.*max_coordinate"),
        ("0 0\n1 1\n", r"got 2 points; at least 3 are required \(setting min_points\)"),
        ("", r"no points found"),
        ("\n# only a comment\n\n", r"no points found"),
        ("x,y\n", r"no points found"),
    ],
)
def test_text_errors(text: str, match: str) -> None:
    with pytest.raises(IngestError, match=match):
        points_from_text(text)


def test_text_too_many_points_stops_early() -> None:
    text = "".join(f"{i} {i}\n" for i in range(20)) + "this line is never reached\n"
    with pytest.raises(
        IngestError, match=r"more than 10 points, the limit \(setting max_points_per_shape\)"
    ):
        points_from_text(text, limits=Limits(max_points=10))


def test_text_with_nul_bytes_refused() -> None:
    with pytest.raises(IngestError, match=r"not text \(it contains NUL bytes\)"):
        decode_points(b"0 0\n1\x00 1\n", filename="p.txt")


# --------------------------------------------------------------------------- npy


@pytest.mark.parametrize(
    "arr",
    [
        SQUARE_ARR,
        SQUARE_ARR.astype(np.float32),
        SQUARE_ARR.astype(np.float16),
        SQUARE_ARR.astype(np.int32),
        SQUARE_ARR.astype(np.uint8),
        SQUARE_ARR.astype(">f8"),
        SQUARE_ARR.astype(">i2"),
        np.asfortranarray(SQUARE_ARR),
    ],
    ids=lambda a: (
        f"{a.dtype.str}{'-F' if a.flags.f_contiguous and not a.flags.c_contiguous else ''}"
    ),
)
def test_npy_accepted(arr: np.ndarray) -> None:
    p = points_from_npy(npy(arr))
    assert_points(p, 4)
    np.testing.assert_array_equal(p, SQUARE_ARR)
    np.testing.assert_array_equal(decode_points(npy(arr)), SQUARE_ARR)


def test_npy_version_2_header() -> None:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, SQUARE_ARR, version=(2, 0))
    np.testing.assert_array_equal(points_from_npy(buf.getvalue()), SQUARE_ARR)


def test_npy_object_array_refused_even_if_saved_with_pickle() -> None:
    data = npy(np.array(SQUARE, dtype=object), allow_pickle=True)
    with pytest.raises(IngestError, match=r"Python objects \(pickled data\), which are refused"):
        points_from_npy(data)
    with pytest.raises(IngestError, match=r"pickled data"):
        decode_points(data, filename="points.npy")


def test_npy_raw_pickle_refused() -> None:
    import pickle

    data = pickle.dumps(SQUARE_ARR)
    with pytest.raises(IngestError, match=r"not a valid npy file"):
        points_from_npy(data)
    with pytest.raises(IngestError, match=r"not a valid npy file"):
        decode_points(data, filename="points.npy")


def forged_npy(shape: tuple[int, ...], payload: bytes = b"") -> bytes:
    """A v1.0 npy file whose header declares ``shape`` but carries only ``payload``."""
    header = f"{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}".encode()
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + payload


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (npy(np.zeros((5, 3))), r"expected points of shape \(n, 2\); got shape \(5, 3\)"),
        (npy(np.zeros(8)), r"expected points of shape \(n, 2\); got shape \(8,\)"),
        (npy(np.zeros((2, 2, 2))), r"got shape \(2, 2, 2\)"),
        (npy(np.zeros((4, 2), dtype=bool)), r"expected numeric coordinates .*got dtype bool"),
        (npy(np.zeros((4, 2), dtype=complex)), r"expected numeric coordinates .*got dtype complex"),
        (npy(np.zeros((4, 2), dtype="U3")), r"expected numeric coordinates .*got dtype <U3"),
        (
            npy(np.zeros(4, dtype=[("x", "f8"), ("y", "f8")])),
            r"expected numeric coordinates",
        ),
        (npy(np.zeros((2, 2))), r"got 2 points; at least 3 are required \(setting min_points\)"),
        (npy(np.zeros((0, 2))), r"no points found"),
        (
            npy(np.zeros((20001, 2))),
            r"got 20001 points; at most 20000 are allowed \(setting max_points_per_shape\)",
        ),
        (
            npy(np.where(np.arange(40).reshape(20, 2) == 25, np.nan, 1.0)),
            r"^point 12 has a non-finite coordinate \(1, nan\); points are counted from 0$",
        ),
        (npy(np.array([[0, 0], [1, -np.inf], [2, 2]])), r"point 1 has a non-finite coordinate"),
        (npy(np.array([[0, 0], [1, -2e7], [2, 2]])), r"point 1 has a coordinate beyond ±1e\+07"),
        (npy(np.array([[0, 0], [1, 2**62], [2, 2]])), r"point 1 has a coordinate beyond"),
        (npy(SQUARE_ARR)[:-8], r"could not read the npy file"),
        (forged_npy((10**12, 2)), r"got 1000000000000 points; at most 20000"),
        (forged_npy((100, 2)), r"could not read the npy file"),
        (b"\x93NUMPY\x01\x00garbage", r"not a valid npy file"),
        (b"\x93NUMPY\x03\x00" + npy(SQUARE_ARR)[8:], r"unsupported npy format version 3\.0"),
        (b"", r"empty file"),
    ],
)
def test_npy_errors(data: bytes, match: str) -> None:
    with pytest.raises(IngestError, match=match):
        points_from_npy(data)


# --------------------------------------------------------------------------- detection


@pytest.mark.parametrize(
    ("filename", "content_type", "data", "expected"),
    [
        # magic bytes win over a misleading name or type
        (None, None, npy(SQUARE_ARR), "npy"),
        ("shape.csv", "text/csv", npy(SQUARE_ARR), "npy"),
        ("shape.txt", "text/plain", encode(ellipse_image()), "image"),
        ("shape.npy", None, encode(ellipse_image(), "JPEG"), "image"),
        ("shape.png", "image/png", b'{"points": [[0, 0]]}', "json"),
        (None, None, b"  \n[[0,0]]", "json"),
        (None, None, encode(ellipse_image(), "GIF"), "image"),
        # then the extension
        ("shape.JSON", None, b"   ", "json"),
        ("shape.csv", None, b"0 0\n", "text"),
        ("shape.TXT", "application/octet-stream", b"0 0\n", "text"),
        ("shape.npy", None, b"not really", "npy"),
        ("glyph.jpeg", None, b"not really", "image"),
        # then the content type
        ("upload", "application/json; charset=utf-8", b"   ", "json"),
        (None, "application/geo+json", b"   ", "json"),
        (None, "text/csv", b"0 0\n", "text"),
        (None, "text/x-whatever", b"\x01\x02", "text"),
        (None, "application/x-npy", b"\x01\x02", "npy"),
        (None, "image/png", b"\x01\x02", "image"),
        # then plain text
        (None, None, b"0 0\n1 1\n", "text"),
        (None, "application/octet-stream", b"x;y\r\n0;0\r\n", "text"),
        (None, None, "0 0\n".encode("utf-16"), "text"),
    ],
)
def test_detect_format(
    filename: str | None, content_type: str | None, data: bytes, expected: str
) -> None:
    assert detect_format(filename, content_type, data) == expected


@pytest.mark.parametrize(
    ("filename", "content_type", "data", "match"),
    [
        (None, None, b"", r"^empty file$"),
        ("shape.csv", "text/csv", b"", r"^empty file$"),
        (None, None, b"\x00\x01\x02\x03binary", r"could not recognise the file format"),
        ("shape.bin", "application/octet-stream", b"\x00\x01", r"could not recognise"),
        (
            "shapes.npz",
            None,
            b"PK\x03\x04rest",
            r"zip archives \(including \.npz\) are not supported",
        ),
    ],
)
def test_detect_format_errors(
    filename: str | None, content_type: str | None, data: bytes, match: str
) -> None:
    with pytest.raises(IngestError, match=match):
        detect_format(filename, content_type, data)
    with pytest.raises(IngestError, match=match):
        decode_points(data, filename=filename, content_type=content_type)


def test_decode_points_rejects_unknown_mode_for_any_format() -> None:
    with pytest.raises(IngestError, match=r"unknown image mode 'outline'; expected one of contour"):
        decode_points(json.dumps(SQUARE).encode(), mode="outline")  # type: ignore[arg-type]


# --------------------------------------------------------------------------- images: geometry


def test_contour_of_ellipse_lies_on_ellipse() -> None:
    p = points_from_image(encode(ellipse_image()), mode="contour")
    assert_points(p)
    d = dist_to_ellipse(p)
    assert d.max() < 1.5
    assert d.mean() < 0.75
    # one closed contour going all the way round
    ang = np.arctan2(p[:, 1] - CY, p[:, 0] - CX)
    assert np.histogram(ang, bins=36, range=(-np.pi, np.pi))[0].min() > 0
    assert 0.9 * 2 * np.pi * 45 < len(p)  # at least one point per pixel of perimeter


def test_contour_of_ring_has_outer_and_inner_boundary() -> None:
    width = 12
    p = points_from_image(encode(ring_image(width)), mode="contour")
    d_out = dist_to_ellipse(p)
    d_in = dist_to_ellipse(p, A - width, B - width)
    on_outer = d_out < 1.5
    on_inner = d_in < 2.0
    assert (on_outer | on_inner).all()
    assert on_outer.sum() > 200 and on_inner.sum() > 150


def test_contour_of_letter_shape_follows_its_outline() -> None:
    p = points_from_image(encode(t_image()), mode="contour")
    # every contour point lies within 1 px of the union of the two rectangles' boundaries,
    # and outside neither rectangle's interior by more than a pixel
    mask = np.asarray(t_image()) < 128
    r = np.clip(np.rint(p[:, 1]).astype(int), 0, H - 1)
    c = np.clip(np.rint(p[:, 0]).astype(int), 0, W - 1)
    from scipy.ndimage import binary_dilation, binary_erosion

    band = binary_dilation(mask, iterations=1) & ~binary_erosion(mask, iterations=1)
    assert band[r, c].all()
    # the T's extremes are reached
    assert p[:, 0].min() == pytest.approx(T_BAR[0] - 0.5, abs=0.01)
    assert p[:, 0].max() == pytest.approx(T_BAR[2] + 0.5, abs=0.01)
    assert p[:, 1].min() == pytest.approx(T_BAR[1] - 0.5, abs=0.01)
    assert p[:, 1].max() == pytest.approx(T_STEM[3] + 0.5, abs=0.01)


def test_contour_includes_every_stroke_and_drops_specks() -> None:
    im = Image.new("L", (W, H), 255)
    d = ImageDraw.Draw(im)
    d.rectangle((10, 10, 40, 30), fill=0)  # stroke 1
    d.ellipse((90, 60, 120, 90), fill=0)  # stroke 2 (a dot)
    d.point((70, 100), fill=0)  # a one-pixel speck
    p = points_from_image(encode(im), mode="contour")
    assert ((p[:, 0] < 45) & (p[:, 1] < 35)).sum() > 50
    assert ((p[:, 0] > 85) & (p[:, 1] > 55)).sum() > 50
    assert not ((np.abs(p[:, 0] - 70) < 2) & (np.abs(p[:, 1] - 100) < 2)).any()


def test_edges_of_ellipse_lie_on_ellipse() -> None:
    p = points_from_image(encode(ellipse_image()), mode="edges")
    assert_points(p)
    assert dist_to_ellipse(p).max() < 1.5
    # edge pixels are integer pixel coordinates in raster order (row, then column)
    assert np.array_equal(p, np.rint(p))
    assert np.all(np.diff(p[:, 1]) >= 0)


def test_skeleton_of_bar_is_its_centre_line() -> None:
    p = points_from_image(encode(bar_image()), mode="skeleton")
    assert_points(p)
    assert np.array_equal(p, np.rint(p))
    middle = (p[:, 0] > 35) & (p[:, 0] < 125)
    assert np.abs(p[middle, 1] - 59.5).max() <= 1.0
    assert p[:, 0].min() < 35 and p[:, 0].max() > 125
    # inside the bar
    assert ((p[:, 0] >= 20) & (p[:, 0] <= 139) & (p[:, 1] >= 50) & (p[:, 1] <= 69)).all()


def test_skeleton_of_letter_follows_centre_lines() -> None:
    p = points_from_image(encode(t_image()), mode="skeleton")
    bar_cy = (T_BAR[1] + T_BAR[3]) / 2
    stem_cx = (T_STEM[0] + T_STEM[2]) / 2
    on_bar = np.abs(p[:, 1] - bar_cy) <= 1.0
    on_stem = np.abs(p[:, 0] - stem_cx) <= 1.0
    # away from the stroke ends, where skeletonize leaves short spurs
    core = (p[:, 0] > T_BAR[0] + 10) & (p[:, 0] < T_BAR[2] - 10) & (p[:, 1] <= T_BAR[3]) | (
        p[:, 1] > T_BAR[3] + 10
    ) & (p[:, 1] < T_STEM[3] - 10)
    assert (on_bar | on_stem)[core].all()
    assert on_stem.sum() > 40 and on_bar.sum() > 60


# --------------------------------------------------------------------------- images: polarity


@pytest.mark.parametrize("mode", ["contour", "edges", "skeleton"])
@pytest.mark.parametrize("make", [ellipse_image, bar_image])
def test_polarity_white_on_black_equals_black_on_white(mode: str, make: object) -> None:
    black_on_white = make(fg=0, bg=255)  # type: ignore[operator]
    white_on_black = make(fg=255, bg=0)  # type: ignore[operator]
    grey_on_dark = make(fg=200, bg=40)  # type: ignore[operator]
    p = points_from_image(encode(black_on_white), mode=mode)  # type: ignore[arg-type]
    q = points_from_image(encode(white_on_black), mode=mode)  # type: ignore[arg-type]
    r = points_from_image(encode(grey_on_dark), mode=mode)  # type: ignore[arg-type]
    np.testing.assert_array_equal(p, q)
    np.testing.assert_array_equal(p, r)


@pytest.mark.parametrize("fg,bg", [(0, 255), (255, 0)])
def test_polarity_shape_larger_than_background_uses_border(fg: int, bg: int) -> None:
    # the shape covers ~80 % of the image, so it is the majority class: the border decides
    im = Image.new("L", (100, 100), bg)
    ImageDraw.Draw(im).rectangle((5, 5, 94, 94), fill=fg)
    p = points_from_image(encode(im), mode="contour")
    assert p[:, 0].min() == pytest.approx(4.5) and p[:, 0].max() == pytest.approx(94.5)
    assert len(p) < 500  # the rectangle's outline only, not the frame's


@pytest.mark.parametrize("fg,bg", [(0, 255), (255, 0)])
def test_polarity_shape_cut_by_frame_uses_minority(fg: int, bg: int) -> None:
    # a bar crossing the whole image: half of the border is shape, half background
    im = Image.new("L", (100, 100), bg)
    ImageDraw.Draw(im).rectangle((0, 0, 99, 29), fill=fg)
    p = points_from_image(encode(im), mode="skeleton")
    assert (p[:, 1] <= 29).all()


# --------------------------------------------------------------------------- images: encodings


def reference_contour() -> np.ndarray:
    return points_from_image(encode(ellipse_image()), mode="contour")


@pytest.mark.parametrize(
    "data",
    [
        encode(ellipse_image(mode="RGB")),
        encode(ellipse_image(mode="1")),
        encode(ellipse_image(mode="P")),
        encode(ellipse_image().convert("RGB").convert("P", palette=Image.Palette.ADAPTIVE)),
        encode(ellipse_image(mode="LA")),
        encode(ellipse_image(mode="RGBA")),
        encode(Image.fromarray(np.asarray(ellipse_image()).astype(np.uint16) * 257)),
    ],
    ids=["RGB", "1-bit", "P", "P-adaptive", "LA", "RGBA", "16-bit"],
)
def test_png_colour_modes(data: bytes) -> None:
    np.testing.assert_array_equal(points_from_image(data, mode="contour"), reference_contour())


def test_png_alpha_is_composited_over_white() -> None:
    # black ellipse on a fully transparent black background: over white, the ellipse shows
    im = Image.new("RGBA", (W, H), (0, 0, 0, 0))
    ImageDraw.Draw(im).ellipse(BOX, fill=(0, 0, 0, 255))
    np.testing.assert_array_equal(
        points_from_image(encode(im), mode="contour"), reference_contour()
    )
    # palette image with a transparent index
    p = Image.new("P", (W, H), 0)
    p.putpalette([0, 0, 0, 0, 0, 0])
    ImageDraw.Draw(p).ellipse(BOX, fill=1)
    data = encode(p, transparency=0)
    np.testing.assert_array_equal(points_from_image(data, mode="contour"), reference_contour())


def test_png_white_shape_on_transparent_uses_alpha() -> None:
    im = Image.new("RGBA", (W, H), (255, 255, 255, 0))
    ImageDraw.Draw(im).ellipse(BOX, fill=(255, 255, 255, 255))
    np.testing.assert_array_equal(
        points_from_image(encode(im), mode="contour"), reference_contour()
    )


@pytest.mark.parametrize("mode", ["contour", "edges", "skeleton"])
def test_jpeg(mode: str) -> None:
    data = encode(ellipse_image(mode="RGB"), "JPEG", quality=85)
    assert detect_format("photo.jpg", "image/jpeg", data) == "image"
    p = decode_points(data, filename="photo.jpg", mode=mode)  # type: ignore[arg-type]
    assert_points(p)
    d = dist_to_ellipse(p)
    if mode == "skeleton":
        # the skeleton of a filled ellipse is its major axis (plus short spurs)
        assert (np.abs(p[:, 1] - CY) < B).all()
    else:
        assert d.max() < 1.5


def test_jpeg_exif_orientation_applied() -> None:
    exif = Image.Exif()
    exif[0x0112] = 6  # stored image is shown rotated 90° clockwise
    data = encode(bar_image().convert("RGB"), "JPEG", quality=95, exif=exif)
    p = points_from_image(data, mode="skeleton")
    # the horizontal bar is displayed vertical: x spread small, y spread large
    assert np.ptp(p[:, 0]) < 5 and np.ptp(p[:, 1]) > 80


# --------------------------------------------------------------------------- target_points


def test_target_points_contour_resamples_by_arc_length() -> None:
    data = encode(ellipse_image())
    p = points_from_image(data, mode="contour", target_points=100)
    assert_points(p, 100)
    assert dist_to_ellipse(p).max() < 1.5
    step = np.hypot(*np.diff(np.vstack([p, p[:1]]), axis=0).T)
    assert step.std() / step.mean() < 0.1
    np.testing.assert_array_equal(p, points_from_image(data, mode="contour", target_points=100))


def test_target_points_split_over_contours_by_length() -> None:
    p = points_from_image(encode(ring_image(12)), mode="contour", target_points=200)
    assert_points(p, 200)
    n_outer = int((dist_to_ellipse(p) < 1.5).sum())
    # outer perimeter / total perimeter, about 0.6 for this ring
    assert 110 <= n_outer <= 130


@pytest.mark.parametrize("mode", ["edges", "skeleton"])
def test_target_points_subsamples_raster_order(mode: str) -> None:
    data = encode(t_image())
    full = points_from_image(data, mode=mode)  # type: ignore[arg-type]
    p = points_from_image(data, mode=mode, target_points=50)  # type: ignore[arg-type]
    assert_points(p, 50)
    idx = np.rint(np.linspace(0, len(full) - 1, 50)).astype(int)
    np.testing.assert_array_equal(p, full[idx])


@pytest.mark.parametrize("mode", ["contour", "edges", "skeleton"])
def test_target_points_larger_than_output_returns_everything(mode: str) -> None:
    data = encode(bar_image())
    full = points_from_image(data, mode=mode)  # type: ignore[arg-type]
    p = points_from_image(data, mode=mode, target_points=20000)  # type: ignore[arg-type]
    np.testing.assert_array_equal(p, full)


@pytest.mark.parametrize("target", [0, 2, 20001, True, 3.5, "100"])
def test_target_points_invalid(target: object) -> None:
    with pytest.raises(IngestError, match=r"target_points must be an integer between 3 and 20000"):
        points_from_image(encode(bar_image()), mode="contour", target_points=target)  # type: ignore[arg-type]


@pytest.mark.parametrize("mode", ["contour", "edges", "skeleton"])
def test_image_with_too_many_points_suggests_target_points(mode: str) -> None:
    with pytest.raises(
        IngestError,
        match=r"the image yields \d+ points; at most 5 are allowed "
        r"\(setting max_points_per_shape\); ask for fewer with target_points",
    ):
        points_from_image(encode(ellipse_image()), mode=mode, limits=Limits(max_points=5))  # type: ignore[arg-type]


# --------------------------------------------------------------------------- image errors


def png_with_size(width: int, height: int) -> bytes:
    """A small valid PNG whose IHDR is rewritten to declare ``width`` x ``height``."""
    data = bytearray(encode(Image.new("L", (8, 8), 255)))
    ihdr = bytearray(data[12:29])  # b"IHDR" + 13 bytes of header fields
    ihdr[4:12] = struct.pack(">II", width, height)
    data[12:29] = ihdr
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(ihdr)))
    return bytes(data)


@pytest.mark.parametrize("mode", ["contour", "edges", "skeleton"])
@pytest.mark.parametrize(
    ("data", "match"),
    [
        (
            encode(Image.new("L", (50, 40), 255)),
            r"image has no foreground pixels: it is a single uniform colour",
        ),
        (encode(Image.new("RGB", (50, 40), (0, 0, 0))), r"image has no foreground pixels"),
        (encode(Image.new("RGBA", (50, 40), (0, 0, 0, 0))), r"image has no foreground pixels"),
        (
            encode(ellipse_image(fg=200, bg=208)),
            r"image has no foreground pixels: contrast too low \(8 grey levels\)",
        ),
        (b"", r"^empty file$"),
        (encode(ellipse_image())[:200], r"^could not decode image: "),
        (b"\x89PNG\r\n\x1a\n" + b"\x00" * 64, r"^could not decode image: "),
        (b"\xff\xd8\xff\xe0 not a jpeg", r"^could not decode image: "),
        (encode(ellipse_image(), "GIF"), r"could not decode image: not a PNG or JPEG file"),
        (encode(ellipse_image(), "BMP"), r"could not decode image: not a PNG or JPEG file"),
        (
            png_with_size(5000, 5000),
            r"image too large: 5000x5000 = 25000000 pixels; the limit is 16777216 pixels "
            r"\(setting max_image_pixels\)",
        ),
        (png_with_size(100000, 100000), r"image too large: .*\(setting max_image_pixels\)"),
    ],
    ids=[
        "white",
        "black",
        "transparent",
        "low-contrast",
        "empty",
        "truncated-png",
        "garbage-png",
        "garbage-jpeg",
        "gif",
        "bmp",
        "too-large",
        "bomb",
    ],
)
def test_image_errors(data: bytes, match: str, mode: str) -> None:
    with pytest.raises(IngestError, match=match):
        points_from_image(data, mode=mode)  # type: ignore[arg-type]


def test_image_pixel_limit_is_a_setting() -> None:
    data = encode(ellipse_image())
    with pytest.raises(
        IngestError, match=rf"image too large: {W}x{H} = {W * H} pixels; the limit is 1000"
    ):
        points_from_image(data, mode="contour", limits=Limits(max_image_pixels=1000))
    assert len(points_from_image(data, mode="contour", limits=Limits(max_image_pixels=W * H))) > 0


def test_image_with_only_specks_has_no_foreground() -> None:
    im = Image.new("L", (W, H), 255)
    ImageDraw.Draw(im).point([(10, 10), (50, 60), (100, 30)], fill=0)
    with pytest.raises(IngestError, match=r"image has no foreground pixels: only specks"):
        points_from_image(encode(im), mode="contour")


def test_image_too_few_points() -> None:
    im = Image.new("L", (W, H), 255)
    ImageDraw.Draw(im).point([(10, 10)], fill=0)
    with pytest.raises(IngestError, match=r"got 1 point; at least 3 are required"):
        points_from_image(encode(im), mode="skeleton")


def test_points_from_image_rejects_unknown_mode() -> None:
    with pytest.raises(IngestError, match=r"unknown image mode 'canny'"):
        points_from_image(encode(bar_image()), mode="canny")  # type: ignore[arg-type]


def test_limits_must_be_consistent() -> None:
    with pytest.raises(ValueError, match="max_points"):
        Limits(min_points=10, max_points=5)
    with pytest.raises(ValueError, match="min_points"):
        Limits(min_points=0)

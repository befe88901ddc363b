"""Simulated impressions of printing moulds (registration.impressions)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from registration.impressions import (
    PrintVariation,
    draw_strokes,
    identical_moulds,
    mould_from_points,
    recut_stroke_end,
    simulate_impressions,
    stroke_width,
)

STROKES = [[0.2, 0.2, 0.8, 0.2], [0.5, 0.2, 0.5, 0.85], [0.25, 0.55, 0.75, 0.55]]
QUIET = PrintVariation(ink=0.0, ink_local=0.0, blur=(0.0, 0.0), speckle=0.0, warp=0.0,
                       rotation=0.0, scale=0.0, resolution=(1.0, 1.0), noise=0.0)


@pytest.fixture(scope="module")
def mould() -> np.ndarray:
    return draw_strokes(STROKES, size=96, width=0.1)


def test_impressions_are_grey_scans_that_differ_and_repeat_with_the_seed(mould):
    a = simulate_impressions(mould, 3, seed=5)
    b = simulate_impressions(mould, 3, seed=5)
    assert all(x.dtype == np.uint8 for x in a)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert len({x.shape for x in a}) > 1  # scan resolutions differ
    for img in a:
        assert np.median(img) > 180  # light paper
        assert img.min() < 90  # dark ink


def test_quiet_print_reproduces_the_mould(mould):
    (img,) = simulate_impressions(mould, 1, variation=QUIET, seed=0)
    pad = (img.shape[0] - mould.shape[0]) // 2
    ink = img[pad: pad + mould.shape[0], pad: pad + mould.shape[1]] < 128
    assert (ink ^ mould).sum() <= 0.02 * mould.sum()


def test_ink_spread_and_erosion_move_the_boundary_by_at_most_the_bound(mould):
    ink = 1.5
    only_ink = PrintVariation(ink=ink, ink_local=0.0, blur=(0.0, 0.0), speckle=0.0, warp=0.0,
                              rotation=0.0, scale=0.0, resolution=(1.0, 1.0), noise=0.0)
    rng = np.random.default_rng(1)
    areas = [int((img < 128).sum())
             for img in simulate_impressions(mould, 6, variation=only_ink, seed=rng)]
    perimeter = int((mould & ~ndimage.binary_erosion(mould)).sum())
    spread = (np.array(areas) - mould.sum()) / perimeter  # mean boundary shift, px
    assert np.abs(spread).max() <= ink + 0.5
    assert spread.min() < -0.2 and spread.max() > 0.2  # both erosion and spread occur


def test_recut_changes_one_stroke_end_only(mould):
    for change in ("shorten", "extend"):
        r = recut_stroke_end(mould, change=change, seed=3)
        diff = np.argwhere(r.mould ^ mould)
        assert r.pixels_changed == len(diff) > 0
        reach = r.length + 2.0 * stroke_width(mould)
        assert np.hypot(diff[:, 1] - r.tip[0], diff[:, 0] - r.tip[1]).max() <= reach
        grew = r.mould.sum() > mould.sum()
        assert grew == (change == "extend")


def test_identical_renders_count_as_one_mould(mould):
    shifted = np.roll(mould, (2, -1), axis=(0, 1))
    bolder = ndimage.binary_dilation(mould)
    recut = recut_stroke_end(mould, change="shorten", seed=0).mould
    assert identical_moulds([mould, bolder, shifted, recut]) == [[0, 2], [1], [3]]


def test_mould_from_points_fills_an_outline_and_thickens_a_skeleton():
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    ring = np.c_[np.cos(t), np.sin(t)]
    disc = mould_from_points(ring, kind="edge", size=64)
    assert disc[32, 32] and not disc[0, 0]
    line = mould_from_points(np.c_[np.linspace(0, 1, 50), np.zeros(50) + 0.5], kind="skeleton",
                             size=64, stroke=6)
    assert 4 <= line.sum(axis=0)[32] <= 8


@pytest.mark.parametrize(("call", "match"), [
    (lambda m: simulate_impressions(m, 0), "n must be"),
    (lambda m: simulate_impressions(np.zeros((20, 20)), 1), "no ink"),
    (lambda m: simulate_impressions(m[None], 1), "2D binary image"),
    (lambda m: recut_stroke_end(m, change="rotate"), "change must be"),
    (lambda m: recut_stroke_end(m, length=0), "length must be"),
    (lambda m: PrintVariation(ink=-1), "ink must be"),
    (lambda m: PrintVariation(resolution=(2.0, 1.0)), "resolution must be"),
    (lambda m: draw_strokes([[0, 0, 1]]), "shape \\(k, 4\\)"),
    (lambda m: identical_moulds([m], tol=1.5), "tol must be"),
])
def test_bad_input_is_a_value_error(mould, call, match):
    with pytest.raises(ValueError, match=match):
        call(mould)

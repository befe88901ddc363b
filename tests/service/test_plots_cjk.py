"""CJK shape names ("永_song") are drawn with a CJK font in the PNG pictures, not as boxes.

The pictures use DejaVu Sans with a per-glyph fallback list (``service.plots._common``); the
CJK glyphs come from whichever CJK font is installed (Debian: ``fonts-noto-cjk``). Without
one the test is skipped, unless ``REGTREE_REQUIRE_CJK_FONT=1`` (CI installs the font and sets
it), where the absence fails it.
"""

from __future__ import annotations

import io
import os
from typing import Any

import numpy as np
import pytest
from PIL import Image

from service.plots import render_subject, render_tree
from service.plots._common import CJK_FONTS, cjk_font, font_families
from tests.service.test_plots import document_subject

NAMES = ["永_song", "永_kaishu", "東京_mincho", "글자_batang", "字_hei", "model"]


@pytest.fixture(scope="module")
def cjk() -> str:
    """The CJK family the pictures fall back to (skip, or fail when one is required)."""
    found = cjk_font()
    if found is None:
        reason = (
            "no CJK font is installed (apt-get install -y fonts-noto-cjk); "
            f"fallback list: {font_families()}"
        )
        if os.environ.get("REGTREE_REQUIRE_CJK_FONT", "") not in ("", "0"):
            pytest.fail(f"REGTREE_REQUIRE_CJK_FONT is set but {reason}")
        pytest.skip(reason)
    return found


def document() -> dict[str, Any]:
    """A small tree whose names are CJK: the model, two layers and one unattached shape."""

    def subject(sid: int, layer: int | None, parent: int | None, e: float | None):
        return document_subject(sid, NAMES[sid - 1], layer, parent, e, direct_factor=2.0)

    return {
        "job_id": 3,
        "method": "dynamic_tree",
        "root_shape_id": 6,
        "shape_ids": [1, 2, 3, 4, 5, 6],
        "names": NAMES,
        "subjects": [
            subject(1, 2, 6, 0.001),
            subject(2, 2, 6, 0.002),
            subject(3, 3, 1, 0.003),
            subject(4, 3, 2, 0.004),
            subject(5, None, None, None),
        ],
    }


def ink_columns(png: bytes) -> int:
    """Columns of the picture with any dark pixel (a crude measure of how much was drawn)."""
    image = np.asarray(Image.open(io.BytesIO(png)).convert("L"))
    return int((image < 128).any(axis=0).sum())


def test_fallback_list_keeps_dejavu_first_then_installed_cjk(cjk: str) -> None:
    families = font_families()
    assert families[0] == "DejaVu Sans"  # Latin text keeps its look
    assert cjk in families and cjk in CJK_FONTS
    from matplotlib import font_manager

    assert cjk in {f.name for f in font_manager.fontManager.ttflist}


def test_tree_png_draws_cjk_names(cjk: str) -> None:
    rendered = render_tree(document(), fmt="png")
    assert rendered.meta["missing_glyphs"] == "", rendered.meta["missing_glyphs"]
    names = {n["name"] for n in rendered.meta["nodes"]} | {
        u["name"] for u in rendered.meta["unattached"]
    }
    assert names == set(NAMES)
    # the SVG keeps the names as text, with the fallback families named for the browser
    svg = render_tree(document(), fmt="svg")
    assert svg.meta["missing_glyphs"] == ""
    text = svg.data.decode()
    assert "永_song" in text and cjk in text


def test_subject_png_draws_cjk_name_and_path(cjk: str) -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(30, 2))
    subject = {
        "shape_id": 3,
        "name": "東京_mincho",
        "layer": 3,
        "attached": True,
        "parent_shape_id": 1,
        "error": 0.003,
        "reason": "registered from 永_song (layer 2)",
        "warped": (points + 0.01).tolist(),
        "correspondence": list(range(30)),
    }
    rendered = render_subject(subject, points, width=800, method="dynamic tree")
    assert rendered.meta["missing_glyphs"] == "", rendered.meta["missing_glyphs"]
    assert "東京_mincho" in rendered.meta["title"]["text"]
    # a glyph drawn as a box and a glyph drawn properly both leave ink; what tells them apart
    # is matplotlib's report, checked above. Here: the picture is not blank where the title is.
    assert ink_columns(rendered.data) > 100

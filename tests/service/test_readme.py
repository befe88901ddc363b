"""The README's Python snippets, run as written against a real ``regtree serve``.

The client snippet ("From Python") is executed with only its server address replaced by the
test server's, in a folder holding the ``glyphs/`` it names (generated ellipse images), and
so is the snippet that takes points from an image without a server. A renamed client method
or a changed signature fails here before a reader finds it.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image, ImageDraw

from service.client import JobResult, Subject
from tests.service.conftest import Service

README = Path(__file__).resolve().parents[2] / "README.md"
README_URL = "http://127.0.0.1:8000"


def snippet(after: str) -> str:
    """The first ``python`` code block of the README after the line starting with ``after``."""
    text = README.read_text(encoding="utf-8")
    start = text.index(after)
    match = re.search(r"```python\n(.*?)```", text[start:], re.DOTALL)
    assert match is not None, f"no python block after {after!r}"
    return match.group(1)


def write_glyphs(folder: Path) -> None:
    """Six ellipse images of growing width: ``00-root.png`` first, as the README names it."""
    folder.mkdir()
    for k, width in enumerate((40, 48, 56, 64, 72, 80)):
        image = Image.new("L", (120, 90), 255)
        ImageDraw.Draw(image).ellipse((60 - width // 2, 20, 60 + width // 2, 70), fill=0)
        image.save(folder / (f"{k:02d}-root.png" if k == 0 else f"{k:02d}-w{width}.png"))


@pytest.fixture
def in_glyph_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    write_glyphs(tmp_path / "glyphs")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_the_client_snippet_runs_as_written(service: Service, in_glyph_folder: Path) -> None:
    code = snippet("### From Python")
    assert README_URL in code
    for call in ("client.result(", "client.subject(", "client.apply_transform(", "on_progress="):
        assert call in code, call
    namespace: dict[str, Any] = {}
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code.replace(README_URL, service.base_url), "README.md", "exec"), namespace)
    printed = out.getvalue().splitlines()
    # the compact progress line, one per change, ending succeeded; which states a poll
    # (every 0.5 s) lands on depends on the machine's load (a loaded CI run saw "queued",
    # "running", then "succeeded ...", no stage in between), so only their form is checked
    progress = printed[:-3]
    assert all(line.split(" ")[0] in ("queued", "running") for line in progress), printed
    assert all(a != b for a, b in itertools.pairwise(printed[:-2])), printed
    assert printed[-3].startswith("succeeded"), printed
    assert printed[-2] == "5 of 5 attached", printed

    result = namespace["result"]
    assert isinstance(result, JobResult) and len(result.subjects) == 5
    confidences = [s.confidence for s in result.subjects]
    assert confidences == sorted(confidences), confidences  # sort="confidence"
    one = namespace["one"]
    assert isinstance(one, Subject) and one.warped is not None and one.warped.shape[1] == 2
    model = namespace["model"]
    mapped, back = namespace["mapped"], namespace["back"]
    assert mapped.shape == back.shape == (5, 2)
    assert np.isfinite(mapped).all()
    np.testing.assert_allclose(back, model[:5], atol=0.05)  # pixels


def test_the_image_points_snippet_runs_as_written(in_glyph_folder: Path) -> None:
    namespace: dict[str, Any] = {}
    exec(compile(snippet("Points from images without a server"), "README.md", "exec"), namespace)
    points = namespace["pts"]
    assert points.ndim == 2 and points.shape[1] == 2 and 3 <= len(points) <= 300

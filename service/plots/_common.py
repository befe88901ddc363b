"""Shared rendering machinery: an Agg/SVG figure without pyplot, one lock, stable output.

Pictures are built on :class:`matplotlib.figure.Figure` directly (no ``pyplot``, no global
figure registry), and every render holds one module lock, so the functions are safe to call
from a web server's thread pool. SVG text stays text (``svg.fonttype = none``) so names can
be searched and selected, and ids are stable (``svg.hashsalt``) so identical input gives
identical bytes.
"""

from __future__ import annotations

import io
import re
import threading
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal

import matplotlib
from matplotlib import font_manager
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

Format = Literal["png", "svg"]
MEDIA_TYPES: dict[str, str] = {"png": "image/png", "svg": "image/svg+xml"}

# Fonts tried after DejaVu Sans for glyphs it lacks (CJK glyph names are common in archives).
_FALLBACK_FONTS = (
    "Noto Sans CJK JP",
    "Noto Sans CJK SC",
    "Noto Sans CJK TC",
    "Noto Sans CJK KR",
    "Source Han Sans",
    "WenQuanYi Zen Hei",
    "WenQuanYi Micro Hei",
    "Droid Sans Fallback",
    "AR PL UMing CN",
    "Noto Sans",
)

_LOCK = threading.RLock()
_MISSING_GLYPH = re.compile(r"Glyph (\d+) .*missing from")
_families: list[str] | None = None


def _font_families() -> list[str]:
    global _families
    if _families is None:
        installed = {f.name for f in font_manager.fontManager.ttflist}
        _families = ["DejaVu Sans", *[f for f in _FALLBACK_FONTS if f in installed]]
    return _families


@dataclass(frozen=True)
class Rendered:
    """A rendered picture.

    Attributes
    ----------
    data : bytes
        The PNG or SVG file.
    media_type : str
        ``image/png`` or ``image/svg+xml`` (for an HTTP ``Content-Type``).
    width, height : int
        Size in pixels (for SVG, the size it is drawn at by default, 1 px = 1 CSS px).
    meta : dict
        What was drawn, for callers and tests (see each function's documentation).
    """

    data: bytes
    media_type: str
    width: int
    height: int
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def format(self) -> str:
        return "svg" if self.media_type == MEDIA_TYPES["svg"] else "png"


def check_format(fmt: str) -> Format:
    fmt = fmt.lower().lstrip(".")
    if fmt not in MEDIA_TYPES:
        raise ValueError(f"format must be 'png' or 'svg'; got {fmt!r}")
    return fmt  # type: ignore[return-value]


def check_size(width: int, height: int, dpi: float) -> None:
    if not (16 <= width <= 20_000 and 16 <= height <= 20_000):
        raise ValueError(f"picture size {width}x{height} px is outside 16..20000 px")
    if not 10 <= dpi <= 1000:
        raise ValueError(f"dpi {dpi} is outside 10..1000")


@contextmanager
def figure(width: int, height: int, dpi: float) -> Iterator[Figure]:
    """A new figure of exactly ``width`` x ``height`` pixels at ``dpi``, under the lock."""
    check_size(width, height, dpi)
    with _LOCK, matplotlib.rc_context(_rc()):
        fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
        FigureCanvasAgg(fig)
        yield fig


def _rc() -> Any:
    return {
        "svg.fonttype": "none",
        "svg.hashsalt": "regtree",
        "font.family": "sans-serif",
        "font.sans-serif": _font_families(),
        "axes.titlesize": "medium",
        "path.simplify": False,
    }


def save(fig: Figure, fmt: Format, meta: Mapping[str, Any] | None = None) -> Rendered:
    """Render ``fig`` (inside :func:`figure`) to bytes."""
    buffer = io.BytesIO()
    dpi = fig.dpi
    with warnings.catch_warnings(record=True) as caught:
        # a glyph missing from every font is drawn as a box: report it in meta, not in logs
        warnings.simplefilter("always")
        if fmt == "png":
            fig.savefig(buffer, format="png", dpi=dpi, metadata={"Software": "regtree"})
        else:
            fig.savefig(
                buffer, format="svg", dpi=dpi, metadata={"Date": None, "Creator": "regtree"}
            )
    missing: set[str] = set()
    for w in caught:
        found = _MISSING_GLYPH.search(str(w.message))
        if found:
            missing.add(chr(int(found.group(1))))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    out = dict(meta or {})
    out["missing_glyphs"] = "".join(sorted(missing))
    width = round(fig.get_figwidth() * dpi)
    height = round(fig.get_figheight() * dpi)
    return Rendered(buffer.getvalue(), MEDIA_TYPES[fmt], width, height, out)


def data_to_pixel(fig: Figure, ax: Axes) -> list[list[float]]:
    """The affine map from ``ax``'s data coordinates to PNG pixels (column, row from the top):
    ``[[a, 0, b], [0, c, d]]`` with ``col = a x + b``, ``row = c y + d``. Call after a draw."""
    height = fig.get_figheight() * fig.dpi
    (x0, y0), (x1, y1) = ax.transData.transform([(0.0, 0.0), (1.0, 1.0)])
    return [[float(x1 - x0), 0.0, float(x0)], [0.0, float(-(y1 - y0)), float(height - y0)]]


def axes_box_pixels(fig: Figure, ax: Axes) -> list[float]:
    """``[col0, row0, col1, row1]`` of the axes' box in PNG pixels (row 0 at the top)."""
    height = fig.get_figheight() * fig.dpi
    bbox = ax.get_window_extent()
    return [float(bbox.x0), float(height - bbox.y1), float(bbox.x1), float(height - bbox.y0)]


METHOD_LABELS = {
    "dynamic_tree": "dynamic tree",
    "static_tree": "static tree",
    "direct": "direct CPD",
}


def method_label(result: Mapping[str, Any]) -> str:
    method = str(result.get("method") or "tree")
    return METHOD_LABELS.get(method, method.replace("_", " "))


def shorten(text: str, limit: int = 40) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def fmt_e(value: float | None) -> str:
    if value is None:
        return "n/a"
    return f"{value:.3g}"

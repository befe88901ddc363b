"""Shared rendering machinery: an Agg/SVG figure without pyplot, one lock, stable output.

Pictures are built on :class:`matplotlib.figure.Figure` directly (no ``pyplot``, no global
figure registry), and every render holds one module lock, so the functions are safe to call
from a web server's thread pool. SVG text stays text (``svg.fonttype = none``) so names can
be searched and selected, and ids are stable (``svg.hashsalt``) so identical input gives
identical bytes.
"""

from __future__ import annotations

import io
import os
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
from matplotlib.font_manager import FontProperties

Format = Literal["png", "svg"]
MEDIA_TYPES: dict[str, str] = {"png": "image/png", "svg": "image/svg+xml"}

# Fonts tried, glyph by glyph, after DejaVu Sans (which draws Latin, Greek and Cyrillic) for
# the glyphs it lacks: shape names in archives are often CJK ("永_song"). Matplotlib >= 3.6
# falls back per glyph along ``font.sans-serif``; only installed families are listed there.
# Chinese forms first (glyph archives are mostly Chinese), then Japanese and Korean; Debian:
# fonts-noto-cjk, fonts-wqy-zenhei, fonts-wqy-microhei, fonts-arphic-uming, fonts-droid-fallback.
_FALLBACK_FONTS = (
    "Noto Sans CJK SC",
    "Noto Sans CJK TC",
    "Noto Sans CJK HK",
    "Noto Sans CJK JP",
    "Noto Sans CJK KR",
    "Source Han Sans SC",
    "Source Han Sans CN",
    "Source Han Sans",
    "Noto Serif CJK SC",
    "Noto Serif CJK TC",
    "Noto Serif CJK JP",
    "Noto Serif CJK KR",
    "Source Han Serif",
    "WenQuanYi Zen Hei",
    "WenQuanYi Micro Hei",
    "Droid Sans Fallback",
    "AR PL UMing CN",
    "AR PL UKai CN",
    "IPAexGothic",
    "IPAGothic",
    "TakaoPGothic",
    "NanumGothic",
    "Noto Sans",
    "Unifont",
)
#: The subset of :data:`_FALLBACK_FONTS` that draws CJK ideographs.
CJK_FONTS = frozenset(_FALLBACK_FONTS) - {"Noto Sans", "Unifont"}

_LOCK = threading.RLock()
_MISSING_GLYPH = re.compile(r"Glyph (\d+) .*missing from")
_families: list[str] | None = None


def _installed_names() -> set[str]:
    return {f.name for f in font_manager.fontManager.ttflist}


def _add_new_system_fonts() -> int:
    """Add to matplotlib's font manager the system fonts it does not know yet; return how many
    files were added.

    Matplotlib lists the system fonts once, into a cache file (``fontlist-*.json`` in its cache
    directory), and trusts that file afterwards: a font installed later (``apt-get install
    fonts-noto-cjk`` after the first plot on the machine) stays unknown to it. Adding the new
    files to the running font manager is cheaper than rebuilding it and keeps every reference
    to it (``font_manager.findfont`` is bound to the instance) valid.
    """
    manager = font_manager.fontManager
    known = {os.path.realpath(f.fname) for f in manager.ttflist}
    added = 0
    for path in font_manager.findSystemFonts():
        if os.path.realpath(path) in known:
            continue
        try:
            manager.addfont(path)
        except Exception:  # an unreadable or unsupported file: skip it
            continue
        known.add(os.path.realpath(path))
        added += 1
    return added


def font_families(refresh: bool = False) -> list[str]:
    """The font families the pictures use, in order: DejaVu Sans, then the installed fallbacks
    (one family per font file: the SC, TC, JP and KR families of Noto Sans CJK share one).

    It is ``font.family`` itself, not only ``font.sans-serif``: matplotlib falls back glyph by
    glyph along the families of a text's ``font.family``, and ``"sans-serif"`` alone resolves
    to one font.

    Worked out once per process. When matplotlib knows no CJK font, the system's fonts are
    looked at again (see :func:`_add_new_system_fonts`), so that a CJK font installed after
    matplotlib built its cache is used. ``refresh=True`` works it out anew.
    """
    global _families
    with _LOCK:
        if _families is None or refresh:
            installed = _installed_names()
            if not installed & CJK_FONTS and _add_new_system_fonts():
                installed = _installed_names()
            _families = ["DejaVu Sans"]
            files = {_font_file("DejaVu Sans")}
            for family in _FALLBACK_FONTS:
                path = _font_file(family) if family in installed else None
                if path is not None and path not in files:  # one family per font file
                    files.add(path)
                    _families.append(family)
        return list(_families)


def _font_file(family: str) -> str | None:
    try:
        path = font_manager.findfont(FontProperties(family=family), fallback_to_default=False)
    except ValueError:
        return None
    return os.path.realpath(path)


def cjk_font() -> str | None:
    """The first CJK family the pictures fall back to, or None when none is installed."""
    return next((f for f in font_families() if f in CJK_FONTS), None)


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
        "font.family": font_families(),
        "font.sans-serif": font_families(),
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


# --- fitting text into a width ---------------------------------------------------------------

_BREAK_AFTER = "_-/.,;:)]"


@dataclass(frozen=True)
class Fitted:
    """Text fitted to a width: ``text`` (lines joined by newlines), ``fontsize`` in points,
    ``lines``, ``width_px`` (of the widest line, as measured) and whether it was ``cut``."""

    text: str
    fontsize: float
    lines: int
    width_px: float
    cut: bool


def text_width_px(fig: Figure, text: str, fontsize: float, weight: str = "normal") -> float:
    """Width in pixels of one line of ``text`` drawn in ``fig`` (inside :func:`figure`)."""
    if not text:
        return 0.0
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    prop = FontProperties(size=fontsize, weight=weight)
    width, _, _ = renderer.get_text_width_height_descent(text, prop, ismath=False)
    return float(width)


def line_height_px(fontsize: float, dpi: float, lines: int = 1) -> float:
    """Height of ``lines`` lines of text (matplotlib's 1.2 line spacing)."""
    return 1.2 * fontsize * dpi / 72.0 * max(lines, 1)


def _split_word(fig: Figure, word: str, max_px: float, size: float, weight: str) -> list[str]:
    """A word too wide for a line, in pieces that fit, broken after punctuation if possible."""
    pieces: list[str] = []
    rest = word
    while rest and text_width_px(fig, rest, size, weight) > max_px:
        lo, hi = 1, len(rest)  # longest prefix that fits (at least one character)
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if text_width_px(fig, rest[:mid], size, weight) <= max_px:
                lo = mid
            else:
                hi = mid - 1
        cut = lo
        soft = max((rest.rfind(c, 0, lo) for c in _BREAK_AFTER), default=-1)
        if soft + 1 >= max(lo // 2, 1):
            cut = soft + 1
        pieces.append(rest[:cut])
        rest = rest[cut:]
    if rest:
        pieces.append(rest)
    return pieces


def _wrap(fig: Figure, text: str, max_px: float, size: float, weight: str) -> list[str]:
    lines: list[str] = []
    current = ""
    for word in text.split():
        trial = f"{current} {word}" if current else word
        if text_width_px(fig, trial, size, weight) <= max_px:
            current = trial
            continue
        if current:
            lines.append(current)
        pieces = _split_word(fig, word, max_px, size, weight)
        lines.extend(pieces[:-1])
        current = pieces[-1] if pieces else ""
    if current:
        lines.append(current)
    return lines or [""]


def _ellipsize(fig: Figure, line: str, max_px: float, size: float, weight: str) -> str:
    while line and text_width_px(fig, line + "…", size, weight) > max_px:
        line = line[:-1]
    return line.rstrip() + "…"


def fit_text(
    fig: Figure,
    text: str,
    max_px: float,
    fontsize: float,
    *,
    min_fontsize: float = 7.0,
    max_lines: int = 2,
    weight: str = "normal",
) -> Fitted:
    """Fit ``text`` into ``max_px`` pixels of width (inside :func:`figure`).

    On one line if it fits at ``fontsize`` or a little smaller (down to 85 %); else wrapped
    (between words, or inside a long word after punctuation) into at most ``max_lines``
    lines at the largest size from ``fontsize`` down to ``min_fontsize`` that needs no more;
    else ``max_lines`` lines at ``min_fontsize``, the last ending in "…".
    """
    text = " ".join(text.split())
    max_px = max(max_px, 1.0)
    steps = [fontsize - 0.5 * k for k in range(int((fontsize - min_fontsize) / 0.5) + 1)]
    steps = steps or [fontsize]

    def fitted(lines: list[str], size: float, cut: bool) -> Fitted:
        width = max(text_width_px(fig, line, size, weight) for line in lines)
        return Fitted("\n".join(lines), size, len(lines), width, cut)

    for size in steps:
        if size < 0.85 * fontsize:
            break
        if text_width_px(fig, text, size, weight) <= max_px:
            return fitted([text], size, False)
    for size in steps:
        lines = _wrap(fig, text, max_px, size, weight)
        if len(lines) <= max_lines:
            return fitted(lines, size, False)
    size = steps[-1]
    lines = _wrap(fig, text, max_px, size, weight)[:max_lines]
    lines[-1] = _ellipsize(fig, lines[-1], max_px, size, weight)
    return fitted(lines, size, True)


def text_box_pixels(fig: Figure, artist: Any) -> list[float]:
    """``[col0, row0, col1, row1]`` of a drawn text artist in PNG pixels. Call after a draw."""
    height = fig.get_figheight() * fig.dpi
    bbox = artist.get_window_extent(fig.canvas.get_renderer())  # type: ignore[attr-defined]
    return [float(bbox.x0), float(height - bbox.y1), float(bbox.x1), float(height - bbox.y0)]

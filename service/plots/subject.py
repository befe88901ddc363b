"""One subject: its points, the model warped onto it, and correspondence lines; beside direct
CPD's registration of the same subject when the job compared with it."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.lines import Line2D
from numpy.typing import ArrayLike, NDArray

from service.plots import _doc
from service.plots._common import (
    METHOD_LABELS,
    Rendered,
    axes_box_pixels,
    check_format,
    data_to_pixel,
    figure,
    fit_text,
    fmt_e,
    line_height_px,
    save,
    shorten,
    text_box_pixels,
    text_width_px,
)

SUBJECT_COLOUR = "#555555"
WARPED_COLOUR = "#d62728"
LINE_COLOUR = "#2ca02c"
COLOURS = {"subject": SUBJECT_COLOUR, "warped": WARPED_COLOUR, "lines": LINE_COLOUR}

_BOTTOM_PX, _SIDE_PX, _GAP_PX = 58, 44, 40
_LEGEND_PT = 8.5


def _points(value: Any) -> NDArray[np.float64] | None:
    if value is None:
        return None
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"points must have shape (n, 2); got {arr.shape}")
    return arr


def _panels(subject: Mapping[str, Any], method: str) -> list[dict[str, Any]]:
    panels: list[dict[str, Any]] = []
    warped = _points(subject.get("warped"))
    confidence = _doc.confidence(subject)
    leaf = _doc.is_leaf(subject)
    if warped is not None:
        layer = subject.get("layer")
        title = (
            f"{method}: layer {layer if layer is not None else '?'}, "
            f"e = {fmt_e(subject.get('error'))}"
        )
        if confidence is not None:
            title += f", confidence {confidence:.2f}"
        if leaf:
            # its reason starts "low-confidence leaf: ..."
            reason = str(subject.get("reason") or "low-confidence leaf")
            title += f" — {shorten(reason, 300)}"
        panels.append(
            {
                "name": "tree",
                "label": method,
                "warped": warped,
                "correspondence": subject.get("correspondence"),
                "error": subject.get("error"),
                "layer": layer,
                "leaf": leaf,
                "confidence": confidence,
                "title": title,
            }
        )
    else:
        reason = str(subject.get("reason") or "not attached")
        panels.append(
            {
                "name": "subject",
                "label": "unattached",
                "warped": None,
                "correspondence": None,
                "error": None,
                "layer": None,
                "leaf": False,
                "confidence": confidence,
                "title": f"unattached: {shorten(reason, 300)}",
            }
        )
    direct = subject.get("direct")
    if isinstance(direct, Mapping) and _points(direct.get("warped")) is not None:
        panels.append(
            {
                "name": "direct",
                "label": "direct CPD",
                "warped": _points(direct.get("warped")),
                "correspondence": direct.get("correspondence"),
                "error": direct.get("error"),
                "layer": None,
                "leaf": False,
                "confidence": None,
                "title": f"direct CPD from the model: e = {fmt_e(direct.get('error'))}",
            }
        )
    return panels


def _sample(n: int, k: int) -> NDArray[np.intp]:
    if k <= 0 or n == 0:
        return np.zeros(0, dtype=np.intp)
    if k >= n:
        return np.arange(n, dtype=np.intp)
    return np.unique(np.linspace(0, n - 1, k).round().astype(np.intp))


def _draw_panel(
    ax: Axes,
    panel: dict[str, Any],
    subject_points: NDArray[np.float64],
    n_lines: int,
    marker: float,
    warnings: list[str],
) -> int:
    ax.scatter(
        subject_points[:, 0],
        subject_points[:, 1],
        s=marker,
        color=SUBJECT_COLOUR,
        linewidths=0,
        zorder=2,
        label="subject",
    )
    warped = panel["warped"]
    drawn = 0
    if warped is None:
        return drawn
    corr = panel["correspondence"]
    if corr is not None and n_lines > 0:
        idx = np.asarray(corr, dtype=np.intp)
        if idx.shape != (warped.shape[0],):
            warnings.append(
                f"{panel['name']}: {idx.shape[0]} correspondences for {warped.shape[0]} "
                "warped points; no lines drawn"
            )
        elif idx.size and (idx.min() < 0 or idx.max() >= subject_points.shape[0]):
            warnings.append(
                f"{panel['name']}: correspondence indices outside the subject's "
                f"{subject_points.shape[0]} points (are these the subject's stored points?); "
                "no lines drawn"
            )
        else:
            chosen = _sample(warped.shape[0], n_lines)
            segments = np.stack([warped[chosen], subject_points[idx[chosen]]], axis=1)
            xs = np.column_stack([segments[:, :, 0], np.full(len(chosen), np.nan)]).ravel()
            ys = np.column_stack([segments[:, :, 1], np.full(len(chosen), np.nan)]).ravel()
            ax.plot(xs, ys, color=LINE_COLOUR, lw=0.9, alpha=0.8, zorder=1)
            drawn = len(chosen)
    ax.scatter(
        warped[:, 0],
        warped[:, 1],
        s=marker * 0.45,
        color=WARPED_COLOUR,
        linewidths=0,
        zorder=3,
    )
    return drawn


def render_subject(
    subject: Mapping[str, Any],
    subject_points: ArrayLike,
    *,
    fmt: str = "png",
    width: int = 1200,
    height: int | None = None,
    dpi: float = 100.0,
    y_down: bool = True,
    n_lines: int = 40,
    method: str = "tree",
    title: str | None = None,
) -> Rendered:
    """Draw a subject with the model warped onto it.

    Parameters
    ----------
    subject : mapping
        The subject's entry with its points: ``GET /v1/jobs/{id}/result/subjects/{shape_id}``
        or one item of ``GET /v1/jobs/{id}/result?full=true`` (``warped``, ``correspondence``,
        and ``direct`` when the job compared with direct CPD).
    subject_points : (n, 2) array
        The subject shape's stored points (``GET /v1/collections/{c}/shapes/{shape_id}``),
        in the order the correspondences index.
    width, height : int
        Pixels; by default the height follows the shape's aspect ratio.
    y_down : bool
        Draw y growing downwards, as in images (default, for pixel-coordinate glyph data).
    n_lines : int
        Correspondence lines drawn per panel, for an evenly spread sample of model points:
        each joins a warped model point to the subject point it corresponds to.
    method : str
        The job's method (``dynamic_tree``, ``static_tree``, ``direct``) or any label, for
        the first panel's title.

    One panel for the tree registration, titled with its layer, e and confidence (and, for a
    low-confidence leaf, its reason), or, for an unattached subject, the subject alone
    with the reason; and beside it, with the same axes limits, direct CPD's registration when
    the subject has a ``direct`` entry. Subject points are grey, the warped model red, the
    correspondence lines green (``COLOURS``); equal aspect, the user's own coordinates.

    ``meta``: ``panels`` (per panel ``name`` — "tree", "subject" or "direct" —, ``error``,
    ``leaf``, ``confidence`` (None for direct), ``lines``, ``data_to_pixel``
    ``[[a, 0, b], [0, c, d]]`` mapping a point to PNG pixel column ``a x + b`` and row
    ``c y + d``, ``bbox_px`` of the axes, ``slot_px`` of the
    room the panel was given, and ``title``), ``title`` (the picture's), ``colours``,
    ``y_down``, ``warnings``. A ``title`` is ``text`` (lines joined by newlines),
    ``fontsize``, ``lines``, ``cut`` (ends in "…") and ``bbox_px``; all boxes are
    ``[col0, row0, col1, row1]`` in PNG pixels.

    Titles are fitted to their room: a little smaller on one line, else wrapped (up to four
    lines for a panel, two for the picture), and cut with "…" only if still too long.
    """
    fmt_ = check_format(fmt)
    points = _points(subject_points)
    if points is None:
        raise ValueError("subject_points is empty")
    panels = _panels(subject, METHOD_LABELS.get(method, method))
    warnings: list[str] = []

    everything = [points] + [p["warped"] for p in panels if p["warped"] is not None]
    stacked = np.concatenate(everything)
    lo, hi = stacked.min(axis=0), stacked.max(axis=0)
    span = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-9))
    pad = 0.05 * span
    xlim = (lo[0] - pad, hi[0] + pad)
    ylim = (lo[1] - pad, hi[1] + pad)

    n_max = max(len(p) for p in everything)
    marker = float(np.clip(2500.0 / n_max, 2.0, 30.0))

    k = len(panels)
    panel_w = (width - 2 * _SIDE_PX - (k - 1) * _GAP_PX) / k
    name = str(subject.get("name", ""))
    sid = subject.get("shape_id")
    heading = title or (f"{shorten(name, 120)} (shape {sid})" if sid is not None else name)
    # provisional height: titles are fitted to widths, then the height is settled
    with figure(width, height or 600, dpi) as fig:
        # a title may use its panel's width and half of each gap beside it
        title_px = panel_w + _GAP_PX - 8
        titles = [
            fit_text(fig, p["title"], title_px, 9.5, min_fontsize=7.5, max_lines=4) for p in panels
        ]
        # side by side panels read alike: one size for their titles
        size = min(t.fontsize for t in titles)
        titles = [
            fit_text(fig, p["title"], title_px, size, min_fontsize=size, max_lines=4)
            for p in panels
        ]
        head = fit_text(fig, heading, width - 24, 12.0, min_fontsize=9.0, max_lines=2)
        legend_labels = ["subject points"]
        if any(p["warped"] is not None for p in panels):
            legend_labels.append("model warped onto it")
        if n_lines > 0 and any(
            p["warped"] is not None and p["correspondence"] is not None for p in panels
        ):
            legend_labels.append(f"correspondences ({n_lines} sampled)")
        entry_px = [
            text_width_px(fig, label, _LEGEND_PT) + 4.0 * _LEGEND_PT * dpi / 72
            for label in legend_labels
        ]
        legend_cols = len(entry_px)
        while legend_cols > 1 and sum(entry_px[:legend_cols]) > width - 16:
            legend_cols -= 1
        legend_rows = math.ceil(len(entry_px) / legend_cols)

        title_h = max(line_height_px(t.fontsize, dpi, t.lines) for t in titles)
        top_px = 10 + line_height_px(head.fontsize, dpi, head.lines) + 12 + title_h + 10
        bottom_px = _BOTTOM_PX + line_height_px(_LEGEND_PT, dpi, legend_rows - 1) * 1.4
        if height is None:
            aspect = (ylim[1] - ylim[0]) / (xlim[1] - xlim[0])
            height = int(top_px + bottom_px + np.clip(panel_w * aspect, 160, 1200))
            fig.set_size_inches(width / dpi, height / dpi)
        panel_h = max(height - top_px - bottom_px, 20.0)
        axes: list[Axes] = []
        lines: list[int] = []
        title_artists = []
        for i, panel in enumerate(panels):
            left = _SIDE_PX + i * (panel_w + _GAP_PX)
            ax = fig.add_axes((left / width, bottom_px / height, panel_w / width, panel_h / height))
            ax.set_gid(f"panel-{panel['name']}")
            lines.append(_draw_panel(ax, panel, points, n_lines, marker, warnings))
            ax.set_xlim(*xlim)
            ax.set_ylim(*(ylim[::-1] if y_down else ylim))
            ax.set_aspect("equal", adjustable="box", anchor="C")
            ax.tick_params(labelsize=7, colors="#666666")
            title_artists.append(
                ax.set_title(
                    titles[i].text,
                    fontsize=titles[i].fontsize,
                    linespacing=1.2,
                    parse_math=False,
                )
            )
            axes.append(ax)

        suptitle = fig.suptitle(
            head.text,
            y=1 - 10 / height,
            va="top",
            fontsize=head.fontsize,
            linespacing=1.2,
            parse_math=False,
        )
        handles = [
            Line2D([], [], ls="", marker="o", color=SUBJECT_COLOUR, label="subject points"),
        ]
        if len(legend_labels) > 1:
            handles.append(
                Line2D([], [], ls="", marker="o", color=WARPED_COLOUR, label=legend_labels[1])
            )
        if any(lines):
            handles.append(
                Line2D([], [], color=LINE_COLOUR, label=f"correspondences ({max(lines)} sampled)")
            )
        fig.legend(
            handles=handles,
            loc="lower center",
            ncols=min(legend_cols, len(handles)),
            frameon=False,
            fontsize=_LEGEND_PT,
            bbox_to_anchor=(0.5, 2 / height),
        )
        fig.canvas.draw()
        meta: dict[str, Any] = {
            "panels": [
                {
                    "name": panel["name"],
                    "error": panel["error"],
                    "leaf": panel["leaf"],
                    "confidence": panel["confidence"],
                    "lines": n,
                    "data_to_pixel": data_to_pixel(fig, ax),
                    "bbox_px": axes_box_pixels(fig, ax),
                    "slot_px": [
                        _SIDE_PX + i * (panel_w + _GAP_PX),
                        top_px,
                        _SIDE_PX + i * (panel_w + _GAP_PX) + panel_w,
                        height - bottom_px,
                    ],
                    "title": {
                        "text": titles[i].text,
                        "fontsize": titles[i].fontsize,
                        "lines": titles[i].lines,
                        "cut": titles[i].cut,
                        "bbox_px": text_box_pixels(fig, title_artists[i]),
                    },
                }
                for i, (panel, ax, n) in enumerate(zip(panels, axes, lines, strict=True))
            ],
            "title": {
                "text": head.text,
                "fontsize": head.fontsize,
                "lines": head.lines,
                "cut": head.cut,
                "bbox_px": text_box_pixels(fig, suptitle),
            },
            "colours": dict(COLOURS),
            "y_down": y_down,
            "warnings": warnings,
        }
        return save(fig, fmt_, meta)

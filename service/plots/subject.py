"""One subject: its points, the model warped onto it, and correspondence lines; beside direct
CPD's registration of the same subject when the job compared with it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.lines import Line2D
from numpy.typing import ArrayLike, NDArray

from service.plots._common import (
    METHOD_LABELS,
    Rendered,
    axes_box_pixels,
    check_format,
    data_to_pixel,
    figure,
    fmt_e,
    save,
    shorten,
)

SUBJECT_COLOUR = "#555555"
WARPED_COLOUR = "#d62728"
LINE_COLOUR = "#2ca02c"
COLOURS = {"subject": SUBJECT_COLOUR, "warped": WARPED_COLOUR, "lines": LINE_COLOUR}

_TOP_PX, _BOTTOM_PX, _SIDE_PX, _GAP_PX = 64, 58, 44, 40


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
    if warped is not None:
        layer = subject.get("layer")
        panels.append(
            {
                "name": "tree",
                "label": method,
                "warped": warped,
                "correspondence": subject.get("correspondence"),
                "error": subject.get("error"),
                "layer": layer,
                "title": f"{method}: layer {layer if layer is not None else '?'}, "
                f"e = {fmt_e(subject.get('error'))}",
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
                "title": f"unattached: {shorten(reason, 70)}",
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

    One panel for the tree registration (or, for an unattached subject, the subject alone
    with the reason), and beside it, with the same axes limits, direct CPD's registration when
    the subject has a ``direct`` entry. Subject points are grey, the warped model red, the
    correspondence lines green (``COLOURS``); equal aspect, the user's own coordinates.

    ``meta``: ``panels`` (per panel ``name`` — "tree", "subject" or "direct" —, ``error``,
    ``lines``, ``data_to_pixel`` ``[[a, 0, b], [0, c, d]]`` mapping a point to PNG pixel
    column ``a x + b`` and row ``c y + d``, and ``bbox_px``), ``colours``, ``y_down``,
    ``warnings``.
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
    if height is None:
        aspect = (ylim[1] - ylim[0]) / (xlim[1] - xlim[0])
        height = int(_TOP_PX + _BOTTOM_PX + np.clip(panel_w * aspect, 240, 1200))
    with figure(width, height, dpi) as fig:
        panel_h = height - _TOP_PX - _BOTTOM_PX
        axes: list[Axes] = []
        lines: list[int] = []
        for i, panel in enumerate(panels):
            left = _SIDE_PX + i * (panel_w + _GAP_PX)
            ax = fig.add_axes(
                (left / width, _BOTTOM_PX / height, panel_w / width, panel_h / height)
            )
            ax.set_gid(f"panel-{panel['name']}")
            lines.append(_draw_panel(ax, panel, points, n_lines, marker, warnings))
            ax.set_xlim(*xlim)
            ax.set_ylim(*(ylim[::-1] if y_down else ylim))
            ax.set_aspect("equal", adjustable="box", anchor="C")
            ax.tick_params(labelsize=7, colors="#666666")
            ax.set_title(panel["title"], fontsize=9.5)
            axes.append(ax)

        name = str(subject.get("name", ""))
        sid = subject.get("shape_id")
        fig.suptitle(
            title or (f"{shorten(name, 60)} (shape {sid})" if sid is not None else name),
            y=1 - 10 / height,
            va="top",
            fontsize=12,
        )
        handles = [
            Line2D([], [], ls="", marker="o", color=SUBJECT_COLOUR, label="subject points"),
            Line2D([], [], ls="", marker="o", color=WARPED_COLOUR, label="model warped onto it"),
        ]
        if any(lines):
            handles.append(
                Line2D([], [], color=LINE_COLOUR, label=f"correspondences ({max(lines)} sampled)")
            )
        fig.legend(
            handles=handles,
            loc="lower center",
            ncols=len(handles),
            frameon=False,
            fontsize=8.5,
            bbox_to_anchor=(0.5, 2 / height),
        )
        fig.canvas.draw()
        meta: dict[str, Any] = {
            "panels": [
                {
                    "name": panel["name"],
                    "error": panel["error"],
                    "lines": n,
                    "data_to_pixel": data_to_pixel(fig, ax),
                    "bbox_px": axes_box_pixels(fig, ax),
                }
                for panel, ax, n in zip(panels, axes, lines, strict=True)
            ],
            "colours": dict(COLOURS),
            "y_down": y_down,
            "warnings": warnings,
        }
        return save(fig, fmt_, meta)

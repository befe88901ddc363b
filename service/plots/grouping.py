"""Pictures of a grouping job (issue 11), from its grouping document
(``GET /v1/jobs/{id}/groups``) and the shapes' points.

* :func:`render_gallery` — the groups, one row each: the representative (framed) and its
  members, each labelled with its confidence;
* :func:`render_dendrogram` — the average-linkage tree with the cut, leaves coloured by group;
* :func:`render_instance` — an instance aligned onto its group's representative, with the
  local outline difference as a heat map and its largest value circled.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.patches import Circle
from numpy.typing import NDArray

from service.plots._common import Rendered, check_format, figure, save, shorten

__all__ = ["render_dendrogram", "render_gallery", "render_instance"]

FloatArray = NDArray[np.float64]

PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
           "#7f7f7f", "#bcbd22", "#17becf"]
REP_COLOUR = "#d62728"
_THUMB_PX, _LABEL_PX, _TITLE_PX = 84, 150, 36
MAX_ROWS, MAX_COLUMNS = 60, 10


def group_colour(label: int) -> str:
    return PALETTE[label % len(PALETTE)]


def _thumb(ax: Any, points: FloatArray, colour: str, y_down: bool) -> None:
    ax.scatter(points[:, 0], points[:, 1], s=0.6, c=colour, linewidths=0)
    ax.set_aspect("equal", adjustable="datalim")
    if y_down:
        ax.invert_yaxis()
    ax.set_xticks([])
    ax.set_yticks([])


def render_gallery(
    doc: Mapping[str, Any],
    points: Mapping[int, FloatArray],
    *,
    fmt: str = "png",
    width: int | None = None,
    dpi: float = 100.0,
    y_down: bool = True,
) -> Rendered:
    """The groups as rows of thumbnails (at most 60 rows of 10: the largest groups, then
    a note of how many were left out); shapes missing from `points` (deleted) are drawn
    as an empty framed cell. ``meta``: ``rows``, ``groups_left_out``, ``drawn`` (shape
    ids)."""
    fmt_ = check_format(fmt)
    groups = list(doc.get("groups") or [])
    conf = {int(i["shape_id"]): float(i["confidence"]) for i in doc.get("instances") or []}
    rows = groups[:MAX_ROWS]
    columns = min(MAX_COLUMNS, max((int(g["size"]) for g in rows), default=1))
    w = width or (_LABEL_PX + columns * _THUMB_PX + 20)
    h = _TITLE_PX + max(len(rows), 1) * _THUMB_PX + 10
    drawn: list[int] = []
    with figure(w, h, dpi) as fig:
        fig.text(0.01, 1 - 12 / h, f"{doc.get('n_groups', len(groups))} groups of "
                 f"{len(doc.get('shape_ids') or [])} shapes (threshold "
                 f"{float(doc.get('threshold', 0)):.3g})", fontsize=10, va="top")
        cell_w = (w - _LABEL_PX - 20) / columns
        for r, g in enumerate(rows):
            top = h - _TITLE_PX - r * _THUMB_PX
            label = int(g["label"])
            fig.text(8 / w, (top - _THUMB_PX / 2) / h,
                     f"group {label}\n{g['size']} shape(s)\nspread {float(g['spread']):.3f}",
                     fontsize=8, va="center", color=group_colour(label))
            rep = int(g["representative_shape_id"])
            members = [rep] + [int(s) for s in g["shape_ids"] if int(s) != rep]
            for c, sid in enumerate(members[:columns]):
                left = _LABEL_PX + c * cell_w
                ax = fig.add_axes((left / w, (top - _THUMB_PX + 14) / h,
                                   (cell_w - 6) / w, (_THUMB_PX - 18) / h))
                pts = points.get(sid)
                if pts is not None and len(pts):
                    _thumb(ax, pts, group_colour(label), y_down)
                    drawn.append(sid)
                else:
                    ax.set_xticks([])
                    ax.set_yticks([])
                for spine in ax.spines.values():
                    spine.set_color(REP_COLOUR if sid == rep else "#cccccc")
                    spine.set_linewidth(2.0 if sid == rep else 0.8)
                ax.set_title(f"{sid} · {conf.get(sid, 0.0):.2f}", fontsize=6.5, pad=1)
        if len(groups) > len(rows):
            fig.text(0.5, 2 / h, f"{len(groups) - len(rows)} smaller groups not drawn",
                     fontsize=8, ha="center", va="bottom")
        meta = {"rows": len(rows), "groups_left_out": len(groups) - len(rows),
                "drawn": drawn}
        return save(fig, fmt_, meta)


def render_dendrogram(
    doc: Mapping[str, Any],
    *,
    fmt: str = "png",
    width: int | None = None,
    height: int = 480,
    dpi: float = 100.0,
) -> Rendered:
    """The average-linkage tree: leaves (shape names, coloured by group) along x, merge
    distance up, the cut as a dashed line. ``meta``: ``leaves`` (shape ids, left to
    right), ``threshold``."""
    from scipy.cluster.hierarchy import dendrogram

    fmt_ = check_format(fmt)
    ids = [int(s) for s in doc.get("shape_ids") or []]
    names = list(doc.get("names") or [str(s) for s in ids])
    labels = {int(i["shape_id"]): int(i["label"]) for i in doc.get("instances") or []}
    n = len(ids)
    w = width or int(np.clip(120 + 14 * n, 500, 4000))
    thr = float(doc.get("threshold", 0.0))
    with figure(w, height, dpi) as fig:
        ax = fig.add_axes((70 / w, 110 / height, 1 - 90 / w, 1 - 150 / height))
        leaves: list[int] = []
        if n >= 2 and doc.get("linkage"):
            Z = np.asarray(doc["linkage"], dtype=np.float64)
            tree = dendrogram(Z, no_plot=True)
            for xs, ys in zip(tree["icoord"], tree["dcoord"], strict=True):
                ax.plot(xs, ys, color="#444444", linewidth=0.8)
            leaves = [ids[k] for k in tree["leaves"]]
            ax.set_xticks([5 + 10 * k for k in range(n)])
            ax.set_xticklabels([shorten(names[ids.index(s)], 16) for s in leaves],
                               rotation=90, fontsize=7)
            for tick, sid in zip(ax.get_xticklabels(), leaves, strict=True):
                tick.set_color(group_colour(labels.get(sid, 0)))
            ax.set_xlim(0, 10 * n)
        ax.axhline(thr, color=REP_COLOUR, linestyle="--", linewidth=1)
        ax.text(1, thr, f" cut {thr:.3g}", color=REP_COLOUR, fontsize=8, va="bottom",
                ha="left", transform=ax.get_yaxis_transform())
        ax.set_ylabel("mould distance (RMS radius)")
        ax.set_title(f"{doc.get('n_groups', '?')} groups of {n} shapes (average linkage)",
                     fontsize=10)
        return save(fig, fmt_, {"leaves": leaves, "threshold": thr})


def render_instance(
    instance: Mapping[str, Any],
    instance_points: FloatArray,
    representative_points: FloatArray,
    *,
    fmt: str = "png",
    width: int = 900,
    height: int = 460,
    dpi: float = 100.0,
    y_down: bool = True,
) -> Rendered:
    """Left: the instance (blue) aligned onto its group's representative (grey). Right:
    the local outline difference (ink discounted) with its largest value circled.
    ``meta``: ``distance``, ``ink_offset``, ``worst`` (x, y in the representative's
    normalised frame)."""
    from registration import compare_instances

    fmt_ = check_format(fmt)
    cmp = compare_instances(instance_points, representative_points)
    half = float(cmp.grid[-1] + (cmp.grid[1] - cmp.grid[0]) / 2)
    with figure(width, height, dpi) as fig:
        axes = [fig.add_axes((0.04, 0.08, 0.44, 0.78)), fig.add_axes((0.52, 0.08, 0.44, 0.78))]
        ref, ins = cmp.reference, cmp.instance
        axes[0].scatter(ref[:, 0], ref[:, 1], s=1.2, c="#888888", linewidths=0,
                        label="representative")
        axes[0].scatter(ins[:, 0], ins[:, 1], s=1.2, c="#1f77b4", linewidths=0,
                        label="instance")
        axes[0].legend(loc="lower right", fontsize=7, markerscale=6)
        axes[1].imshow(cmp.difference, extent=(-half, half, -half, half), origin="lower",
                       cmap="magma_r", vmin=0.0,
                       vmax=max(float(cmp.difference.max()), 1e-6))
        axes[1].scatter(ref[:, 0], ref[:, 1], s=0.4, c="#2a9d8f", linewidths=0)
        for ax in axes:
            ax.add_patch(Circle(cmp.worst, 0.18, fill=False, color=REP_COLOUR, linewidth=1.5))
            lo, hi = np.r_[ref, ins].min(axis=0) - 0.2, np.r_[ref, ins].max(axis=0) + 0.2
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(*((hi[1], lo[1]) if y_down else (lo[1], hi[1])))
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
        sid, rep = instance.get("shape_id"), instance.get("representative_shape_id")
        fig.text(0.5, 0.97, f"shape {sid} {shorten(str(instance.get('name', '')), 30)} "
                 f"beside representative {rep}: group {instance.get('label')}, confidence "
                 f"{float(instance.get('confidence', 0.0)):.2f}, distance {cmp.distance:.3f} "
                 f"(ink offset {cmp.ink_offset:+.3f})", ha="center", va="top", fontsize=9)
        meta = {"distance": cmp.distance, "ink_offset": cmp.ink_offset,
                "worst": list(cmp.worst)}
        return save(fig, fmt_, meta)

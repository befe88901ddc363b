"""Registration error e per tree layer: the tree against direct CPD on the same subjects."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from service.plots import _doc
from service.plots._common import Rendered, check_format, figure, fmt_e, method_label, save

TREE_COLOUR = "#1f77b4"
DIRECT_COLOUR = "#ff7f0e"
P95_COLOUR = "#222222"


def _series(stats: Mapping[int, Mapping[str, Any]], layers: list[int], key: str) -> list[Any]:
    return [stats.get(layer, {}).get(key) for layer in layers]


def render_summary(
    result: Mapping[str, Any],
    *,
    fmt: str = "png",
    width: int = 900,
    height: int = 520,
    dpi: float = 100.0,
    log: bool | None = None,
    title: str | None = None,
) -> Rendered:
    """Bar chart of e per tree layer: mean (bar) and 95th percentile (whisker and tick), for
    the tree and, beside it, for direct CPD on the same subjects (when the job compared).

    Parameters
    ----------
    result : mapping
        The result document (``GET /v1/jobs/{id}/result``): ``summary.per_layer`` and
        ``summary.direct.per_layer`` are used, else the statistics are computed from the
        subjects' ``error`` and ``direct_error``.
    log : bool, optional
        Logarithmic e axis; by default when the bars span more than a factor of 100.

    Layers are the subjects' layers in the tree (the model is layer 1, so they start at 2);
    under each layer, the number of subjects. Bars are SVG groups ``tree-layer-<L>`` and
    ``direct-layer-<L>``. ``meta``: ``layers``, ``tree`` and ``direct`` (each ``mean``,
    ``p95``, ``count`` lists aligned with ``layers``; ``direct`` None without direct CPD),
    ``bars`` (number drawn), ``log``, ``unattached``.
    """
    fmt_ = check_format(fmt)
    label = method_label(result)
    tree, direct = _doc.layer_statistics(result)
    layers = sorted(tree)
    summary = result.get("summary") or {}
    has_direct = bool(direct) and any(direct.get(layer, {}).get("count") for layer in layers)

    series: dict[str, dict[str, list[Any]]] = {
        "tree": {k: _series(tree, layers, k) for k in ("mean", "p95", "count")}
    }
    if has_direct:
        series["direct"] = {k: _series(direct, layers, k) for k in ("mean", "p95", "count")}
    values = [
        v for s in series.values() for k in ("mean", "p95") for v in s[k] if v is not None and v > 0
    ]
    if log is None:
        log = bool(values) and max(values) / min(values) > 100

    with figure(width, height, dpi) as fig:
        ax = fig.add_axes((0.1, 0.14, 0.86, 0.68))
        x = np.arange(len(layers), dtype=float)
        bar_w = 0.38 if has_direct else 0.6
        offsets = {"tree": -bar_w / 2, "direct": bar_w / 2} if has_direct else {"tree": 0.0}
        colours = {"tree": TREE_COLOUR, "direct": DIRECT_COLOUR}
        bars = 0
        for key, s in series.items():
            for i, layer in enumerate(layers):
                mean, p95 = s["mean"][i], s["p95"][i]
                if mean is None:
                    continue
                xi = x[i] + offsets[key]
                patch = ax.bar(xi, mean, width=bar_w, color=colours[key], zorder=2)[0]
                patch.set_gid(f"{key}-layer-{layer}")
                bars += 1
                if p95 is not None:
                    ax.plot([xi, xi], [mean, p95], color=P95_COLOUR, lw=1.0, zorder=3)
                    ax.plot([xi], [p95], marker="_", ms=12, mew=1.6, color=P95_COLOUR, zorder=3)
        ax.set_xticks(
            x,
            [f"layer {layer}\nn = {tree[layer].get('count', 0)}" for layer in layers],
            fontsize=8.5,
        )
        if log:
            ax.set_yscale("log")
        ax.set_ylabel("registration error e (eq. 10)")
        ax.grid(axis="y", color="#e5e5e5", zorder=0)
        ax.set_axisbelow(True)
        for side in ("top", "right"):
            ax.spines[side].set_visible(False)
        if not layers:
            ax.text(0.5, 0.5, "no attached subject", ha="center", va="center",
                    transform=ax.transAxes)  # fmt: skip

        handles: list[Any] = [Patch(color=TREE_COLOUR, label=f"{label}: mean e")]
        if has_direct:
            handles.append(Patch(color=DIRECT_COLOUR, label="direct CPD: mean e"))
        handles.append(Line2D([], [], color=P95_COLOUR, marker="_", ms=12, label="95th percentile"))
        ax.legend(
            handles=handles,
            loc="lower center",
            bbox_to_anchor=(0.5, 1.0),
            ncols=len(handles),
            fontsize=8.5,
            frameon=False,
        )

        overall = summary.get("all") or {}
        overall_direct = (summary.get("direct") or {}).get("all") or {}
        subtitle = f"all attached: {label} mean e = {fmt_e(overall.get('mean'))}"
        if has_direct:
            subtitle += f", direct CPD mean e = {fmt_e(overall_direct.get('mean'))}"
        unattached = summary.get("unattached")
        if unattached is None:
            unattached = sum(1 for s in _doc.subjects(result) if not _doc.is_attached(s))
        subtitle += f"; unattached: {unattached}"
        fig.suptitle(
            title
            or f"job {result.get('job_id', '?')}: e per layer, {label}"
            + (" vs direct CPD" if has_direct else ""),
            y=1 - 10 / height,
            va="top",
            fontsize=12,
            parse_math=False,
        )
        fig.text(0.5, 1 - 36 / height, subtitle, ha="center", va="top", fontsize=9, color="#444")
        meta: dict[str, Any] = {
            "layers": layers,
            "tree": series["tree"],
            "direct": series.get("direct"),
            "bars": bars,
            "log": log,
            "unattached": unattached,
        }
        return save(fig, fmt_, meta)

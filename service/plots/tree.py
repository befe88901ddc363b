"""The registration tree: shapes by layer, edges coloured by e, low-confidence leaves dashed,
unattached shapes apart."""

from __future__ import annotations

import math
import unicodedata
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection
from matplotlib.colors import ListedColormap, LogNorm, Normalize
from matplotlib.lines import Line2D

from service.plots import _doc
from service.plots._common import (
    Rendered,
    check_format,
    data_to_pixel,
    figure,
    method_label,
    save,
    shorten,
)

# plasma without its palest yellows, which vanish on white
# (an edge without e is grey)
EDGE_CMAP = ListedColormap(
    colormaps["plasma"](np.linspace(0.0, 0.85, 256)), name="regtree_e"
).with_extremes(bad="#bbbbbb")
NODE_COLOUR = "#333333"
ROOT_COLOUR = "#1f4e79"
UNATTACHED_COLOUR = "#888888"
LEAF_COLOUR = "#777777"  # outline and name of a low-confidence leaf
LEAF_DASH = (0, (3.5, 2.5))  # its edge: dashed, in the colour of its e
LEAF_LABEL = "low-confidence leaf"
NAME_LIMIT = 40  # characters of a name drawn; longer names end in "…"

_LEFT_PX, _RIGHT_PX, _TOP_PX, _BOTTOM_PX = 64, 120, 56, 24
_LEGEND_PX = 14  # room under the title for the legend, when there are leaves
#: The results page's tree box on a 1440 x 1000 screen (a tree wider than half the page gets
#: three fifths of it), where the picture is fitted whole.
_VIEW_W, _VIEW_H = 680, 700
_UPRIGHT_SLOT_PX = 30  # room per shape in a row when names are upright


@dataclass
class _Plan:
    """A way to write the names, and the picture it makes."""

    rotation: int  # 0: across, 270: upright
    lines: int  # names across take turns on this many lines
    fontsize: float
    fig_w: int
    fig_h: int
    axes_w: float
    slot_px: float
    row_y: list[float]
    below: float
    u_fontsize: float
    per_row: int
    u_rows: int
    u_box: float
    fits: bool  # every name within its room
    dpi: float  # the figure's pixels per inch: a point is dpi / 72 pixels

    def fitted_px(self) -> float:
        """Names' point size in screen pixels once the picture is fitted into the page's box
        (never enlarged)."""
        scale = min(1.0, _VIEW_W / self.fig_w, _VIEW_H / self.fig_h)
        return self.fontsize * self.dpi / 72 * scale


@dataclass
class _Node:
    shape_id: int
    name: str
    layer: int
    parent: int | None
    error: float | None
    leaf: bool = False
    confidence: float | None = None
    children: list[int] = field(default_factory=list)
    x: float = 0.0


def _build(doc: Mapping[str, Any]) -> tuple[dict[int, _Node], list[tuple[int, str]], list[str]]:
    names = _doc.shape_names(doc)
    root = _doc.root_id(doc)
    nodes: dict[int, _Node] = {root: _Node(root, names.get(root, f"shape {root}"), 1, None, None)}
    unattached: list[tuple[int, str]] = []
    warnings: list[str] = []
    attached = []
    for s in _doc.subjects(doc):
        sid = int(s["shape_id"])
        name = str(s.get("name", names.get(sid, f"shape {sid}")))
        if sid == root:
            continue
        if _doc.is_attached(s) and s.get("layer") is not None:
            err = s.get("error")
            node = _Node(sid, name, int(s["layer"]), _doc.parent_of(s), None)
            node.error = None if err is None else float(err)
            node.leaf = _doc.is_leaf(s)
            node.confidence = _doc.confidence(s)
            nodes[sid] = node
            attached.append(node)
        else:
            unattached.append((sid, name))
    for node in attached:
        if node.parent not in nodes or node.parent == node.shape_id:
            warnings.append(f"shape {node.shape_id}: parent {node.parent} unknown; drawn on root")
            node.parent = root
        nodes[node.parent].children.append(node.shape_id)
    return nodes, unattached, warnings


def _layout(nodes: dict[int, _Node], root: int, row: dict[int, int]) -> float:
    """Tidy layered layout (in the manner of Reingold and Tilford); ``row`` maps a layer to its
    row. Returns the width in slots.

    Each subtree is laid out on its own, then a parent's subtrees are put side by side,
    left to right in the document's order, each as close to the previous ones as keeps every
    row's nodes at least one slot apart; the parent goes at the mean x of its children. So
    rows never cross, a parent is over its children, and a shallow branch tucks in beside
    deeper ones instead of taking columns of its own all the way down. An edge that skips
    rows (a child attached layers after its parent) keeps its rows clear as a node would.
    """
    # the tree as reached from the root, children in order (a broken document's cycles cut)
    order: list[int] = []
    seen = {root}
    stack = [root]
    while stack:
        sid = stack.pop()
        order.append(sid)
        kids = [c for c in nodes[sid].children if c not in seen]
        seen.update(kids)
        nodes[sid].children = kids
        stack.extend(reversed(kids))

    # per subtree, relative to its root: the children's offsets and the row contours
    offset: dict[int, float] = {}
    left: dict[int, dict[int, float]] = {}
    right: dict[int, dict[int, float]] = {}
    for sid in reversed(order):  # children before parents
        node = nodes[sid]
        r = row[node.layer]
        if not node.children:
            left[sid], right[sid] = {r: 0.0}, {r: 0.0}
            continue
        forest_left: dict[int, float] = {}
        forest_right: dict[int, float] = {}
        placed: list[float] = []
        for c in node.children:
            c_left, c_right = left.pop(c), right.pop(c)
            # the edge from this node down to the child passes the rows between them
            c_row = row[nodes[c].layer]
            for between in range(r + 1, c_row):
                c_left.setdefault(between, 0.0)
                c_right.setdefault(between, 0.0)
            common = [k for k in c_left if k in forest_right]
            if common:
                x = max(forest_right[k] - c_left[k] + 1.0 for k in common)
            else:
                x = placed[-1] + 1.0 if placed else 0.0
            placed.append(x)
            offset[c] = x
            for k, v in c_left.items():
                forest_left[k] = min(forest_left.get(k, math.inf), v + x)
            for k, v in c_right.items():
                forest_right[k] = max(forest_right.get(k, -math.inf), v + x)
        centre = float(np.mean(placed))
        for c in node.children:
            offset[c] -= centre
        left[sid] = {k: v - centre for k, v in forest_left.items()}
        right[sid] = {k: v - centre for k, v in forest_right.items()}
        left[sid][r] = min(left[sid].get(r, 0.0), 0.0)
        right[sid][r] = max(right[sid].get(r, 0.0), 0.0)

    # absolute positions, the leftmost node at 0
    lowest = min(left[root].values())
    nodes[root].x = -lowest
    for sid in order:
        for c in nodes[sid].children:
            nodes[c].x = nodes[sid].x + offset[c]
    width = max(right[root].values()) - lowest + 1.0
    # nodes unreachable from the root (cycles in a broken document): a slot each
    for node in nodes.values():
        if node.shape_id not in seen:
            node.x = width
            width += 1.0
    return max(width, 1.0)


def _edge_norm(errors: list[float]) -> tuple[Normalize, str]:
    positive = [e for e in errors if e > 0]
    if positive and len(positive) == len(errors) and max(positive) / min(positive) > 50:
        return LogNorm(vmin=min(positive), vmax=max(positive)), "log"
    hi = max(errors) if errors else 1.0
    return Normalize(vmin=0.0, vmax=hi if hi > 0 else 1.0), "linear"


def _text_px(chars: float, fontsize: float, dpi: float) -> float:
    return 0.62 * fontsize * dpi / 72.0 * chars


def _chars(text: str) -> float:
    """Length of ``text`` in average Latin characters (0.62 em): a wide (CJK) character
    takes a full em, about 1.6 of them."""
    return sum(1.6 if unicodedata.east_asian_width(c) in "WF" else 1.0 for c in text)


def render_tree(
    result: Mapping[str, Any],
    *,
    fmt: str = "svg",
    width: int | None = None,
    height: int | None = None,
    dpi: float = 100.0,
    title: str | None = None,
) -> Rendered:
    """Draw a job's registration tree.

    Parameters
    ----------
    result : mapping
        The result document (``GET /v1/jobs/{id}/result``; ``full`` not needed).
    fmt : "svg" or "png"
    width, height : int, optional
        Pixels; by default sized to the widest layer and the number of layers.
    dpi : float
        Pixels per inch (font sizes are in points, so a higher dpi means smaller text).
    title : str, optional
        Defaults to the job, method and how many subjects were attached.

    The root (the model) is on top; each row is a layer (the root is layer 1); an edge goes
    from the member a shape was registered from to the shape, coloured by that shape's
    registration error e (colour bar on the right; logarithmic when e spans more than 50x).
    A low-confidence leaf (a subject the tree could not accept, given its best registration
    after the tree stopped growing; never a parent) hangs from its parent by a dashed edge,
    as a hollow grey node with a grey name, and a legend under the title says so (only when
    there are leaves). Shapes no member could register are in a separate box labelled
    "unattached" below.
    The layout is tidy (see `_layout`): each parent at the mean x of its children, rows that
    never cross, subtrees packed side by side. Names are written across below their shapes,
    in one line or taking turns on two or three (a name may be that many slots wide), or upright,
    read downwards from the shape (``label_rotation`` 270, the shapes of a row about 30 px
    apart): by default whichever shows the names largest once the whole picture is fitted
    into the results page's tree box (680 x 700 px; a 40-shape glyph tree nine layers deep
    takes two lines), with a given ``width`` the first of them that fits.

    In SVG the tree is the group ``<g id="tree">`` and the box ``<g id="unattached">``; each
    name is a ``<text>`` in a group ``node-<shape_id>`` (``unattached-<shape_id>``); the
    edges are ``<g id="edges">`` and the leaves' ``<g id="leaf-edges">``, their nodes
    ``<g id="leaf-nodes">``, the legend ``<g id="legend">``.
    ``meta`` holds ``nodes`` (shape_id, name, layer, parent_shape_id, error, leaf,
    confidence, x), ``leaves`` (their shape ids), ``legend`` (its labels; empty without
    leaves), ``unattached`` (shape_id, name), ``depth``, ``norm`` ("log" or "linear"),
    ``e_range``, ``label_rotation``
    (0 or 270), ``label_fontsize``, ``data_to_pixel`` (``[[a, 0, b], [0, c, d]]``: a node at
    ``x`` in row ``y`` is at PNG pixel column ``a x + b``, row ``c y + d``; ``meta["rows"]``
    gives each layer's ``y``) and ``warnings``; ``x`` is in slots, one slot at least between
    two shapes of a row. Each row is as far below the previous one as that row's longest
    name needs, and a wide fan of edges a little more (64 to 200 px at the default height).
    """
    fmt_ = check_format(fmt)
    nodes, unattached, warnings = _build(result)
    root = _doc.root_id(result)
    depth = max(n.layer for n in nodes.values())
    layers = sorted({n.layer for n in nodes.values()})
    layer_index = {layer: i for i, layer in enumerate(layers)}
    slots = _layout(nodes, root, layer_index)

    label_len = (
        max(_chars(shorten(n.name, NAME_LIMIT)) for n in nodes.values() if n.parent)
        if len(nodes) > 1
        else _chars(shorten(nodes[root].name, NAME_LIMIT))
    )
    u_len = max((_chars(shorten(n, NAME_LIMIT)) for _, n in unattached), default=0.0)
    leaves = [n for n in nodes.values() if n.leaf and n.parent is not None]
    top_px = _TOP_PX + (_LEGEND_PX if leaves else 0)
    # each shape's line of names in its row: names written across in two lines take turns
    # (by x within the row), so that a name may be as wide as two slots
    rank: dict[int, int] = {}
    for layer in layers:
        in_row = sorted((n for n in nodes.values() if n.layer == layer), key=lambda n: n.x)
        rank.update({n.shape_id: i for i, n in enumerate(in_row)})

    def plan(rotation: int, lines: int, fontsize: float = 9.0) -> _Plan:
        """The picture's size with names written so (``width``/``height`` as asked)."""
        text = _text_px(label_len, fontsize, dpi)
        line_px = 1.4 * fontsize * dpi / 72
        if width:
            fig_w = width
            slot_px = max(width - _LEFT_PX - _RIGHT_PX, 40) / slots
        else:
            slot_px = _UPRIGHT_SLOT_PX if rotation else max(34.0, text / (0.92 * lines) + 4)
        # a name across the last shape of a row reaches past it: room before the colour bar
        right_px = _RIGHT_PX + (0.0 if rotation else max(0.0, 0.5 * (text - slot_px) + 12))
        if not width:
            fig_w = int(min(20_000, max(640, _LEFT_PX + right_px + slots * slot_px)))
        axes_w = max(fig_w - _LEFT_PX - right_px, 40)
        slot_px = axes_w / slots
        u_fontsize = min(9.0, fontsize + 1)
        u_slot = max(34.0, _text_px(u_len, u_fontsize, dpi) + 16)
        per_row = max(1, int(axes_w // u_slot))
        u_rows = math.ceil(len(unattached) / per_row) if unattached else 0
        u_box = 34 + 30 * u_rows if unattached else 0
        # each row's names hang below it (the model's goes above): a row is as far below
        # the previous one as that row's longest name needs, so short names make short gaps
        row_label_px = [0.0] * len(layers)
        for node in nodes.values():
            if node.parent is None:
                continue
            chars = _chars(shorten(node.name, NAME_LIMIT))
            line = rank[node.shape_id] % lines
            need = (_text_px(chars, fontsize, dpi) if rotation else line_px * (line + 1)) + 10
            i = layer_index[node.layer]
            row_label_px[i] = max(row_label_px[i], need)
        # ... and a wide fan of edges gets some height, so that its edges can be told apart
        fan_px = [0.0] * len(layers)
        for node in nodes.values():
            if node.parent is not None:
                parent = nodes[node.parent]
                i = layer_index[parent.layer]
                fan_px[i] = max(fan_px[i], abs(node.x - parent.x) * slot_px)
        row_y = [0.0]  # in pixels, downwards from the model's row
        for i in range(len(layers) - 1):
            gap = max(64.0, row_label_px[i] + 42, min(200.0, 0.2 * fan_px[i]))
            row_y.append(row_y[-1] - gap)
        label_px = (text if rotation else line_px) + 10
        below = row_label_px[-1] if len(layers) > 1 else label_px
        tree_px = -row_y[-1] + below + 36
        fig_h = height or int(min(6000, max(320, top_px + tree_px + u_box + _BOTTOM_PX + 20)))
        fits = rotation != 0 or text <= 0.92 * lines * slot_px
        return _Plan(rotation, lines, fontsize, fig_w, fig_h, axes_w, slot_px, row_y, below,
                     u_fontsize, per_row, u_rows, u_box, fits, dpi)  # fmt: skip

    # names: across in one line, taking turns on two or three, or upright, whichever shows
    # them largest when the whole picture is fitted into the results page's tree box (a narrower
    # picture wins a tie: it leaves room to zoom); with a given width, the first that fits
    candidates = [plan(0, 1), plan(0, 2), plan(0, 3), plan(270, 1)]
    if width:
        chosen = next(c for c in candidates if c.fits)
        while chosen.rotation and chosen.fontsize > 4 and 1.4 * chosen.fontsize * dpi / 72 > (
            0.9 * chosen.slot_px
        ):
            chosen = plan(270, 1, chosen.fontsize - 0.5)  # crowded: smaller upright names
    else:
        chosen = max(candidates, key=lambda c: (round(c.fitted_px(), 1), -c.fig_w))
    rotation, fontsize, lines = chosen.rotation, chosen.fontsize, chosen.lines
    fig_w, fig_h, axes_w, slot_px = chosen.fig_w, chosen.fig_h, chosen.axes_w, chosen.slot_px
    row_y, below, u_fontsize = chosen.row_y, chosen.below, chosen.u_fontsize
    per_row, u_rows, u_box = chosen.per_row, chosen.u_rows, chosen.u_box
    above = 1.6 * fontsize * dpi / 72 + 14

    def y_of(node: _Node) -> float:
        return row_y[layer_index[node.layer]]

    errors = [n.error for n in nodes.values() if n.parent is not None and n.error is not None]
    norm, norm_kind = _edge_norm(errors)

    with figure(fig_w, fig_h, dpi) as fig:
        avail = fig_h - top_px - _BOTTOM_PX
        u_h = min(u_box, 0.45 * avail) if unattached else 0
        tree_h = avail - u_h - (16 if unattached else 0)
        ax = fig.add_axes(
            (
                _LEFT_PX / fig_w,
                (_BOTTOM_PX + u_h + (16 if unattached else 0)) / fig_h,
                axes_w / fig_w,
                tree_h / fig_h,
            )
        )
        ax.set_gid("tree")
        # rows at row_y (pixels at the default height); room below the last row for its names
        ax.set_xlim(-0.5, slots - 0.5)
        ax.set_ylim(row_y[-1] - below - 10, above)
        for spine in ax.spines.values():
            spine.set_visible(False)
        ax.set_xticks([])
        ax.set_yticks(
            row_y,
            [f"layer {layer}" for layer in layers],
        )
        ax.tick_params(axis="y", length=0, labelsize=8, labelcolor="#555555")
        for y in row_y:
            ax.axhline(y, color="#eeeeee", lw=0.8, zorder=0)

        # an edge per attached shape, coloured by its e; a leaf's dashed
        edges: dict[bool, tuple[list[Any], list[float]]] = {False: ([], []), True: ([], [])}
        for node in nodes.values():
            if node.parent is None:
                continue
            parent = nodes[node.parent]
            segments, colours = edges[node.leaf]
            segments.append([(parent.x, row_y[layer_index[parent.layer]]), (node.x, y_of(node))])
            colours.append(np.nan if node.error is None else node.error)
        segments = edges[False][0] + edges[True][0]
        for dashed, gid in ((False, "edges"), (True, "leaf-edges")):
            if not edges[dashed][0]:
                continue
            lc = LineCollection(
                edges[dashed][0],
                cmap=EDGE_CMAP,
                norm=norm,
                linewidths=1.8 if dashed else 2.2,
                linestyles=LEAF_DASH if dashed else "solid",
                zorder=1,
                colors=None,
            )
            lc.set_array(np.asarray(edges[dashed][1], dtype=float))
            lc.set_gid(gid)
            ax.add_collection(lc)

        xs = np.asarray([n.x for n in nodes.values()])
        ys = np.asarray([y_of(n) for n in nodes.values()])
        is_root = np.asarray([n.parent is None for n in nodes.values()])
        leaf_mask = np.asarray([n.leaf and n.parent is not None for n in nodes.values()])
        member = ~is_root & ~leaf_mask
        marker_s = float(np.clip(0.25 * slot_px, 12, 60))
        ax.scatter(
            xs[member], ys[member], s=marker_s, facecolor="white",
            edgecolor=NODE_COLOUR, linewidths=1.2, zorder=2,
        )  # fmt: skip
        if leaf_mask.any():
            # hollow: the dashed edge shows through
            leaf_nodes = ax.scatter(
                xs[leaf_mask], ys[leaf_mask], s=marker_s, facecolor="none",
                edgecolor=LEAF_COLOUR, linewidths=1.2, zorder=2,
            )  # fmt: skip
            leaf_nodes.set_gid("leaf-nodes")
        ax.scatter(
            xs[is_root], ys[is_root], s=marker_s * 1.8, marker="s", color=ROOT_COLOUR, zorder=2
        )
        # text offset below a node, in points
        offset = math.sqrt(marker_s) / 2 + 3
        for node in nodes.values():
            is_model = node.parent is None
            label = shorten(node.name, NAME_LIMIT)
            if is_model:
                # the model sits on top: its name goes above it, clear of the edges
                label += " (model)"
                # ... and stays inside the picture when the model is near a side
                centre_px = _LEFT_PX + (node.x + 0.5) / slots * axes_w
                half = 0.55 * _text_px(_chars(label), fontsize, dpi) + 6
                shift_px = max(0.0, half - centre_px) - max(0.0, centre_px + half - fig_w)
                where: dict[str, Any] = {
                    "xytext": (shift_px * 72 / dpi, offset * 1.3),
                    "ha": "center",
                    "va": "bottom",
                }
            elif rotation:
                # vertical names beside the node, clear of an edge going straight down
                where = {"xytext": (2, -offset), "ha": "left", "va": "top"}
            else:
                line = rank[node.shape_id] % lines  # a later line is a name lower,
                drop = offset + 1.4 * fontsize * line
                where = {"xytext": (0, -drop), "ha": "center", "va": "top"}
                if line:  # tied to its shape by a faint line
                    where["arrowprops"] = {
                        "arrowstyle": "-", "color": "#bbbbbb", "lw": 0.6, "shrinkA": 0,
                        "shrinkB": 2,
                    }  # fmt: skip
            text = ax.annotate(
                label,
                (node.x, y_of(node)),
                textcoords="offset points",
                rotation=0 if is_model else rotation,
                fontsize=fontsize,
                color=ROOT_COLOUR if is_model else LEAF_COLOUR if node.leaf else "#111111",
                fontweight="bold" if is_model else "normal",
                fontstyle="italic" if node.leaf and not is_model else "normal",
                annotation_clip=False,
                parse_math=False,  # a name is shown as written, "$" and all
                bbox={"boxstyle": "square,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.85},
                zorder=3,
                **where,
            )
            text.set_gid(f"node-{node.shape_id}")

        if segments:
            tree_bottom = _BOTTOM_PX + u_h + 16 if unattached else _BOTTOM_PX
            bar_h = min(max(tree_h * 0.8, 20), 420)
            cax = fig.add_axes(
                (
                    (fig_w - _RIGHT_PX + 28) / fig_w,
                    (tree_bottom + 0.8 * tree_h - bar_h) / fig_h,
                    14 / fig_w,
                    bar_h / fig_h,
                )
            )
            cb = fig.colorbar(ScalarMappable(norm=norm, cmap=EDGE_CMAP), cax=cax)
            cb.set_label("e of the child (eq. 10)", fontsize=8)
            cb.ax.tick_params(labelsize=7)
            cax.set_gid("colorbar")

        if unattached:
            uax = fig.add_axes((_LEFT_PX / fig_w, _BOTTOM_PX / fig_h, axes_w / fig_w, u_h / fig_h))
            uax.set_gid("unattached")
            uax.set_xlim(-0.5, per_row - 0.5)
            uax.set_ylim(-u_rows + 0.2, 0.9)
            uax.set_xticks([])
            uax.set_yticks([])
            for spine in uax.spines.values():
                spine.set_linestyle((0, (4, 3)))
                spine.set_color(UNATTACHED_COLOUR)
            uax.set_title(
                f"unattached ({len(unattached)}): no member gave them a usable registration",
                loc="left",
                fontsize=9,
                color="#555555",
            )
            for i, (sid, name) in enumerate(unattached):
                row, col = divmod(i, per_row)
                uax.scatter([col], [-row + 0.45], s=22, facecolor="white",
                            edgecolor=UNATTACHED_COLOUR, linewidths=1.0)  # fmt: skip
                t = uax.text(
                    col, -row + 0.2, shorten(name, NAME_LIMIT), ha="center", va="top",
                    fontsize=u_fontsize, color="#444444", clip_on=False, parse_math=False,
                )  # fmt: skip
                t.set_gid(f"unattached-{sid}")

        legend_labels: list[str] = []
        if leaves:
            handles = [
                Line2D(
                    [], [], color="#777777", lw=2.2, marker="o", markersize=6,
                    markerfacecolor="white", markeredgecolor=NODE_COLOUR, label="tree member",
                ),
                Line2D(
                    [], [], color="#777777", lw=1.8, ls=LEAF_DASH, marker="o", markersize=6,
                    markerfacecolor="none", markeredgecolor=LEAF_COLOUR,
                    label=f"{LEAF_LABEL} (never a parent)",
                ),
            ]  # fmt: skip
            legend = fig.legend(
                handles=handles,
                loc="upper left",
                bbox_to_anchor=(_LEFT_PX / fig_w, 1 - 34 / fig_h),
                ncols=2,
                frameon=False,
                fontsize=8,
                handlelength=3.2,
                borderaxespad=0.0,
                borderpad=0.0,
                columnspacing=1.6,
            )
            legend.set_gid("legend")
            legend_labels = [str(h.get_label()) for h in handles]

        n_subjects = len(nodes) - 1 + len(unattached)
        as_leaves = f" ({len(leaves)} as leaves)" if leaves else ""
        fig.suptitle(
            title
            or (
                f"job {result.get('job_id', '?')}: {method_label(result)} — "
                f"{len(nodes) - 1} of {n_subjects} subjects attached{as_leaves}, depth {depth}"
            ),
            x=_LEFT_PX / fig_w,
            y=1 - 14 / fig_h,
            ha="left",
            va="top",
            fontsize=11,
            parse_math=False,
        )
        meta = {
            "nodes": [
                {
                    "shape_id": n.shape_id,
                    "name": n.name,
                    "layer": n.layer,
                    "parent_shape_id": n.parent,
                    "error": n.error,
                    "leaf": n.leaf,
                    "confidence": n.confidence,
                    "x": n.x,
                }
                for n in nodes.values()
            ],
            "leaves": [n.shape_id for n in leaves],
            "legend": legend_labels,
            "unattached": [{"shape_id": sid, "name": name} for sid, name in unattached],
            "depth": depth,
            "norm": norm_kind,
            "e_range": [norm.vmin, norm.vmax] if segments else None,
            "rows": {layer: row_y[i] for i, layer in enumerate(layers)},
            "label_rotation": rotation,
            "label_lines": lines,
            "data_to_pixel": data_to_pixel(fig, ax),
            "label_fontsize": fontsize,
            "warnings": warnings,
        }
        return save(fig, fmt_, meta)

"""Short text and HTML representations of the library's results, for notebooks.

The dataclasses' generated reprs print every array (a 40 x 300-point result ran to 3.8 MB);
the results, transforms and CPD runs say what they are in a line instead, and
``_repr_html_`` adds a summary table and a small SVG drawing of the tree (plain SVG: no
plotting library). Each class writes its own from the pieces here, which take what they
print as plain values: this module knows none of the classes.
"""

from __future__ import annotations

import html
from collections.abc import Iterable, Sequence
from typing import Any

__all__ = ["html_table", "number_text", "points_text", "tree_svg"]

#: The tree drawing stops at this many nodes (the table still counts them all).
MAX_DRAWN_NODES = 400


def number_text(value: Any) -> str:
    """A number in 4 significant digits, "-" for none."""
    if value is None:
        return "-"
    try:
        number = float(value)
    except (TypeError, ValueError):
        return str(value)
    return f"{number:.4g}"


def points_text(array: Any) -> str:
    """``<n points>`` for an array of points, "None" for none."""
    return "None" if array is None else f"<{len(array)} points>"


def _row(*cells: Any, head: bool = False) -> str:
    tag = "th" if head else "td"
    return "<tr>" + "".join(f"<{tag}>{html.escape(str(c))}</{tag}>" for c in cells) + "</tr>"


def html_table(title: str, rows: Iterable[tuple[str, Any]], after: str = "") -> str:
    """A titled table of (label, value) rows, then `after` (HTML), in one ``<div>``."""
    return (
        f"<div><b>{title}</b><table>" + "".join(_row(label, value) for label, value in rows)
        + "</table>" + after + "</div>"
    )


def tree_svg(root: int, names: Sequence[str],
             nodes: Iterable[tuple[int, int, int | None, str]]) -> str:
    """The tree by layer: the root on top, edges parent -> child, leaves hollow, unattached
    subjects in a row of their own at the bottom. Names are in each node's ``<title>``.

    `nodes` are ``(index, layer, parent, status)``: layer 0 for an unattached subject,
    status ``"root"``, ``"tree"``, ``"leaf"`` or ``"unattached"``."""
    layer_of: dict[int, int] = {}
    parent_of: dict[int, int | None] = {}
    status: dict[int, str] = {}
    for index, layer, parent, state in nodes:
        layer_of[index], parent_of[index], status[index] = layer, parent, state
    if len(layer_of) > MAX_DRAWN_NODES:
        return f"<p>({len(layer_of)} shapes: too many to draw here)</p>"
    rows: dict[int, list[int]] = {}
    for node, layer in layer_of.items():
        rows.setdefault(layer, []).append(node)
    order = sorted(k for k in rows if k > 0) + ([0] if 0 in rows else [])
    width = max(240, 18 * max(len(v) for v in rows.values()))
    pos: dict[int, tuple[float, float]] = {}
    for r, layer in enumerate(order):
        members = sorted(rows[layer])
        for k, node in enumerate(members):
            pos[node] = ((k + 0.5) * width / len(members), 16 + 36 * r)
    height = 32 + 36 * (len(order) - 1)
    colours = {"root": "#333", "tree": "#2a7ab0", "leaf": "#fff", "unattached": "#c44"}
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{height}">']
    for node, parent in parent_of.items():
        if parent is not None and parent in pos:
            (x1, y1), (x2, y2) = pos[parent], pos[node]
            dash = ' stroke-dasharray="3,2"' if status[node] == "leaf" else ""
            parts.append(
                f'<line x1="{x1:.1f}" y1="{y1:.1f}" x2="{x2:.1f}" y2="{y2:.1f}" '
                f'stroke="#999"{dash}/>'
            )
    for node, (x, y) in pos.items():
        name = names[node] if 0 <= node < len(names) else str(node)
        parts.append(
            f'<circle cx="{x:.1f}" cy="{y:.1f}" r="5" fill="{colours[status[node]]}" '
            f'stroke="#333"><title>{html.escape(f"{node}: {name} ({status[node]})")}'
            "</title></circle>"
        )
    parts.append("</svg>")
    return "".join(parts)

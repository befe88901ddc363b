"""Short text and HTML representations of the library's results, for notebooks.

The dataclasses' generated reprs print every array (a 40 x 300-point result ran to 3.8 MB);
these say what a result is in a line, and ``_repr_html_`` adds a summary table and a small
SVG drawing of the tree (plain SVG: no plotting library).
"""

from __future__ import annotations

import html
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ._cpd import CPDResult, NonrigidTransform
    from ._result import CollectionResult, SubjectResult
    from ._transform import ChainTransform

__all__ = [
    "chain_repr",
    "collection_html",
    "collection_repr",
    "cpd_repr",
    "nonrigid_repr",
    "subject_html",
    "subject_repr",
]

#: The tree drawing stops at this many nodes (the table still counts them all).
MAX_DRAWN_NODES = 400


def _g(value: Any) -> str:
    """A number in 4 significant digits, "-" for none."""
    if value is None:
        return "-"
    try:
        number = float(value)
    except (TypeError, ValueError):
        return str(value)
    return f"{number:.4g}"


def _points(array: Any) -> str:
    return "None" if array is None else f"<{len(array)} points>"


def subject_repr(s: SubjectResult) -> str:
    where = (
        f"layer={s.layer}, parent={s.parent}" if s.attached else "unattached"
    ) + (", leaf" if s.leaf else "")
    return (
        f"SubjectResult(index={s.index}, name={s.name!r}, {where}, e={_g(s.error)}, "
        f"confidence={_g(s.confidence)}, warped={_points(s.warped)}, "
        f"attempts={len(s.attempts)})"
    )


def _counts(result: CollectionResult) -> dict[str, Any]:
    summary = result.summary()
    return {
        "subjects": summary["subjects"],
        "attached": summary["attached"],
        "leaves": summary["leaves"],
        "unattached": summary["unattached"],
        "depth": summary["depth"],
        "deep": summary["layer_ge_3"],
        "all": summary["all"],
        "direct": summary.get("direct"),
    }


def collection_repr(result: CollectionResult) -> str:
    c = _counts(result)
    root = result.names[result.root] if 0 <= result.root < len(result.names) else result.root
    text = (
        f"CollectionResult(method={result.method!r}, root={result.root} ({root!r}), "
        f"{c['subjects']} subjects: {c['attached']} attached ({c['leaves']} leaves), "
        f"{c['unattached']} unattached, depth {c['depth']}; "
        f"e layer>=3 mean {_g(c['deep']['mean'])} p95 {_g(c['deep']['p95'])}, "
        f"all mean {_g(c['all']['mean'])}"
    )
    if c["direct"] is not None:
        text += f"; direct layer>=3 mean {_g(c['direct']['layer_ge_3']['mean'])}"
    return text + ")"


def cpd_repr(r: CPDResult) -> str:
    return (
        f"CPDResult(warped={_points(r.warped)}, iterations={r.iterations}, "
        f"converged={r.converged}, sigma2={_g(r.sigma2)}, objective={_g(r.objective)})"
    )


def nonrigid_repr(t: NonrigidTransform) -> str:
    return (
        f"NonrigidTransform(control_points={_points(t.control_points)}, beta={_g(t.beta)}, "
        f"model_scale={_g(t.model_scale)}, subject_scale={_g(t.subject_scale)})"
    )


def chain_repr(t: ChainTransform) -> str:
    kinds = ", ".join(type(s).__name__ for s in t.steps) or "identity"
    return f"ChainTransform(path={t.path}, steps=[{kinds}])"


def _row(*cells: Any, head: bool = False) -> str:
    tag = "th" if head else "td"
    return "<tr>" + "".join(f"<{tag}>{html.escape(str(c))}</{tag}>" for c in cells) + "</tr>"


def _tree_svg(result: CollectionResult) -> str:
    """The tree by layer: the root on top, edges parent -> child, leaves hollow, unattached
    subjects in a row of their own at the bottom. Names are in each node's ``<title>``."""
    layer_of = {result.root: 1}
    parent_of: dict[int, int | None] = {result.root: None}
    status: dict[int, str] = {result.root: "root"}
    for s in result.subjects:
        layer_of[s.index] = s.layer if s.layer is not None else 0
        parent_of[s.index] = s.parent
        status[s.index] = "leaf" if s.leaf else ("tree" if s.attached else "unattached")
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
        name = result.names[node] if 0 <= node < len(result.names) else str(node)
        parts.append(
            f'<circle cx="{x:.1f}" cy="{y:.1f}" r="5" fill="{colours[status[node]]}" '
            f'stroke="#333"><title>{html.escape(f"{node}: {name} ({status[node]})")}'
            "</title></circle>"
        )
    parts.append("</svg>")
    return "".join(parts)


def collection_html(result: CollectionResult) -> str:
    c = _counts(result)
    direct = c["direct"]
    rows = [
        _row("method", result.method),
        _row("root", f"{result.root}: {result.names[result.root]}"),
        _row("subjects", c["subjects"]),
        _row("attached (leaves)", f"{c['attached']} ({c['leaves']})"),
        _row("unattached", c["unattached"]),
        _row("depth", c["depth"]),
        _row("e at layer >= 3: mean / p95", f"{_g(c['deep']['mean'])} / {_g(c['deep']['p95'])}"),
        _row("e, all attached: mean / p95", f"{_g(c['all']['mean'])} / {_g(c['all']['p95'])}"),
    ]
    if direct is not None:
        deep = direct["layer_ge_3"]
        rows.append(_row("direct CPD, layer >= 3: mean / p95",
                         f"{_g(deep['mean'])} / {_g(deep['p95'])}"))
    return (
        "<div><b>CollectionResult</b><table>" + "".join(rows) + "</table>"
        + _tree_svg(result) + "</div>"
    )


def subject_html(s: SubjectResult) -> str:
    rows = [
        _row("index", s.index),
        _row("name", s.name),
        _row("layer", "unattached" if not s.attached else s.layer),
        _row("parent", s.parent if s.parent is not None else "-"),
        _row("path", " > ".join(map(str, s.path)) or "-"),
        _row("D from parent", _g(s.similarity)),
        _row("e", _g(s.error)),
        _row("confidence", _g(s.confidence)),
        _row("leaf", s.leaf),
        _row("reason", s.reason),
        _row("warped", _points(s.warped)),
        _row("attempts", len(s.attempts)),
    ]
    return "<div><b>SubjectResult</b><table>" + "".join(rows) + "</table></div>"



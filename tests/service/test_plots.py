"""service.plots: the pictures show what the result says (content checks, not just bytes)."""

from __future__ import annotations

import io
import json
import re
import threading
import xml.etree.ElementTree as ET
from itertools import pairwise
from typing import Any

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from service.plots import (
    Rendered,
    find_subject,
    layer_statistics,
    render_subject,
    render_summary,
    render_tree,
)
from service.plots.subject import WARPED_COLOUR

SVG = "{http://www.w3.org/2000/svg}"

# --- data ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real() -> dict[str, Any]:
    """A real dynamic-tree result, turned into the API's documents exactly as the worker does."""
    from registration import build_dynamic_tree
    from registration.synthetic import chained_family
    from service.jobs.runner import to_api_document

    fam = chained_family(n_chains=2, chain_length=3, n_points=60, step=0.25, seed=1)
    result = build_dynamic_tree(fam.shapes, root=0, names=fam.names, compare_direct=True)
    shape_ids = [101 + k for k in range(len(fam.shapes))]
    raw = json.loads(json.dumps(result.to_dict()))
    document, full = to_api_document(7, raw, shape_ids)
    return {
        "document": document,
        "full": full,
        "points": dict(zip(shape_ids, fam.shapes, strict=True)),
    }


def document_subject(
    sid: int, name: str, layer: int | None, parent: int | None, e: float | None,
    *, direct_factor: float = 3.0,
) -> dict[str, Any]:
    """One subject of a hand-made result document (unattached when `layer` is None); its
    direct CPD error is `direct_factor` times the tree's."""
    return {
        "shape_id": sid,
        "name": name,
        "layer": layer,
        "attached": layer is not None,
        "parent_shape_id": parent,
        "error": e,
        "direct_error": None if e is None else direct_factor * e,
    }


def handmade() -> dict[str, Any]:
    """A tree with known structure: 4 layers, two unattached shapes, awkward names."""
    subject = document_subject
    return {
        "job_id": 5,
        "method": "dynamic_tree",
        "root_shape_id": 1,
        "shape_ids": list(range(1, 10)),
        "names": ["model", "a<b & c", "b", "c", "d", "e", "f", "g", "永-glyph"],
        "subjects": [
            subject(2, "a<b & c", 2, 1, 0.001),
            subject(3, "b", 2, 1, 0.002),
            subject(4, "c", 3, 2, 0.003),
            subject(5, "d", 3, 2, 0.004),
            subject(6, "e", 3, 3, 0.005),
            subject(7, "f", 4, 6, 0.006),
            subject(8, "g", None, None, None),
            subject(9, "永-glyph", None, None, None),
        ],
    }


def png_image(rendered: Rendered) -> np.ndarray:
    assert rendered.media_type == "image/png" and rendered.data.startswith(b"\x89PNG")
    image = Image.open(io.BytesIO(rendered.data))
    assert image.size == (rendered.width, rendered.height)
    return np.asarray(image.convert("RGB")).astype(int)


def svg_texts(element: ET.Element) -> list[str]:
    return ["".join(t.itertext()) for t in element.iter(f"{SVG}text")]


def svg_group(root: ET.Element, gid: str) -> ET.Element:
    found = root.find(f".//{SVG}g[@id='{gid}']")
    assert found is not None, f"no <g id={gid!r}>"
    return found


# --- tree ------------------------------------------------------------------------------------


def test_tree_svg_names_attached_in_tree_and_unattached_apart() -> None:
    doc = handmade()
    rendered = render_tree(doc, fmt="svg")
    assert rendered.media_type == "image/svg+xml"
    root = ET.fromstring(rendered.data)
    tree_texts = svg_texts(svg_group(root, "tree"))
    unattached_texts = svg_texts(svg_group(root, "unattached"))
    for s in doc["subjects"]:
        if s["attached"]:
            assert s["name"] in tree_texts  # XML escaping round-trips "a<b & c"
            assert s["name"] not in unattached_texts
        else:
            assert s["name"] in unattached_texts
            assert s["name"] not in tree_texts
    assert "model (model)" in tree_texts
    assert any(t.startswith("unattached (2)") for t in unattached_texts)
    assert ["layer 1", "layer 2", "layer 3", "layer 4"] == [
        t for t in tree_texts if t.startswith("layer")
    ]
    svg_group(root, "colorbar")
    assert rendered.meta["depth"] == 4 and rendered.meta["norm"] == "linear"
    assert rendered.meta["e_range"] == [0.0, 0.006]
    # the same picture as PNG, at the size asked for
    png = render_tree(doc, fmt="png", width=700, height=450)
    assert png_image(png).shape == (450, 700, 3)
    assert png.meta["nodes"] == rendered.meta["nodes"]
    assert png.meta["unattached"] == rendered.meta["unattached"]


def test_tree_layout_rows_by_layer_parents_over_children() -> None:
    meta = render_tree(handmade(), fmt="svg").meta
    nodes = {n["shape_id"]: n for n in meta["nodes"]}
    assert nodes[1]["layer"] == 1 and nodes[1]["parent_shape_id"] is None
    assert {n["layer"] for n in nodes.values()} == {1, 2, 3, 4}
    for layer in (2, 3, 4):
        xs = [n["x"] for n in nodes.values() if n["layer"] == layer]
        assert len(set(xs)) == len(xs)  # no two shapes of a row on top of each other
    for sid, node in nodes.items():
        kids = [n["x"] for n in nodes.values() if n["parent_shape_id"] == sid]
        if kids:
            assert min(kids) <= node["x"] <= max(kids)
    # rows do not cross: children appear left to right in their parents' order
    assert nodes[4]["x"] < nodes[5]["x"] < nodes[6]["x"]
    assert [u["shape_id"] for u in meta["unattached"]] == [8, 9]


def test_tree_real_result_and_log_colour_scale(real: dict[str, Any]) -> None:
    doc = real["document"]
    rendered = render_tree(doc, fmt="svg")
    root = ET.fromstring(rendered.data)
    tree_texts = svg_texts(svg_group(root, "tree"))
    attached = [s for s in doc["subjects"] if s["attached"]]
    unattached = [s for s in doc["subjects"] if not s["attached"]]
    assert attached
    assert all(s["name"] in tree_texts for s in attached)
    if unattached:
        texts = svg_texts(svg_group(root, "unattached"))
        assert all(s["name"] in texts for s in unattached)
    else:
        assert root.find(f".//{SVG}g[@id='unattached']") is None
    assert rendered.meta["depth"] == doc["summary"]["depth"]

    spread = handmade()
    for k, s in enumerate(s for s in spread["subjects"] if s["attached"]):
        s["error"] = 10.0 ** (-5 + k)
    assert render_tree(spread, fmt="png").meta["norm"] == "log"


def tree_doc(parents: dict[int, int], layers: dict[int, int], **names: str) -> dict[str, Any]:
    """A result document from child -> parent and child -> layer (the root is shape 1)."""
    subjects = [
        {"shape_id": k, "name": names.get(f"s{k}", f"shape-{k}"), "layer": layers[k],
         "attached": True, "parent_shape_id": p, "error": 0.001 * k}
        for k, p in parents.items()
    ]  # fmt: skip
    return {"job_id": 1, "method": "dynamic_tree", "root_shape_id": 1, "subjects": subjects}


def check_tidy(meta: dict[str, Any]) -> dict[int, dict[str, Any]]:
    nodes = {n["shape_id"]: n for n in meta["nodes"]}
    rows: dict[int, list[float]] = {}
    for n in nodes.values():
        rows.setdefault(n["layer"], []).append(n["x"])
    for xs in rows.values():
        xs.sort()
        assert all(b - a >= 1 - 1e-9 for a, b in pairwise(xs))
    for sid, node in nodes.items():
        kids = [n["x"] for n in nodes.values() if n["parent_shape_id"] == sid]
        if kids:  # each parent at the mean of its children
            assert node["x"] == pytest.approx(float(np.mean(kids)))
    return nodes


def test_tree_layout_is_tidy_and_compact() -> None:
    # root -> a (three leaves under it), b (a leaf): b tucks in beside a's children's row
    doc = tree_doc({2: 1, 3: 1, 4: 2, 5: 2, 6: 2}, {2: 2, 3: 2, 4: 3, 5: 3, 6: 3})
    nodes = check_tidy(render_tree(doc, fmt="svg").meta)
    assert [nodes[k]["x"] for k in (4, 5, 6)] == [0.0, 1.0, 2.0]
    assert nodes[2]["x"] == 1.0 and nodes[3]["x"] == 2.0  # not a column of its own
    assert nodes[1]["x"] == 1.5  # the model is over its children, not off to a side

    # a big random tree, some children attached layers after their parents
    rng = np.random.default_rng(3)
    parents: dict[int, int] = {}
    layers = {1: 1}
    for k in range(2, 302):
        parent = int(rng.choice(list(layers)[-40:]))
        parents[k] = parent
        layers[k] = layers[parent] + int(rng.choice([1, 1, 1, 2]))
    rendered = render_tree(tree_doc(parents, layers), fmt="svg")
    nodes = check_tidy(rendered.meta)
    # an edge that skips rows keeps them clear: no node of a skipped row sits on it
    for k, node in nodes.items():
        parent = nodes[node["parent_shape_id"]] if node["parent_shape_id"] else None
        if parent is None or node["layer"] - parent["layer"] < 2:
            continue
        between = [n["x"] for n in nodes.values() if parent["layer"] < n["layer"] < node["layer"]]
        assert all(abs(x - node["x"]) >= 1 - 1e-9 for x in between), k
    # names stand upright rather than making a very wide picture; every name is there
    assert rendered.meta["label_rotation"] == 270
    slots = max(n["x"] for n in nodes.values()) + 1
    assert rendered.width <= 200 + 30 * slots  # about 30 px a shape, not 80 for a wide name
    texts = svg_texts(svg_group(ET.fromstring(rendered.data), "tree"))
    assert all(f"shape-{k}" in texts for k in parents)


def test_tree_rows_are_as_far_apart_as_their_names_need() -> None:
    # upright names: long ones below row 2, short ones below row 3, none below the model
    long = {f"s{k}": f"a-rather-long-font-family-name__variant-{k:03d}" for k in range(2, 80)}
    parents = {k: 1 for k in range(2, 80)} | {k: 2 for k in range(80, 90)}
    layers = {k: 2 for k in range(2, 80)} | {k: 3 for k in range(80, 90)}
    rendered = render_tree(tree_doc(parents, layers, **long), fmt="png")
    meta = rendered.meta
    assert meta["label_rotation"] == 270
    (_, _, _), (_, c, d) = meta["data_to_pixel"]
    row_px = {layer: c * y + d for layer, y in meta["rows"].items()}
    assert 60 <= row_px[2] - row_px[1] <= 210  # the model is near its children
    assert row_px[3] - row_px[2] > 250  # room for the long upright names of row 2
    assert row_px[2] - row_px[1] < row_px[3] - row_px[2] - 100
    assert row_px[3] < rendered.height - 80  # and for the short ones of row 3


def test_tree_names_are_drawn_as_written() -> None:
    names = {"s2": "cost $5 and $6", "s3": r"$\alpha$"}
    doc = tree_doc({2: 1, 3: 1}, {2: 2, 3: 2}, **names)
    doc["subjects"].append(
        {"shape_id": 4, "name": "$x$", "layer": None, "attached": False, "error": None}
    )
    texts = svg_texts(ET.fromstring(render_tree(doc, fmt="svg").data))
    assert {"cost $5 and $6", r"$\alpha$", "$x$"} <= set(texts)


def test_tree_crowded_labels_turn_vertical() -> None:
    subjects = [
        {"shape_id": k, "name": f"glyph-instance-{k:04d}", "layer": 2, "attached": True,
         "parent_shape_id": 1, "error": 0.001 * k}
        for k in range(2, 120)
    ]  # fmt: skip
    doc = {"job_id": 1, "method": "dynamic_tree", "root_shape_id": 1, "subjects": subjects}
    rendered = render_tree(doc, fmt="png", width=1600)
    assert rendered.meta["label_rotation"] == 270
    assert png_image(rendered).shape[1] == 1600



@pytest.mark.parametrize("dpi", [100.0, 200.0])
def test_tree_names_fitted_size_counts_the_figure_dpi(dpi: float) -> None:
    """A point is dpi / 72 pixels: the layout compares names' fitted size at the real dpi."""
    from service.plots.tree import _Plan

    plan = _Plan(0, 1, 9.0, 600, 600, 500.0, 40.0, [0.0], 20.0, 9.0, 10, 0, 0.0, True, dpi)
    assert plan.fitted_px() == pytest.approx(9.0 * dpi / 72)
    # fitted into the page's box, a wider picture shrinks its names by the same factor
    wide = _Plan(0, 1, 9.0, 1360, 600, 1260.0, 40.0, [0.0], 20.0, 9.0, 10, 0, 0.0, True, dpi)
    assert wide.fitted_px() == pytest.approx(9.0 * dpi / 72 * 680 / 1360)

# --- subject ---------------------------------------------------------------------------------


def colour_mask(image: np.ndarray, colour: str, tolerance: int = 40) -> np.ndarray:
    rgb = np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)])
    return np.asarray(np.abs(image - rgb).max(axis=2) <= tolerance)


def project(points: np.ndarray, transform: list[list[float]]) -> np.ndarray:
    (a, _, b), (_, c, d) = transform
    return np.c_[a * points[:, 0] + b, c * points[:, 1] + d]


def near_fraction(image: np.ndarray, panel: dict[str, Any], points: np.ndarray) -> float:
    """Share of the panel's warped-model-coloured pixels within 10 px of a subject point."""
    c0, r0, c1, r1 = (round(v) for v in panel["bbox_px"])
    red = np.zeros(image.shape[:2], dtype=bool)
    red[r0:r1, c0:c1] = colour_mask(image[r0:r1, c0:c1], WARPED_COLOUR)
    subject = np.zeros_like(red)
    px = np.round(project(points, panel["data_to_pixel"])).astype(int)
    rows, cols = image.shape[:2]
    inside = (px[:, 0] >= 0) & (px[:, 0] < cols) & (px[:, 1] >= 0) & (px[:, 1] < rows)
    subject[px[inside, 1], px[inside, 0]] = True
    near = ndimage.distance_transform_edt(~subject) <= 10
    assert red.sum() > 50, "the warped model is not drawn"
    return float((red & near).sum() / red.sum())


def good_subject(real: dict[str, Any]) -> dict[str, Any]:
    deep = [s for s in real["full"] if s["attached"] and not s.get("leaf") and s.get("direct")]
    return max(deep, key=lambda s: s["layer"])


def test_subject_overlay_warped_model_lies_on_the_subject(real: dict[str, Any]) -> None:
    subject = good_subject(real)
    points = real["points"][subject["shape_id"]]
    rendered = render_subject(subject, points, width=1000, height=520, method="dynamic tree")
    image = png_image(rendered)
    assert image.shape == (520, 1000, 3)
    panels = {p["name"]: p for p in rendered.meta["panels"]}
    assert list(panels) == ["tree", "direct"]
    assert panels["tree"]["error"] == subject["error"]
    assert panels["direct"]["error"] == subject["direct"]["error"]
    assert panels["tree"]["lines"] == 40 and not rendered.meta["warnings"]
    tree_near = near_fraction(image, panels["tree"], points)
    direct_near = near_fraction(image, panels["direct"], points)
    assert tree_near > 0.9
    assert direct_near > 0.3  # drawn over the same subject, in the same axes
    if subject["direct"]["error"] > 2 * subject["error"]:
        assert tree_near > direct_near  # the worse e is visibly further off

    # control: a model warped to the wrong place is seen as off the subject
    span = float(np.ptp(points, axis=0).max())
    wrong = dict(subject, warped=(np.asarray(subject["warped"]) + 0.3 * span).tolist())
    wrong.pop("direct")
    bad = render_subject(wrong, points, width=1000, height=520)
    assert near_fraction(png_image(bad), bad.meta["panels"][0], points) < 0.5


@pytest.mark.parametrize("y_down", [True, False])
def test_subject_y_axis_direction(real: dict[str, Any], y_down: bool) -> None:
    subject = dict(good_subject(real))
    subject.pop("direct")
    points = real["points"][subject["shape_id"]]
    rendered = render_subject(subject, points, width=600, height=500, y_down=y_down, n_lines=0)
    panel = rendered.meta["panels"][0]
    c = panel["data_to_pixel"][1][1]
    assert (c > 0) if y_down else (c < 0)  # larger y lower in the picture when y points down
    image = png_image(rendered)
    c0, r0, c1, r1 = (round(v) for v in panel["bbox_px"])
    red = np.zeros(image.shape[:2], dtype=bool)
    red[r0:r1, c0:c1] = colour_mask(image[r0:r1, c0:c1], WARPED_COLOUR)  # not the legend
    rows, cols = np.nonzero(red)
    expected = project(np.asarray(subject["warped"]), panel["data_to_pixel"]).mean(axis=0)
    # the red pixels weigh each warped point by the ink drawn around it, so their centre
    # is a few pixels from the points' mean where the points are unevenly spaced (6.7 px
    # for this subject); a y axis the wrong way round would be off by far more
    assert abs(cols.mean() - expected[0]) < 10 and abs(rows.mean() - expected[1]) < 10


def test_subject_unattached_shows_reason_and_direct(real: dict[str, Any]) -> None:
    base = good_subject(real)
    points = real["points"][base["shape_id"]]
    unattached = dict(
        base, attached=False, layer=None, warped=None, correspondence=None, reason="no similar"
    )
    rendered = render_subject(unattached, points, fmt="svg")
    assert [p["name"] for p in rendered.meta["panels"]] == ["subject", "direct"]
    texts = svg_texts(ET.fromstring(rendered.data))
    assert "unattached: no similar" in texts
    assert any(t.startswith("direct CPD from the model") for t in texts)
    alone = dict(unattached)
    alone.pop("direct")
    assert [p["name"] for p in render_subject(alone, points).meta["panels"]] == ["subject"]
    # correspondences that do not index these points are reported, not drawn
    mismatch = render_subject(base, points[:10])
    assert mismatch.meta["panels"][0]["lines"] == 0 and mismatch.meta["warnings"]


LONG_NAME = "aoyagi-soseki__aoyagi-soseki__0_edge_outline_of_the_glyph_with_a_long_name"
LONG_REASON = (
    "no member of the tree registered it within the error threshold "
    "(best e = 0.0123 from shape 17, threshold 0.0045); similar to 0 members"
)


def within(box: list[float], room: list[float], slack: float = 1.0) -> bool:
    return (
        box[0] >= room[0] - slack
        and box[2] <= room[2] + slack
        and box[1] >= room[1] - slack
        and box[3] <= room[3] + slack
    )


def apart(a: list[float], b: list[float]) -> bool:
    return a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1]


@pytest.mark.parametrize("width", [700, 520])
@pytest.mark.parametrize("attached", [True, False])
def test_subject_titles_fit_their_panels(real: dict[str, Any], width: int, attached: bool) -> None:
    base = good_subject(real)
    points = real["points"][base["shape_id"]]
    subject = dict(base, name=LONG_NAME)
    if not attached:
        subject.update(attached=False, layer=None, warped=None, correspondence=None)
        subject["reason"] = LONG_REASON
    rendered = render_subject(subject, points, width=width, method="dynamic_tree")
    meta = rendered.meta
    panels = meta["panels"]
    assert [p["name"] for p in panels] == (["tree" if attached else "subject", "direct"])
    picture = [0.0, 0.0, float(rendered.width), float(rendered.height)]
    gaps = [panels[0]["slot_px"][2], panels[1]["slot_px"][0]]
    for i, panel in enumerate(panels):
        title = panel["title"]
        # within the panel's column (up to the middle of the gap beside it) and the picture
        left = (gaps[0] + gaps[1]) / 2 if i else 0.0
        right = (gaps[0] + gaps[1]) / 2 if i == 0 else float(rendered.width)
        assert within(title["bbox_px"], [left, 0.0, right, panel["bbox_px"][1]]), title
        assert within(title["bbox_px"], picture)
        # the whole text is shown, legibly
        assert not title["cut"] and title["fontsize"] >= 7.5
    if not attached:  # lines break between words, or inside a word too long for a line
        shown = panels[0]["title"]["text"].replace("\n", " ").split()
        assert "".join(shown) == "".join(f"unattached: {LONG_REASON}".split())
    assert apart(panels[0]["title"]["bbox_px"], panels[1]["title"]["bbox_px"])
    heading = meta["title"]
    assert within(heading["bbox_px"], picture) and not heading["cut"]
    assert LONG_NAME in heading["text"].replace("\n", "")
    for panel in panels:
        assert apart(heading["bbox_px"], panel["title"]["bbox_px"])
    # the same boxes hold in the SVG: titles are text with the same lines
    svg = render_subject(subject, points, width=width, fmt="svg", method="dynamic_tree")
    texts = svg_texts(ET.fromstring(svg.data))
    for panel in panels:
        for line in panel["title"]["text"].split("\n"):
            assert line in texts
    # wider, the titles are whole too
    wide = render_subject(subject, points, width=900, method="dynamic_tree").meta
    assert not any(p["title"]["cut"] for p in wide["panels"])


def test_find_subject(real: dict[str, Any]) -> None:
    doc = {**real["document"], "subjects": real["full"]}
    sid = real["full"][2]["shape_id"]
    assert find_subject(doc, sid)["shape_id"] == sid
    with pytest.raises(KeyError):
        find_subject(doc, 999)


# --- summary ---------------------------------------------------------------------------------


def bar_ids(rendered: Rendered) -> list[str]:
    root = ET.fromstring(rendered.data)
    return [
        g.attrib["id"]
        for g in root.iter(f"{SVG}g")
        if re.fullmatch(r"(tree|direct)-layer-\d+", g.attrib.get("id", ""))
    ]


def test_summary_one_bar_per_layer_tree_and_direct(real: dict[str, Any]) -> None:
    doc = real["document"]
    layers = sorted(int(k) for k in doc["summary"]["per_layer"])
    rendered = render_summary(doc, fmt="svg")
    ids = bar_ids(rendered)
    assert sorted(ids) == sorted(
        [f"tree-layer-{k}" for k in layers] + [f"direct-layer-{k}" for k in layers]
    )
    meta = rendered.meta
    assert meta["layers"] == layers and meta["bars"] == 2 * len(layers)
    per_layer = doc["summary"]["per_layer"]
    assert meta["tree"]["mean"] == [per_layer[str(k)]["mean"] for k in layers]
    assert meta["tree"]["p95"] == [per_layer[str(k)]["p95"] for k in layers]
    direct = doc["summary"]["direct"]["per_layer"]
    assert meta["direct"]["mean"] == [direct[str(k)]["mean"] for k in layers]
    png = render_summary(doc, fmt="png", width=640, height=360)
    assert png_image(png).shape == (360, 640, 3)


def test_summary_without_summary_or_direct_is_computed_from_subjects() -> None:
    doc = handmade()  # no "summary": statistics come from the subjects
    tree, direct = layer_statistics(doc)
    assert sorted(tree) == [2, 3, 4]
    assert tree[3]["count"] == 3 and tree[3]["mean"] == pytest.approx(0.004)
    assert direct[2]["mean"] == pytest.approx(0.0045)
    rendered = render_summary(doc, fmt="svg")
    assert len(bar_ids(rendered)) == 6 and rendered.meta["unattached"] == 2

    for s in doc["subjects"]:
        s["direct_error"] = None
    tree_only = render_summary(doc, fmt="svg")
    assert bar_ids(tree_only) == ["tree-layer-2", "tree-layer-3", "tree-layer-4"]
    assert tree_only.meta["direct"] is None


# --- rendering machinery ---------------------------------------------------------------------


def test_output_is_deterministic_and_thread_safe(real: dict[str, Any]) -> None:
    doc = real["document"]
    expected = [render_tree(doc, fmt=f).data for f in ("svg", "png")]
    results: list[list[bytes]] = []

    def work() -> None:
        results.append([render_tree(doc, fmt=f).data for f in ("svg", "png")])

    threads = [threading.Thread(target=work) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == [expected] * 3


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="png' or 'svg"):
        render_tree(handmade(), fmt="gif")
    with pytest.raises(ValueError, match="outside"):
        render_summary(handmade(), width=5)
    with pytest.raises(ValueError, match="root_shape_id"):
        render_tree({"subjects": []})


def test_subject_default_height_follows_the_shape() -> None:
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    wide = np.c_[100 * np.cos(t), 40 * np.sin(t)]
    tall = wide[:, ::-1]
    subject = {"shape_id": 1, "name": "s", "layer": 2, "warped": wide.tolist(), "error": 0.0}
    short_png = render_subject(subject, wide, width=600)
    tall_png = render_subject({**subject, "warped": tall.tolist()}, tall, width=600)
    assert short_png.height < tall_png.height
    assert png_image(short_png).shape[:2] == (short_png.height, 600)

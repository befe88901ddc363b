"""Short reprs for notebooks: a result prints its summary, not its arrays."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np

from registration import build_dynamic_tree, cpd_nonrigid
from registration.synthetic import chained_family


def test_results_print_a_short_summary() -> None:
    fam = chained_family(n_chains=3, chain_length=3, n_points=200, seed=4)
    result = build_dynamic_tree(fam.shapes, root=0, compare_direct=True)
    text = repr(result)
    # the generated repr printed every array: about 17 kB per point per subject
    assert len(text) < 400, len(text)
    summary = result.summary()
    assert f"{summary['subjects']} subjects: {summary['attached']} attached" in text
    assert "direct layer>=3" in text and "dynamic_tree" in text
    for s in result.subjects:
        assert len(repr(s)) < 250 and f"index={s.index}" in repr(s)
        assert "<200 points>" in repr(s)
        assert len(repr(s.transform)) < 200 and str(s.transform.path) in repr(s.transform)
    assert "unattached" in repr(type(result.subjects[0])(index=9, name="x"))

    reg = cpd_nonrigid(fam.shapes[0], fam.shapes[1])
    assert len(repr(reg)) < 200 and f"iterations={reg.iterations}" in repr(reg)
    assert len(repr(reg.transform)) < 200 and "<200 points>" in repr(reg.transform)


def test_html_repr_has_the_summary_and_the_tree() -> None:
    fam = chained_family(n_chains=2, chain_length=3, n_points=60, seed=5)
    result = build_dynamic_tree(fam.shapes, root=0)
    page = result._repr_html_()
    assert len(page) < 20_000
    svg = re.search(r"<svg.*</svg>", page, re.S)
    assert svg is not None
    drawing = ET.fromstring(svg.group(0))  # well-formed
    ns = "{http://www.w3.org/2000/svg}"
    assert len(drawing.findall(f"{ns}circle")) == len(fam.shapes)  # root + every subject
    attached = sum(1 for s in result.subjects if s.attached)
    assert len(drawing.findall(f"{ns}line")) == attached  # one edge per attached subject
    titles = [c.find(f"{ns}title").text for c in drawing.findall(f"{ns}circle")]  # type: ignore[union-attr]
    assert any("(root)" in (t or "") for t in titles)
    subject_page = result.subjects[0]._repr_html_()
    assert "<table>" in subject_page and result.subjects[0].name in subject_page
    assert np.isfinite(result.subjects[0].error)

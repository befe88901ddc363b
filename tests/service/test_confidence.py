"""Per-subject confidence and low-confidence leaves: sorting and filtering a result's subjects
over HTTP, through the Python client and ``regtree results``, and how the pictures mark leaves.

A job with a tiny explicit ``error_threshold`` makes every subject a low-confidence leaf (the
tree accepts none; each gets its best registration from the model), with distinct
confidences: a quick way to a result with leaves.
"""

from __future__ import annotations

import math
import re
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from service.api.routes.results import SUBJECT_SORTS, select_subjects
from service.client import SUBJECT_SORTS as CLIENT_SORTS
from service.client import RegtreeClient, ValidationError
from service.plots import render_subject, render_tree
from tests.service.conftest import (
    Service,
    assert_problem,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)
from tests.service.test_cli_client import regtree
from tests.service.test_plots import SVG, document_subject, handmade, svg_group, svg_texts

LEAF_REASON = "low-confidence leaf: best of 2 registrations, from b; not accepted (e >= 1e-9)"


# --- the rule, on its own ----------------------------------------------------------------


def subjects_for_sorting() -> list[dict[str, Any]]:
    return [
        {"shape_id": 10, "confidence": 0.5, "error": 0.003, "leaf": False},
        {"shape_id": 11, "confidence": None, "error": None, "leaf": False},  # unattached
        {"shape_id": 12, "confidence": 0.9, "error": 0.001, "leaf": False},
        {"shape_id": 13, "confidence": 0.2, "error": 0.004, "leaf": True},
        {"shape_id": 14, "error": 0.002},  # a result from before confidences
        {"shape_id": 15, "confidence": 0.5, "error": 0.003, "leaf": True},  # ties 10
    ]


def ids(subjects: list[Any]) -> list[int]:
    return [int(s["shape_id"]) for s in subjects]


def test_select_subjects_sorts_with_missing_values_last_and_filters() -> None:
    subjects = subjects_for_sorting()
    assert ids(select_subjects(subjects)) == [10, 11, 12, 13, 14, 15]
    assert ids(select_subjects(subjects, sort="confidence")) == [13, 10, 15, 12, 11, 14]
    assert ids(select_subjects(subjects, sort="-confidence")) == [12, 10, 15, 13, 11, 14]
    assert ids(select_subjects(subjects, sort="error")) == [12, 14, 10, 15, 13, 11]
    assert ids(select_subjects(subjects, sort="-error")) == [13, 10, 15, 14, 12, 11]
    # min_confidence leaves out subjects without one; the bound is inclusive
    assert ids(select_subjects(subjects, min_confidence=0.5)) == [10, 12, 15]
    assert ids(select_subjects(subjects, min_confidence=0.0)) == [10, 12, 13, 15]
    assert ids(select_subjects(subjects, leaf=True)) == [13, 15]
    assert ids(select_subjects(subjects, leaf=False)) == [10, 11, 12, 14]
    assert ids(select_subjects(subjects, leaf=True, min_confidence=0.3, sort="-confidence")) == [15]
    with pytest.raises(ValueError, match="sort must be one of"):
        select_subjects(subjects, sort="name")
    assert SUBJECT_SORTS == CLIENT_SORTS  # the client offers what the server takes


# --- over HTTP ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def jobs(service: Service) -> dict[str, Any]:
    """Two succeeded jobs on the same family: ``leaves`` (every subject a leaf) and ``tree``
    (the automatic threshold: no leaves)."""
    with service.client() as client:
        collection_id = create_collection(client, "confidence")
        shape_ids = upload_family(client, collection_id, family(n_chains=2, chain_length=3))
        leaves = submit_job(client, collection_id, shape_ids[0], error_threshold=1e-9)
        tree = submit_job(client, collection_id, shape_ids[0])
        for job in (leaves, tree):
            assert wait_job(client, job["id"])["status"] == "succeeded"
    return {
        "collection_id": collection_id,
        "shape_ids": shape_ids,
        "leaves": leaves["id"],
        "tree": tree["id"],
    }


def result(client: httpx.Client, job_id: int, **params: Any) -> dict[str, Any]:
    response = client.get(f"/v1/jobs/{job_id}/result", params=params)
    assert response.status_code == 200, response.text
    document: dict[str, Any] = response.json()
    return document


def test_result_subjects_carry_confidence_leaf_and_quality(
    client: httpx.Client, jobs: dict[str, Any]
) -> None:
    leaves = result(client, jobs["leaves"])
    summary = leaves["summary"]
    assert summary["leaves"] == len(leaves["subjects"]) == summary["subjects"] == 6
    assert summary["attached"] == 6 and summary["unattached"] == 0  # leaves count as attached
    for s in leaves["subjects"]:
        assert s["leaf"] is True and s["attached"] is True
        assert s["parent_shape_id"] == jobs["shape_ids"][0]  # from the model: never a parent
        assert s["reason"].startswith("low-confidence leaf")
        assert 0.0 <= s["confidence"] <= 1.0
        quality = s["quality"]  # the light document keeps the checks
        assert quality["confidence"] == pytest.approx(s["confidence"])
        for key in ("error_ratio", "distortion", "anisotropy", "coverage", "min_jacobian"):
            assert key in quality, key
        assert quality["pose"] in ("as given", "rotated", "aligned", "none")
        assert "warped" not in s and "transform" not in s
    tree = result(client, jobs["tree"])
    assert tree["summary"]["leaves"] == 0
    assert all(s["leaf"] is False and s["confidence"] is not None for s in tree["subjects"])
    # the subject route has them too
    one = leaves["subjects"][0]
    detail = client.get(f"/v1/jobs/{jobs['leaves']}/result/subjects/{one['shape_id']}").json()
    assert detail["leaf"] is True and detail["confidence"] == one["confidence"]


def test_result_subjects_sort_and_filter(client: httpx.Client, jobs: dict[str, Any]) -> None:
    job_id = jobs["leaves"]
    plain = result(client, job_id)
    by_position = plain["subjects"]
    assert [s["position"] for s in by_position] == sorted(s["position"] for s in by_position)
    assert result(client, job_id, sort="position") == plain

    confidences = [s["confidence"] for s in result(client, job_id, sort="confidence")["subjects"]]
    assert confidences == sorted(confidences) and len(confidences) == 6
    assert len(set(confidences)) > 1  # a real order, not a trivial one
    down = [s["confidence"] for s in result(client, job_id, sort="-confidence")["subjects"]]
    assert down == sorted(confidences, reverse=True)
    errors = [s["error"] for s in result(client, job_id, sort="error")["subjects"]]
    assert errors == sorted(errors)
    errors_down = [s["error"] for s in result(client, job_id, sort="-error")["subjects"]]
    assert errors_down == sorted(errors, reverse=True)

    middle = sorted(confidences)[3]
    kept = result(client, job_id, min_confidence=middle)
    assert sorted(s["confidence"] for s in kept["subjects"]) == sorted(confidences)[3:]
    assert [s["shape_id"] for s in kept["subjects"]] == [
        s["shape_id"] for s in by_position if s["confidence"] >= middle
    ]  # position order kept
    assert kept["summary"] == plain["summary"]  # the summary covers every subject
    assert result(client, job_id, min_confidence=1)["subjects"] == []
    assert len(result(client, job_id, min_confidence=0)["subjects"]) == 6

    assert len(result(client, job_id, leaf="true")["subjects"]) == 6
    assert result(client, job_id, leaf="false")["subjects"] == []
    tree = jobs["tree"]
    assert result(client, tree, leaf="true")["subjects"] == []
    assert len(result(client, tree, leaf="false")["subjects"]) == 6

    # with the heavy arrays: the same choice and order
    full = result(client, job_id, full="true", sort="-confidence", min_confidence=middle)
    assert [s["shape_id"] for s in full["subjects"]] == [
        s["shape_id"]
        for s in result(client, job_id, sort="-confidence", min_confidence=middle)["subjects"]
    ]
    assert all("warped" in s for s in full["subjects"])


@pytest.mark.parametrize(
    "params",
    [
        {"sort": "name"},
        {"sort": "confidence,error"},
        {"sort": ""},
        {"min_confidence": "1.5"},
        {"min_confidence": "-0.1"},
        {"min_confidence": "nan"},
        {"min_confidence": "inf"},
        {"min_confidence": "high"},
        {"leaf": "maybe"},
    ],
)
def test_result_bad_sort_or_filter_is_422(
    client: httpx.Client, jobs: dict[str, Any], params: dict[str, str]
) -> None:
    response = client.get(f"/v1/jobs/{jobs['leaves']}/result", params=params)
    problem = assert_problem(response, 422)
    assert problem["type"] == "/problems/validation-error"
    assert next(iter(params)) in problem["detail"], problem


def test_openapi_documents_sort_and_filter(client: httpx.Client) -> None:
    operation = client.get("/openapi.json").json()["paths"]["/v1/jobs/{job_id}/result"]["get"]
    parameters = {p["name"]: p for p in operation["parameters"]}
    assert {"full", "min_confidence", "leaf", "sort"} <= set(parameters)
    sort = parameters["sort"]
    assert set(sort["schema"]["enum"]) == set(SUBJECT_SORTS)
    assert sort["schema"]["default"] == "position"
    assert "last" in sort["description"]
    confidence = parameters["min_confidence"]
    bounds = next(s for s in confidence["schema"]["anyOf"] if s.get("type") == "number")
    assert (bounds["minimum"], bounds["maximum"]) == (0, 1)
    assert "left out" in confidence["description"]
    assert "leaves" in parameters["leaf"]["description"]
    assert "422" in operation["responses"]
    assert "low-confidence leaf" in operation["description"]


# --- the Python client --------------------------------------------------------------------


def test_client_passes_sort_and_filter_through() -> None:
    seen: list[httpx.QueryParams] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.url.params)
        subject = {
            "shape_id": 2, "name": "b", "layer": 2, "attached": True, "parent_shape_id": 1,
            "confidence": 0.25, "leaf": True, "reason": LEAF_REASON, "quality": {"pose": "none"},
        }  # fmt: skip
        return httpx.Response(
            200, json={"job_id": 4, "method": "dynamic_tree", "root_shape_id": 1,
                       "subjects": [subject], "summary": {"leaves": 1}},
        )  # fmt: skip

    with RegtreeClient("http://x", transport=httpx.MockTransport(handler)) as rt:
        got = rt.result(4, min_confidence=0.25, sort="-confidence", leaf=True)
        rt.result(4)
        rt.result_document(4, full=True, sort="error", leaf=False, min_confidence=0)
    assert dict(seen[0]) == {"min_confidence": "0.25", "sort": "-confidence", "leaf": "true"}
    assert dict(seen[1]) == {}
    assert dict(seen[2]) == {
        "full": "true",
        "sort": "error",
        "leaf": "false",
        "min_confidence": "0.0",
    }
    subject = got.subjects[0]
    assert subject.confidence == 0.25 and subject.leaf is True and subject.attached
    assert subject.quality == {"pose": "none"} and got.leaves == [subject]


def test_client_result_queries_refuse_unknown_keywords() -> None:
    # one query definition (ResultQuery, SubjectQuery) for the three methods; a keyword
    # outside it is Python's TypeError, before any request
    def handler(request: httpx.Request) -> httpx.Response:
        raise AssertionError(f"no request expected: {request.url}")

    with RegtreeClient("http://x", transport=httpx.MockTransport(handler)) as rt:
        for method, bad in (("result", "min_conf"), ("result_document", "sorted"),
                            ("result_csv", "full")):
            with pytest.raises(TypeError, match=rf"^{method}\(\) got an unexpected keyword "
                                                rf"argument '{bad}'$"):
                getattr(rt, method)(4, **{bad: True})


def test_client_against_the_service(service: Service, jobs: dict[str, Any]) -> None:
    with RegtreeClient(service.base_url) as rt:
        everything = rt.result(jobs["leaves"])
        assert len(everything.leaves) == 6 and everything.summary["leaves"] == 6
        ordered = rt.result(jobs["leaves"], sort="-confidence", min_confidence=0.3)
        confidences = [s.confidence for s in ordered.subjects]
        assert confidences == sorted(confidences, reverse=True)  # type: ignore[type-var]
        assert all(c is not None and c >= 0.3 for c in confidences)
        assert rt.result(jobs["tree"], leaf=True).subjects == []
        with pytest.raises(ValidationError) as bad:
            rt.result(jobs["leaves"], sort="name")  # type: ignore[arg-type]
        assert bad.value.status == 422 and "sort" in (bad.value.detail or "")
        with pytest.raises(ValidationError):
            rt.result(jobs["leaves"], min_confidence=math.nan)


# --- regtree results ---------------------------------------------------------------------

ROW = re.compile(
    r"^\s*(\d+)\s+(\S+)\s+(\d+|-)\s+(\S+)\s+(\S+)\s+(\S+)\s+([\d.]+|-)\s+([\d.]+|-)"
    r"\s+(tree|leaf|unattached)$"
)


def table_rows(stdout: str) -> list[tuple[int, float | None, str]]:
    """(shape id, confidence, status) of each subject line (the disagreement column, which
    lies between the last two, is read by :func:`table_disagreements`)."""
    rows = []
    for line in stdout.splitlines():
        m = ROW.match(line)
        if m:
            rows.append((int(m[1]), None if m[7] == "-" else float(m[7]), m[9]))
    return rows


def table_disagreements(stdout: str) -> list[float | None]:
    """The disagreement column of each subject line."""
    return [None if m[8] == "-" else float(m[8])
            for m in map(ROW.match, stdout.splitlines()) if m]


def test_cli_results_table_sort_filter_and_pictures(
    service: Service, jobs: dict[str, Any], tmp_path: Path
) -> None:
    url = service.base_url
    job_id = jobs["leaves"]
    with RegtreeClient(url) as rt:
        subjects = rt.result(job_id).subjects

    plain = regtree("results", str(job_id), url=url)  # no --out: the tables only
    assert plain.returncode == 0, plain.stderr
    assert "6 attached (6 as low-confidence leaves), 0 unattached" in plain.stdout
    assert "subjects: 6" in plain.stdout and "confidence" in plain.stdout
    rows = table_rows(plain.stdout)
    assert [r[0] for r in rows] == [s.shape_id for s in subjects]  # position order
    assert all(status == "leaf" for _, _, status in rows)
    for (_, shown, _), s in zip(rows, subjects, strict=True):
        assert shown == pytest.approx(s.confidence, abs=5e-4)
    for shown_d, s in zip(table_disagreements(plain.stdout), subjects, strict=True):
        assert (shown_d is None) == (s.disagreement is None)
        if shown_d is not None:
            assert shown_d == pytest.approx(s.disagreement, abs=5e-5)
    assert "leaf: a low-confidence leaf" in plain.stdout
    assert not list(tmp_path.iterdir())  # nothing written

    threshold = sorted(s.confidence or 0 for s in subjects)[2]
    chosen = regtree(
        "results", str(job_id), "--sort=-confidence", "--min-confidence", f"{threshold:.6f}",
        "--only-leaves", url=url,
    )  # fmt: skip
    assert chosen.returncode == 0, chosen.stderr
    expected = sorted(
        (s for s in subjects if (s.confidence or 0) >= float(f"{threshold:.6f}")),
        key=lambda s: -(s.confidence or 0),
    )
    assert [r[0] for r in table_rows(chosen.stdout)] == [s.shape_id for s in expected]
    assert re.search(
        rf"subjects \(confidence >= [\d.]+; low-confidence leaves only; by confidence, "
        rf"descending\): {len(expected)} of 6",
        chosen.stdout,
    ), chosen.stdout
    none = regtree("results", str(job_id), "--no-leaves", url=url)
    assert none.returncode == 0 and table_rows(none.stdout) == []

    # the subject pictures follow the lines: the two least confident
    out = tmp_path / "least"
    least = regtree(
        "results", str(job_id), "--out", str(out), "--sort", "confidence", "--subjects", "2",
        url=url,
    )  # fmt: skip
    assert least.returncode == 0, least.stderr
    weakest = sorted(subjects, key=lambda s: s.confidence or 0)[:2]
    assert sorted(p.stem for p in (out / "subjects").iterdir()) == sorted(s.name for s in weakest)
    assert (out / "tree.svg").exists() and "leaf-edges" in (out / "tree.svg").read_text()
    assert len((out / "result.json").read_text()) > 0

    # "--sort -confidence" works as "--sort=-confidence" does
    spaced = regtree("results", str(job_id), "--sort", "-confidence", url=url)
    assert spaced.returncode == 0, spaced.stderr
    by_confidence = sorted(subjects, key=lambda s: -(s.confidence or 0))
    assert [r[0] for r in table_rows(spaced.stdout)] == [s.shape_id for s in by_confidence]

    usage_error(regtree("results", str(job_id), "--min-confidence", "2", url=url), "0 to 1")
    usage_error(regtree("results", str(job_id), "--min-confidence", "nan", url=url), "0 to 1")
    usage_error(regtree("results", str(job_id), "--sort", "name", url=url), "-confidence")
    usage_error(
        regtree("results", str(job_id), "--only-leaves", "--no-leaves", url=url), "not allowed"
    )


def usage_error(proc: subprocess.CompletedProcess[str], needle: str) -> None:
    """argparse's refusal: exit 2, usage and one ``regtree results: error:`` line."""
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and needle in errors[0], proc.stderr


# --- pictures ------------------------------------------------------------------------------


def with_leaves() -> dict[str, Any]:
    """The hand-made tree with two childless subjects turned into low-confidence leaves."""
    doc = handmade()
    for s in doc["subjects"]:
        s["confidence"] = None if s["layer"] is None else 0.9
        s["leaf"] = False
        if s["shape_id"] in (5, 7):
            s.update(leaf=True, confidence=0.3, reason=LEAF_REASON)
    return doc


def test_tree_marks_leaves_dashed_and_hollow_with_a_legend() -> None:
    rendered = render_tree(with_leaves(), fmt="svg")
    meta = rendered.meta
    assert meta["leaves"] == [5, 7]
    assert meta["legend"] == ["tree member", "low-confidence leaf (never a parent)"]
    nodes = {n["shape_id"]: n for n in meta["nodes"]}
    assert nodes[5]["leaf"] and nodes[7]["leaf"] and not nodes[4]["leaf"]
    assert nodes[5]["confidence"] == 0.3 and nodes[2]["confidence"] == 0.9
    assert [u["shape_id"] for u in meta["unattached"]] == [8, 9]  # still apart

    root = ET.fromstring(rendered.data)
    assert "(2 as leaves)" in " ".join(svg_texts(root))
    legend = svg_group(root, "legend")
    assert "low-confidence leaf (never a parent)" in svg_texts(legend)
    # a leaf's edge is dashed, a member's solid
    leaf_edges = svg_group(root, "leaf-edges").findall(f".//{SVG}path")
    member_edges = svg_group(root, "edges").findall(f".//{SVG}path")
    assert len(leaf_edges) == 2 and len(member_edges) == 4
    assert all("stroke-dasharray" in p.get("style", "") for p in leaf_edges)
    assert not any("stroke-dasharray" in p.get("style", "") for p in member_edges)
    # its node is hollow (no fill): the group holds both leaves' markers
    leaf_nodes = svg_group(root, "leaf-nodes")
    markers = leaf_nodes.findall(f".//{SVG}use") or leaf_nodes.findall(f".//{SVG}path")
    assert len(markers) >= 2
    styles = " ".join(
        (e.get("style") or "") for e in leaf_nodes.iter() if e.get("style") is not None
    )
    assert "fill: none" in styles
    # names stay in their node groups, so the page can make them clickable
    assert svg_texts(svg_group(root, "node-5")) == ["d"]
    assert svg_texts(svg_group(root, "node-7")) == ["f"]

    # no leaves: no legend and nothing dashed, as before
    plain = render_tree(handmade(), fmt="svg")
    assert plain.meta["leaves"] == [] and plain.meta["legend"] == []
    plain_root = ET.fromstring(plain.data)
    assert plain_root.find(f".//{SVG}g[@id='legend']") is None
    assert plain_root.find(f".//{SVG}g[@id='leaf-edges']") is None


def test_tree_png_with_leaves_is_drawn_at_the_size_asked() -> None:
    png = render_tree(with_leaves(), fmt="png", width=700, height=450)
    assert png.data.startswith(b"\x89PNG") and (png.width, png.height) == (700, 450)
    assert png.meta["leaves"] == [5, 7]


def test_subject_overlay_shows_confidence_and_a_leafs_reason() -> None:
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    points = np.c_[np.cos(t), 0.6 * np.sin(t)]
    subject = {
        **document_subject(5, "d", 3, 2, 0.004),
        "warped": (points * 1.01).tolist(),
        "correspondence": list(range(40)),
        "confidence": 0.3141,
        "leaf": True,
        "reason": LEAF_REASON,
    }
    panel = render_subject(subject, points, fmt="png").meta["panels"][0]
    assert panel["name"] == "tree" and panel["leaf"] is True and panel["confidence"] == 0.3141
    text = " ".join(panel["title"]["text"].split())
    assert "confidence 0.31" in text and "low-confidence leaf: best of 2" in text
    member = render_subject({**subject, "leaf": False}, points, fmt="png").meta["panels"][0]
    member_text = " ".join(member["title"]["text"].split())
    assert member["leaf"] is False and "confidence 0.31" in member_text
    assert "low-confidence leaf" not in member_text
    older = {k: v for k, v in subject.items() if k not in ("confidence", "leaf")}
    old_panel = render_subject(older, points, fmt="png").meta["panels"][0]
    assert old_panel["confidence"] is None and "confidence" not in old_panel["title"]["text"]


def test_tree_picture_route_marks_leaves(client: httpx.Client, jobs: dict[str, Any]) -> None:
    svg = client.get(f"/v1/jobs/{jobs['leaves']}/result/tree.svg")
    assert svg.status_code == 200, svg.text
    root = ET.fromstring(svg.content)
    svg_group(root, "leaf-edges")
    assert "low-confidence leaf (never a parent)" in svg_texts(svg_group(root, "legend"))
    plain = client.get(f"/v1/jobs/{jobs['tree']}/result/tree.svg")
    assert b'id="leaf-edges"' not in plain.content

"""Progress of real grouping jobs (issue 10, item 7): a ``grouping`` job reports stages that
:mod:`service.progress` weighs, so that the worker stores an overall fraction and a time left
as for a registration, and ``regtree watch`` (``regtree group --wait``) and the results page
show them. Through the library as the worker calls it, and through real HTTP."""

from __future__ import annotations

import io
import re
from typing import Any

import numpy as np
import pytest

from registration import SerialExecutor
from registration.impressions import draw_strokes, simulate_impressions
from service.client import JobStatus
from service.ingest import points_from_image
from service.jobs.grouping import run_grouping
from service.progress import (
    MIN_FRACTION_FOR_ETA,
    FractionTracker,
    Progress,
    grouping_weights,
    overall_fraction,
    phase_of,
    phase_weights,
)
from tests.service.conftest import create_collection
from tests.service.test_grouping_api import MOULDS, png
from tests.service.test_progress_real import _poll

#: Impressions per mould: 2 moulds x 4 = 8 instances.
PRINTS = 4


def _scans(seed: int) -> list[bytes]:
    rng = np.random.default_rng(seed)
    return [png(img) for strokes in MOULDS
            for img in simulate_impressions(draw_strokes(strokes, size=140, width=0.09),
                                            PRINTS, seed=rng)]  # fmt: skip


def _check_stages(events: list[tuple[str, int, int]], n: int, pairs: int) -> None:
    """The stages in the order the weights place them, each known, counting from 0 to its
    total; the totals match the instances (fields n, alignment two rounds of n, pairs the
    pairs the result says were aligned)."""
    stages = list(dict.fromkeys(s for s, _, _ in events))
    assert stages == list(phase_weights("grouping", compare_direct=False,
                                        coarse_to_fine=False)), stages  # fmt: skip
    expected = {"fields": n, "alignment": 2 * n, "pairs": pairs}
    for stage in stages:
        assert phase_of(stage, "grouping") == stage
        counts = [(d, t) for s, d, t in events if s == stage]
        assert {t for _, t in counts} == {expected[stage]}, (stage, counts)
        done = [d for d, _ in counts]
        assert done == sorted(done) and done[0] == 0 and done[-1] == expected[stage], done


def test_progress_events_of_a_real_grouping_job(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every progress event of a real grouping (the worker's library call), through the
    worker's tracker and through :class:`Progress` one second apart: the percentage only
    grows, stays below the cap until the last stage, ends near 100% and is 100% once the
    job succeeded; the time left is there from the first few percent."""
    shapes = [points_from_image(b, mode="contour", target_points=600) for b in _scans(7)]
    n = len(shapes)
    events: list[tuple[str, int, int]] = []
    doc = run_grouping(1, shapes, [f"s{k}" for k in range(n)], list(range(1, n + 1)), {},
                       executor=SerialExecutor(), progress=lambda *e: events.append(e))
    _check_stages(events, n, doc["pairs_computed"])

    tracker = FractionTracker("grouping", {}, n)
    stored = [tracker.update(*e) for e in events]
    assert all(f is not None for f in stored) and stored == sorted(stored)  # type: ignore[type-var]

    now = [0.0]
    monkeypatch.setattr("service.progress.time.monotonic", lambda: now[0])
    progress = Progress(1, io.StringIO(), tty=False)
    fractions = []
    for stage, done, total in events:
        now[0] += 1.0
        estimate = progress.estimate(_status("running", stage, done, total, n))
        assert estimate.fraction is not None
        fractions.append(estimate.fraction)
        if estimate.fraction >= MIN_FRACTION_FOR_ETA:
            assert estimate.remaining is not None and estimate.remaining > 0
        if stage != "pairs":
            assert estimate.fraction < 0.99, (stage, done, total)
    assert fractions == sorted(fractions) and fractions[0] == 0.0
    assert fractions[-1] >= 0.95, fractions[-1]
    assert progress.estimate(_status("succeeded", *events[-1], n)).fraction == 1.0


def test_grouping_weights_follow_the_rotations_tried() -> None:
    """The alignment weighs more when it tries starting rotations (``max_rotation``), the
    shares sum to 1, and a registration's ``max_rotation`` changes nothing of a tree's."""
    plain, turned = grouping_weights(None), grouping_weights(30.0)
    assert list(plain) == list(turned) == ["fields", "alignment", "pairs"]
    assert sum(plain.values()) == pytest.approx(1) and sum(turned.values()) == pytest.approx(1)
    assert turned["alignment"] / turned["fields"] == pytest.approx(
        2.3125 * plain["alignment"] / plain["fields"])
    assert grouping_weights(5.0) == plain  # no 10 degree step: one start, as without
    # the end of the alignment is where the pairs begin
    end = overall_fraction("grouping", "alignment", 60, 60, compare_direct=False,
                           max_rotation=30.0)  # fmt: skip
    assert end == pytest.approx(turned["fields"] + turned["alignment"])
    assert phase_weights("dynamic_tree", compare_direct=True, coarse_to_fine=False,
                         max_rotation=30.0) == phase_weights(
        "dynamic_tree", compare_direct=True, coarse_to_fine=False)


def _status(status: str, stage: str, done: int, total: int, n: int) -> JobStatus:
    return JobStatus.from_json({
        "id": 1, "collection_id": 1, "model_shape_id": 1, "method": "grouping",
        "status": status, "n_shapes": n, "params": {},
        "progress": {"stage": stage, "done": done, "total": total},
    })  # fmt: skip


# --- over HTTP ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def polled(service: Any) -> tuple[list[dict[str, Any]], dict[str, Any], Any]:
    """A grouping job of scans uploaded as PNGs, every state of it polled over HTTP, its
    groups document, and the service."""
    files = [("files", (f"p{k}.png", b, "image/png")) for k, b in enumerate(_scans(11))]
    with service.client() as client:
        cid = create_collection(client, "grouping progress")
        r = client.post(f"/v1/collections/{cid}/shapes", files=files,
                        data={"mode": "contour", "target_points": "600"})
        assert r.status_code == 201, r.text
        job = client.post("/v1/jobs", json={"collection_id": cid, "method": "grouping"})
        assert job.status_code == 202, job.text
        states = _poll(client, job.json()["id"])
        doc = client.get(f"/v1/jobs/{job.json()['id']}/groups").raise_for_status().json()
    assert states[-1]["status"] == "succeeded", states[-1]
    assert states[-1]["n_shapes"] == len(files)
    return states, doc, service


def test_grouping_progress_over_http(
    polled: tuple[list[dict[str, Any]], dict[str, Any], Any],
) -> None:
    """The job's ``progress`` carries the worker's overall ``fraction`` (never going back, 1
    at the end) and ``seconds_left`` once a few percent are done; ``regtree watch`` prints
    the instances, the stage with its unit and an overall percentage reaching 100%."""
    states, doc, _ = polled
    n = states[-1]["n_shapes"]
    running = [s for s in states if s["status"] == "running" and s["progress"]["stage"]]
    assert running, states
    totals = {"fields": n, "alignment": 2 * n, "pairs": doc["pairs_computed"]}
    for s in running:
        p = s["progress"]
        assert p["total"] == totals[p["stage"]], p
        assert p["fraction"] is not None and 0 <= p["fraction"] < 1, p
        if p["fraction"] >= MIN_FRACTION_FOR_ETA:
            assert p["seconds_left"] is not None and p["seconds_left"] >= 0, p
    fractions = [s["progress"]["fraction"] for s in running]
    assert fractions == sorted(fractions), fractions
    assert states[-1]["progress"]["fraction"] == 1.0
    assert states[-1]["progress"]["seconds_left"] is None

    out = io.StringIO()
    progress = Progress(int(states[0]["id"]), out, tty=False)
    for state in states:
        progress.update(JobStatus.from_json(state))
    lines = out.getvalue().splitlines()
    assert all(f"; {n} instances" in line for line in lines), lines
    overall = [int(m) for m in re.findall(r"overall (\d+)%", out.getvalue())]
    assert overall == sorted(overall) and overall[-1] == 100, lines
    units = {"fields": "instances", "alignment": "alignments", "pairs": "pairs"}
    for line in lines:
        m = re.search(r" running (fields|alignment|pairs) \d+/\d+ (\w+) ", line)
        if m:
            assert m[2] == units[m[1]], line


def test_the_results_page_shows_a_running_grouping_s_progress(
    polled: tuple[list[dict[str, Any]], dict[str, Any], Any], tmp_path: Any,
) -> None:
    """The results page, in Chromium, given a running state the grouping job really had
    (replayed for the job's URL): its bar at the overall fraction, the text with the
    overall percentage and the time left, as ``regtree watch`` shows them."""
    from urllib.parse import urlparse

    from playwright.sync_api import expect

    from tests.service.test_page_browser import open_browser

    states, _, service = polled
    job_id = int(states[0]["id"])
    shown = max((s for s in states if s["status"] == "running"
                 and s["progress"]["seconds_left"] is not None),
                key=lambda s: s["progress"]["fraction"])  # fmt: skip
    p = shown["progress"]
    with open_browser(tmp_path) as browser:
        page = browser.page
        page.route(lambda url: urlparse(url).path == f"/v1/jobs/{job_id}",
                   lambda route: route.fulfill(json=shown))
        page.goto(f"{service.base_url}/ui#/jobs/{job_id}")
        bar = page.locator("#ui-job-progressbar")
        expect(bar).to_be_visible(timeout=60_000)
        text = page.locator("#ui-job-progresstext")
        expect(text).to_contain_text(f"{p['stage']} {p['done']}/{p['total']}")
        expect(text).to_contain_text(f"overall {int(100 * p['fraction'])}%")
        expect(text).to_contain_text("left")
        assert bar.evaluate("b => b.value") == pytest.approx(p["fraction"])
        assert browser.errors == []

"""The results page's smaller promises, in Debian's Chromium driven by Playwright (issue 10,
item 10): names in a 40-shape tree readable at Fit, one number format, the job list naming
the collection and the model, and a clear state for a job id the service does not have.

Skipped without Chromium or Playwright, unless ``REGTREE_REQUIRE_BROWSER=1``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.service.conftest import Service, create_collection, submit_job, upload_family, wait_job
from tests.service.test_page_browser import Browser, open_browser

#: Smallest height (CSS px) of a shape's name in the fitted tree: 9 px text is small but
#: readable; the picture used to fit a 40-shape tree with 5.6 px upright names.
READABLE_PX = 9.0


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[Browser]:
    with open_browser(tmp_path) as b:
        yield b


def forty_glyphs() -> list[tuple[str, object]]:
    """41 generated outlines in five chains of eight, named like glyph instances."""
    from registration.synthetic import chained_family

    fam = chained_family(n_chains=5, chain_length=8, n_points=32, seed=4)
    return [
        ("model" if k == 0 else f"永_Song_{name}", points)
        for k, (name, points) in enumerate(zip(fam.names, fam.shapes, strict=True))
    ]


def test_page_states_readable_tree_names_and_numbers(
    browser: Browser, make_service: Callable[..., Service]
) -> None:
    from playwright.sync_api import expect

    page = browser.page
    svc = make_service(workers=1).start()
    with svc.client() as client:
        collection_id = create_collection(client, "forty glyphs")
        ids = upload_family(client, collection_id, forty_glyphs())
        job_id = submit_job(client, collection_id, ids[0], cpd={"max_iter": 40})["id"]
        assert wait_job(client, job_id, timeout=300)["status"] == "succeeded"
        result = client.get(f"/v1/jobs/{job_id}/result").json()
        job = client.get(f"/v1/jobs/{job_id}").json()
    assert job["collection_name"] == "forty glyphs" and job["model_name"] == "model"

    page.goto(f"{svc.base_url}/ui#/jobs/{job_id}")
    expect(page.locator("#ui-tree[data-render-ms]")).to_have_count(1, timeout=60_000)
    page.click("#ui-zoom-fit")
    page.wait_for_timeout(400)
    heights = page.evaluate(
        """() => [...document.querySelectorAll("#ui-tree-svg g.rt-node text")]
              .map((t) => t.getBoundingClientRect())
              .map((r) => Math.min(r.width, r.height))"""
    )
    attached = sum(s["attached"] for s in result["subjects"])
    assert len(heights) == attached + 1 >= 35
    assert min(heights) >= READABLE_PX, (min(heights), page.get_attribute("#ui-tree", "data-scale"))

    # the job list names what the job registered
    item = page.locator(f"#ui-jobs a[data-job-id='{job_id}'] [data-field=names]")
    expect(item).to_have_text("forty glyphs · model model")

    # one number format: D and e with three significant digits, in decimals
    rows = page.locator("#ui-subjects tbody tr")
    expect(rows).to_have_count(len(result["subjects"]))
    numbers = rows.locator("td.num").all_inner_texts()
    exponents = [t for t in numbers if "e" in t.lower()]
    decimals = [t for t in numbers if "." in t and t not in exponents]
    # exponents only below 1e-6
    assert decimals and all(abs(float(t)) < 1e-6 for t in exponents), numbers
    for text in decimals:
        digits = re.sub(r"^-?0\.0*", "", text).replace(".", "")
        assert len(digits) in (2, 3), text  # 3 significant digits (2: a confidence)
    for text in exponents:  # the mantissa's digits: 1.22e-8
        assert len(re.sub(r"[^0-9]", "", text.lower().split("e")[0])) <= 3, text

    # an unattached shape shows its best rejected attempt (the page is handed a result in
    # which one subject found no usable registration: today's tree attaches every one here)
    subject = result["subjects"][-1]
    members = [s for s in result["subjects"] if s["shape_id"] != subject["shape_id"]][:2]
    attempts = [
        {"member": m["position"], "member_shape_id": m["shape_id"], "layer": m["layer"],
         "error": e, "limit": 0.001, "accepted": False, "reason": f"e above its limit {k}"}
        for k, (m, e) in enumerate(zip(members, (0.0093, 0.0041), strict=True))
    ]  # fmt: skip
    unattached = {
        **subject, "attached": False, "status": "unattached", "layer": None, "parent": None,
        "parent_shape_id": None, "confidence": None, "leaf": False, "attempts": attempts,
        "reason": "no member gave a usable registration",
    }  # fmt: skip
    doctored = {
        **result, "subjects": [*result["subjects"][:-1], unattached],
    }  # fmt: skip
    page.route(f"**/v1/jobs/{job_id}/result", lambda route: route.fulfill(json=doctored))
    page.goto(f"{svc.base_url}/ui#/jobs/{job_id}/subjects/{subject['shape_id']}")
    page.reload()
    attempt = page.locator("#ui-subject-attempt")
    expect(attempt).to_be_visible(timeout=60_000)
    expect(attempt).to_contain_text("Best rejected attempt")
    expect(attempt).to_contain_text("e = 0.00410")  # the lower e of the two, as formatted
    expect(attempt).to_contain_text("e above its limit 1")
    expect(attempt).to_have_attribute("data-member", str(members[1]["shape_id"]))
    # ... and a tree member shows none
    page.goto(f"{svc.base_url}/ui#/jobs/{job_id}/subjects/{members[0]['shape_id']}")
    expect(page.locator("#ui-subject-title")).to_have_text(members[0]["name"])
    expect(attempt).to_be_hidden()
    page.unroute(f"**/v1/jobs/{job_id}/result")

    # a job id the service does not have: a clear state, with the way back
    page.goto(f"{svc.base_url}/ui#/jobs/{job_id + 100}")
    expect(page.locator("#ui-job-title")).to_have_text(f"No job {job_id + 100}")
    error = page.locator("#ui-job-error")
    expect(error).to_be_visible()
    expect(error).to_have_attribute("data-state", "not-found")
    expect(error).to_contain_text("This service has no job")
    expect(page.locator("#ui-result")).to_be_hidden()
    error.locator("a").click()
    expect(page.locator("#ui-welcome")).to_be_visible()
    # the one error allowed: the browser's own line for the 404 it was answered
    assert [e for e in browser.errors if "404" not in e] == []


def test_page_shows_a_grouping_job(browser: Browser, make_service: Callable[..., Service]) -> None:
    """A grouping job's view (service/static/grouping.js): its groups as a table, a click on
    a member shows it beside its representative, the gallery and the dendrogram load."""
    from playwright.sync_api import expect

    from registration.impressions import draw_strokes, simulate_impressions
    from tests.service.test_grouping_api import MOULDS, png

    page = browser.page
    svc = make_service(workers=1).start()
    rng = np.random.default_rng(5)
    files = []
    for k, strokes in enumerate(MOULDS):
        mould = draw_strokes(strokes, size=140, width=0.09)
        for j, img in enumerate(simulate_impressions(mould, 3, seed=rng)):
            files.append(("files", (f"m{k}_{j}.png", png(img), "image/png")))
    with svc.client() as client:
        cid = create_collection(client, "prints")
        r = client.post(f"/v1/collections/{cid}/shapes", files=files,
                        data={"mode": "contour", "target_points": "300"})  # fmt: skip
        assert r.status_code == 201, r.text
        response = client.post("/v1/jobs", json={"collection_id": cid, "method": "grouping"})
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        assert wait_job(client, job_id, timeout=300)["status"] == "succeeded"
        doc = client.get(f"/v1/jobs/{job_id}/groups").json()

    page.goto(f"{svc.base_url}/ui#/jobs/{job_id}")
    view = page.locator("#ui-grouping")
    expect(view).to_be_visible(timeout=60_000)
    expect(view.locator("table tbody tr")).to_have_count(len(doc["groups"]))
    expect(view.locator("figure img")).to_have_count(2, timeout=60_000)  # gallery, dendrogram
    member = doc["instances"][-1]
    view.locator("button.chip", has_text=member["name"]).click()
    compare = view.locator("figure").first
    expect(compare).to_contain_text(f"group {member['label']}")
    expect(compare.locator("img")).to_have_count(1, timeout=60_000)
    assert compare.locator("img").evaluate("img => img.src").startswith("blob:")
    expect(page.locator("#ui-result")).to_be_hidden()
    expect(page.locator("#ui-job-facts")).not_to_contain_text("model shape")
    expect(page.locator(f"#ui-jobs a[data-job-id='{job_id}'] [data-field=names]")).to_have_text(
        "prints · grouping by mould"
    )
    # leaving the job hides the view
    page.goto(f"{svc.base_url}/ui#/")
    expect(view).to_be_hidden()
    assert browser.errors == []

"""The results page in a real headless Chromium, driven by Playwright, against the real server.

The service has an API key and no worker at first, so the page must ask for the key, show the
job queued, follow it live once a worker starts, draw the tree, and open a subject's overlay
and numbers when a tree node is clicked.

Needs Debian's ``chromium`` (``/usr/bin/chromium``, or ``REGTREE_CHROMIUM``) and the
``playwright`` Python package (its own browser download is not used); skipped without them,
unless ``REGTREE_REQUIRE_BROWSER=1`` (CI), where their absence fails the test.
Set ``REGTREE_SCREENSHOT_DIR=docs`` to write the README's ``results-page.png`` there (1440 x
1000); the test then registers the bundled demo collection (``service/demo/chained_family.npz``,
16 shapes in three chains, a tree seven layers deep), which shows what the tree is for far
better than the small family used otherwise (which keeps the test quick). Without it the
screenshot goes to the test's temporary directory.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import pytest

from tests.service.conftest import (
    REPO,
    Service,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)

KEY = "page-s3cret"
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def chromium_path() -> str | None:
    configured = os.environ.get("REGTREE_CHROMIUM")
    if configured:
        return configured if Path(configured).exists() else None
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclass
class Browser:
    page: Any  # playwright.sync_api.Page
    errors: list[str]  # uncaught page errors and console errors


def missing(reason: str) -> NoReturn:
    """Skip, or fail where the browser is required (CI sets REGTREE_REQUIRE_BROWSER=1)."""
    if os.environ.get("REGTREE_REQUIRE_BROWSER", "") not in ("", "0"):
        pytest.fail(f"REGTREE_REQUIRE_BROWSER is set but {reason}")
    pytest.skip(reason)


@contextmanager
def open_browser(tmp_path: Path) -> Iterator[Browser]:
    """Debian's Chromium under Playwright, 1440 x 1000, collecting page and console errors
    (skips, or fails under REGTREE_REQUIRE_BROWSER=1, when either is missing)."""
    try:
        from playwright import sync_api
    except ImportError:
        missing("playwright is not installed (pip install playwright; no browser download)")
    executable = chromium_path()
    if executable is None:
        missing("Chromium is not installed (apt-get install -y chromium)")
    with sync_api.sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            str(tmp_path / "chromium-profile"),
            executable_path=executable,
            args=CHROMIUM_FLAGS,
            headless=True,
            viewport={"width": 1440, "height": 1000},
        )
        context.set_default_timeout(30_000)
        page = context.pages[0] if context.pages else context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(f"page error: {e}"))
        page.on(
            "console",
            lambda m: (
                errors.append(f"console: {m.text}")
                if m.type == "error" and "401" not in m.text  # the first, keyless calls
                else None
            ),
        )
        try:
            yield Browser(page, errors)
        finally:
            context.close()


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[Browser]:
    with open_browser(tmp_path) as b:
        yield b


DEMO = REPO / "service" / "demo" / "chained_family.npz"


def for_readme() -> bool:
    return bool(os.environ.get("REGTREE_SCREENSHOT_DIR"))


def collection() -> tuple[str, list[tuple[str, np.ndarray]]]:
    """The collection to register: the bundled demo for the README's screenshot (the model
    first), else a small family."""
    if for_readme():
        with np.load(DEMO, allow_pickle=False) as npz:
            return "chained family", [(name, npz[name]) for name in npz.files]
    return "glyph family", family(n_chains=2, chain_length=3, n_points=60)


def screenshot_path(tmp_path: Path) -> Path:
    folder = os.environ.get("REGTREE_SCREENSHOT_DIR")
    path = Path(folder) if folder else tmp_path
    path.mkdir(parents=True, exist_ok=True)
    return path / "results-page.png"


def test_results_page_end_to_end(
    browser: Browser, make_service: Callable[..., Service], tmp_path: Path
) -> None:
    from playwright.sync_api import expect

    page = browser.page
    # a page size below what the page asks for (500): it must fall back to the default
    env = {"REGTREE_API_KEY": KEY, "REGTREE_MAX_PAGE_SIZE": "40"}
    svc = make_service(workers=0, env=env).start()
    with svc.client(headers={"X-API-Key": KEY}) as client:
        title, shapes = collection()
        collection_id = create_collection(client, title)
        ids = upload_family(client, collection_id, shapes)
        job_id = submit_job(client, collection_id, ids[0], compare_direct=True)["id"]

        # the page itself is public; the API asks for the key, which the page then keeps
        page.goto(f"{svc.base_url}/ui")
        expect(page.locator("#ui-key-form")).to_be_visible()
        page.fill("#ui-key-input", KEY)
        page.click("#ui-key-form button[type=submit]")
        expect(page.locator("#ui-key-form")).to_be_hidden()
        assert page.evaluate("sessionStorage.getItem('regtree.apiKey')") == KEY

        # collections, then the collection's jobs, then the job: queued, nothing runs it yet
        page.click(f"#ui-collections a[data-collection-id='{collection_id}']")
        expect(page.locator("#ui-jobs-title")).to_have_text(f"Jobs of {title}")
        page.click(f"#ui-jobs a[data-job-id='{job_id}']")
        expect(page.locator("#ui-job-status [data-status]")).to_have_attribute(
            "data-status", "queued"
        )
        expect(page.locator("#ui-job-progress")).to_be_visible()
        expect(page.locator("#ui-result")).to_be_hidden()

        # a worker starts: the page follows the job by polling and draws the result
        svc.start_worker()
        expect(page.locator("#ui-job-status [data-status]")).to_have_attribute(
            "data-status", "succeeded", timeout=180_000
        )
        result = client.get(f"/v1/jobs/{job_id}/result").json()
        assert wait_job(client, job_id)["status"] == "succeeded"

    attached = [s for s in result["subjects"] if s["attached"]]
    nodes = page.locator("#ui-tree-svg g.rt-node")
    expect(nodes).to_have_count(len(attached) + 1)  # attached subjects and the model
    for s in result["subjects"]:
        # unattached shapes are listed under the tree, as buttons
        where = "#ui-tree-svg g.rt-node" if s["attached"] else "#ui-unattached-list button"
        expect(page.locator(f"{where}[data-shape-id='{s['shape_id']}']")).to_have_count(1)
    expect(page.locator("#ui-subjects tbody tr")).to_have_count(len(result["subjects"]))
    expect(page.locator("#ui-summary")).to_be_visible()

    # click a shape in the tree (the one the tree helps most, for the screenshot): its overlay
    # and its numbers appear
    subject = max(attached, key=lambda s: (s["direct_error"] / max(s["error"], 1e-12), s["layer"]))
    sid = subject["shape_id"]
    page.click(f"#ui-tree-svg g.rt-node[data-shape-id='{sid}']")
    assert page.url.endswith(f"#/jobs/{job_id}/subjects/{sid}")
    overlay = page.locator(f"#ui-overlay[data-shape-id='{sid}']")
    expect(overlay).to_be_visible(timeout=60_000)
    width = overlay.evaluate("img => img.naturalWidth")
    assert 700 <= width <= 1600
    assert overlay.evaluate("img => img.src").startswith("blob:")
    expect(page.locator("#ui-subject-title")).to_have_text(subject["name"])
    numbers = page.locator("#ui-subject-numbers")
    expect(numbers.locator("[data-field=layer]")).to_have_text(str(subject["layer"]))
    parent_name = next(
        n for i, n in zip(result["shape_ids"], result["names"], strict=True)
        if i == subject["parent_shape_id"]
    )  # fmt: skip
    expect(numbers.locator("[data-field=parent]")).to_contain_text(parent_name)
    for field in ("similarity", "error", "direct_error"):
        text = numbers.locator(f"[data-field={field}]").inner_text()
        assert text and text != "–", (field, text)
    shown_e = float(numbers.locator("[data-field=error]").inner_text())
    assert shown_e == pytest.approx(subject["error"], rel=0.01)
    shown_direct = float(numbers.locator("[data-field=direct_error]").inner_text().split()[0])
    assert shown_direct == pytest.approx(subject["direct_error"], rel=0.01)
    expect(page.locator(f"#ui-tree-svg g.rt-node.selected[data-shape-id='{sid}']")).to_have_count(1)
    expect(page.locator(f"#ui-subjects tr.selected[data-shape-id='{sid}']")).to_have_count(1)

    page.evaluate("window.scrollTo(0, 0)")
    page.screenshot(path=str(screenshot_path(tmp_path)))

    # downloads go through the API with the key too
    with page.expect_download() as info:
        page.click("a[data-download='tree.svg']")
    download = info.value
    assert download.suggested_filename == f"regtree-job-{job_id}-tree.svg"
    svg_text = Path(download.path()).read_text()
    assert all(s["name"] in svg_text for s in result["subjects"])

    # the parent link in the numbers opens the parent; a table row opens its subject
    numbers.locator("[data-field=parent] a").click()
    expect(
        page.locator(f"#ui-overlay[data-shape-id='{subject['parent_shape_id']}']")
    ).to_be_visible(timeout=60_000)
    other = next(s for s in result["subjects"] if s["shape_id"] not in (sid,))
    page.click(f"#ui-subjects tr[data-shape-id='{other['shape_id']}']")
    expect(page.locator("#ui-subject-title")).to_have_text(other["name"])

    # a deep link in a reloaded tab opens the subject at once, with the key kept for the tab
    page.goto(f"{svc.base_url}/ui#/jobs/{job_id}/subjects/{sid}")
    page.reload()
    expect(page.locator(f"#ui-overlay[data-shape-id='{sid}']")).to_be_visible(timeout=60_000)
    expect(page.locator("#ui-key-form")).to_be_hidden()

    assert browser.errors == []


def test_results_page_confidence_and_leaves(
    browser: Browser, make_service: Callable[..., Service]
) -> None:
    """A job whose every subject is a low-confidence leaf (a tiny error threshold): the page
    marks them in the tree, the table and the subject card, and sorts and filters by
    confidence."""
    from playwright.sync_api import expect

    page = browser.page
    svc = make_service(workers=1).start()
    with svc.client() as client:
        collection_id = create_collection(client, "leaves")
        ids = upload_family(client, collection_id, family(n_chains=2, chain_length=3))
        job_id = submit_job(client, collection_id, ids[0], error_threshold=1e-9)["id"]
        assert wait_job(client, job_id)["status"] == "succeeded"
        result = client.get(f"/v1/jobs/{job_id}/result").json()
    subjects = result["subjects"]
    assert subjects and all(s["leaf"] for s in subjects)

    page.goto(f"{svc.base_url}/ui#/jobs/{job_id}")
    rows = page.locator("#ui-subjects tbody tr")
    expect(rows).to_have_count(len(subjects))
    expect(page.locator("#ui-subjects tbody tr.leaf")).to_have_count(len(subjects))
    expect(page.locator("#ui-subjects tbody .badge.leaf").first).to_have_text("low-confidence leaf")
    expect(page.locator("#ui-job-facts")).to_contain_text("low-confidence leaves")
    # leaves are in the tree (attached), marked
    expect(page.locator("#ui-tree-svg g.rt-node.rt-leaf")).to_have_count(len(subjects))
    expect(page.locator("#ui-tree-svg g#leaf-edges")).to_have_count(1)
    expect(page.locator("#ui-unattached")).to_be_hidden()

    # sorted by confidence: a click on its header, the least confident first
    page.click("#ui-subjects th[data-sort='confidence']")
    shown = [float(t) for t in rows.locator("td:nth-child(8)").all_inner_texts()]
    assert shown == sorted(shown) and len(shown) == len(subjects)
    assert shown == pytest.approx(sorted(s["confidence"] for s in subjects), abs=0.006)

    # filtered: at least a confidence, then by status
    threshold = sorted(s["confidence"] for s in subjects)[3]
    expected = sum(1 for s in subjects if s["confidence"] >= round(threshold, 2))
    page.fill("#ui-subjects-min-confidence", f"{round(threshold, 2)}")
    expect(rows).to_have_count(expected)
    expect(page.locator("#ui-subjects-count")).to_have_text(
        f"{expected} of {len(subjects)} subjects"
    )
    page.fill("#ui-subjects-min-confidence", "")
    page.select_option("#ui-subjects-show", "tree")
    expect(rows).to_have_count(0)
    page.select_option("#ui-subjects-show", "leaf")
    expect(rows).to_have_count(len(subjects))

    # a leaf's card: its confidence, its status and its reason
    leaf = min(subjects, key=lambda s: s["confidence"])
    page.click(f"#ui-subjects tr[data-shape-id='{leaf['shape_id']}']")
    numbers = page.locator("#ui-subject-numbers")
    expect(numbers.locator("[data-field=status]")).to_have_text("low-confidence leaf")
    shown_confidence = float(numbers.locator("[data-field=confidence]").inner_text())
    assert shown_confidence == pytest.approx(leaf["confidence"], abs=0.006)
    expect(page.locator("#ui-subject-reason")).to_contain_text("low-confidence leaf")
    overlay = page.locator(f"#ui-overlay[data-shape-id='{leaf['shape_id']}']")
    expect(overlay).to_be_visible(timeout=60_000)
    assert overlay.evaluate("img => img.naturalWidth") >= 1100  # room for the reason
    assert browser.errors == []

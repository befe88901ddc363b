"""Picture routes against the real server: the pictures show the job's result (names in the
tree, PNGs that decode at the stated size), 409 before success, 404/410 as problem+json,
ETag revalidation, and the results page's files served without an API key."""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from service.plots.subject import WARPED_COLOUR
from tests.service.conftest import (
    Service,
    assert_problem,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)

SVG = "{http://www.w3.org/2000/svg}"


@pytest.fixture(scope="module")
def done(service: Service) -> dict[str, Any]:
    """A succeeded dynamic-tree job on a small chained family, compared with direct CPD."""
    with service.client() as client:
        collection_id = create_collection(client, "pictures")
        shapes = family(n_chains=2, chain_length=3, n_points=60)
        ids = upload_family(client, collection_id, shapes)
        job = submit_job(client, collection_id, ids[0], compare_direct=True)
        job = wait_job(client, job["id"], timeout=180)
        assert job["status"] == "succeeded", job
        result = client.get(f"/v1/jobs/{job['id']}/result").json()
    return {"job": job, "result": result, "ids": ids, "collection_id": collection_id}


def png(response: httpx.Response) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    assert response.content.startswith(b"\x89PNG\r\n\x1a\n")
    image = Image.open(io.BytesIO(response.content))
    image.load()
    width, height = (int(v) for v in response.headers["x-picture-size"].split("x"))
    assert image.size == (width, height)
    assert 200 <= width <= 4000 and 150 <= height <= 6000, image.size
    return np.asarray(image.convert("RGB")).astype(int)


def texts(element: ET.Element) -> list[str]:
    return ["".join(t.itertext()) for t in element.iter(f"{SVG}text")]


def red_pixels(image: np.ndarray) -> np.ndarray:
    rgb = np.array([int(WARPED_COLOUR[i : i + 2], 16) for i in (1, 3, 5)])
    return np.asarray(np.abs(image - rgb).max(axis=2) <= 40)


# --- the tree --------------------------------------------------------------------------------


def test_tree_svg_names_every_subject_in_its_place(client: httpx.Client, done: dict) -> None:
    job_id, result = done["job"]["id"], done["result"]
    response = client.get(f"/v1/jobs/{job_id}/result/tree.svg")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("image/svg+xml")
    assert response.headers["cache-control"] == "private, no-cache"
    assert response.headers["content-security-policy"].startswith("default-src 'none'")
    root = ET.fromstring(response.content)
    tree = root.find(f".//{SVG}g[@id='tree']")
    assert tree is not None
    tree_texts = texts(tree)
    attached = [s for s in result["subjects"] if s["attached"]]
    assert attached, "the family should chain"
    for s in result["subjects"]:
        group_id = f"node-{s['shape_id']}" if s["attached"] else f"unattached-{s['shape_id']}"
        group = root.find(f".//{SVG}g[@id='{group_id}']")
        assert group is not None, f"no clickable group for {s['name']}"
        assert texts(group) == [s["name"]]
        if s["attached"]:
            assert s["name"] in tree_texts
    model_name = result["names"][result["shape_ids"].index(result["root_shape_id"])]
    assert f"{model_name} (model)" in tree_texts
    assert root.find(f".//{SVG}g[@id='node-{result['root_shape_id']}']") is not None


def test_tree_png_and_summary_png_decode(client: httpx.Client, done: dict) -> None:
    job_id = done["job"]["id"]
    tree = png(client.get(f"/v1/jobs/{job_id}/result/tree.png"))
    assert (tree < 200).any(axis=2).sum() > 1000, "the tree picture is blank"
    wide = png(client.get(f"/v1/jobs/{job_id}/result/tree.png", params={"width": 1400}))
    assert wide.shape[1] == 1400
    summary = png(client.get(f"/v1/jobs/{job_id}/result/summary.png"))
    assert summary.shape[:2] == (520, 900)
    assert png(client.get(f"/v1/jobs/{job_id}/result/summary.png?width=700")).shape[1] == 700


# --- a subject -------------------------------------------------------------------------------


def test_overlay_shows_tree_and_direct_side_by_side(client: httpx.Client, done: dict) -> None:
    job_id, result = done["job"]["id"], done["result"]
    deepest = max((s for s in result["subjects"] if s["attached"]), key=lambda s: s["layer"])
    url = f"/v1/jobs/{job_id}/result/subjects/{deepest['shape_id']}/overlay.png"
    image = png(client.get(url, params={"width": 1000}))
    assert image.shape[1] == 1000
    red = red_pixels(image)
    half = image.shape[1] // 2
    # the warped model is drawn in both panels: the tree's on the left, direct CPD's right
    assert red[:, :half].sum() > 50 and red[:, half:].sum() > 50
    # the y direction is a choice: both ways give different pictures, the default one of them
    up = client.get(url, params={"width": 1000, "y_down": "false"})
    down = client.get(url, params={"width": 1000, "y_down": "true"})
    assert up.content != down.content
    assert client.get(url, params={"width": 1000}).content in (up.content, down.content)


def test_overlay_of_every_subject(client: httpx.Client, done: dict) -> None:
    job_id, result = done["job"]["id"], done["result"]

    def fetch(shape_id: int) -> httpx.Response:
        return client.get(f"/v1/jobs/{job_id}/result/subjects/{shape_id}/overlay.png?width=600")

    # concurrent requests share the thread pool and the plots' lock; none fails
    with ThreadPoolExecutor(4) as pool:
        responses = list(pool.map(fetch, [s["shape_id"] for s in result["subjects"]]))
    for response in responses:
        assert png(response).shape[1] == 600


# --- caching ---------------------------------------------------------------------------------


def test_etag_revalidation(client: httpx.Client, done: dict) -> None:
    job_id = done["job"]["id"]
    url = f"/v1/jobs/{job_id}/result/tree.svg"
    first = client.get(url)
    etag = first.headers["etag"]
    assert etag.startswith('"') and etag.endswith('"')
    assert client.get(url).headers["etag"] == etag  # stable: the result never changes
    again = client.get(url, headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.content == b""
    assert again.headers["etag"] == etag
    assert client.get(url, headers={"If-None-Match": f'"x", W/{etag}'}).status_code == 304
    assert client.get(url, headers={"If-None-Match": '"other"'}).status_code == 200
    # another format or size is another picture, with another tag
    tags = {
        etag,
        client.get(f"/v1/jobs/{job_id}/result/tree.png").headers["etag"],
        client.get(f"/v1/jobs/{job_id}/result/tree.svg?width=900").headers["etag"],
        client.get(f"/v1/jobs/{job_id}/result/summary.png").headers["etag"],
    }
    assert len(tags) == 4


# --- errors ----------------------------------------------------------------------------------


def test_unknown_ids_are_404_problems(client: httpx.Client, done: dict) -> None:
    job_id, result = done["job"]["id"], done["result"]
    for path in ("tree.svg", "tree.png", "summary.png", "subjects/1/overlay.png"):
        body = assert_problem(client.get(f"/v1/jobs/999999/result/{path}"), 404)
        assert body["type"] == "/problems/not-found"
    missing = max(result["shape_ids"]) + 1000
    body = assert_problem(
        client.get(f"/v1/jobs/{job_id}/result/subjects/{missing}/overlay.png"), 404
    )
    assert str(missing) in body["detail"]
    # the model is the root of the tree, not a subject
    root = result["root_shape_id"]
    assert_problem(client.get(f"/v1/jobs/{job_id}/result/subjects/{root}/overlay.png"), 404)
    assert_problem(client.get(f"/v1/jobs/{job_id}/result/tree.gif"), 404)
    assert_problem(client.get(f"/v1/jobs/{job_id}/result/tree.png?width=5"), 422)


def test_409_until_the_job_has_succeeded(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0).start()  # no worker: the job stays queued
    with svc.client() as client:
        collection_id = create_collection(client)
        ids = upload_family(client, collection_id, family(n_chains=1, chain_length=2))
        job = submit_job(client, collection_id, ids[0])
        for path in ("tree.svg", "tree.png", "summary.png", f"subjects/{ids[1]}/overlay.png"):
            body = assert_problem(client.get(f"/v1/jobs/{job['id']}/result/{path}"), 409)
            assert body["type"] == "/problems/result-not-ready"
            assert "queued" in body["detail"]


def test_overlay_of_a_deleted_shape_is_410(client: httpx.Client) -> None:
    collection_id = create_collection(client, "deleted")
    ids = upload_family(client, collection_id, family(n_chains=1, chain_length=2, n_points=40))
    job = wait_job(client, submit_job(client, collection_id, ids[0])["id"], timeout=120)
    assert job["status"] == "succeeded", job
    url = f"/v1/jobs/{job['id']}/result/subjects/{ids[-1]}/overlay.png"
    png(client.get(url))
    assert client.delete(f"/v1/collections/{collection_id}/shapes/{ids[-1]}").status_code == 204
    body = assert_problem(client.get(url), 410)
    assert body["type"] == "/problems/shape-deleted"
    png(client.get(f"/v1/jobs/{job['id']}/result/tree.png"))  # the tree does not need it


# --- the page and the API key ----------------------------------------------------------------


def test_page_files_are_public_and_pictures_need_the_key(
    make_service: Callable[..., Service],
) -> None:
    svc = make_service(workers=0, env={"REGTREE_API_KEY": "s3cret"}).start()
    with svc.client() as client:
        page = client.get("/ui")
        assert page.status_code == 200
        assert page.headers["content-type"].startswith("text/html")
        assert "default-src 'self'" in page.headers["content-security-policy"]
        html = page.text
        for asset, media_type in (
            ("/ui/app.js", "text/javascript"),
            ("/ui/app.css", "text/css"),
            ("/ui/favicon.svg", "image/svg+xml"),
        ):
            assert asset in html
            response = client.get(asset)
            assert response.status_code == 200, asset
            assert response.headers["content-type"].startswith(media_type)
        assert "http://" not in html and "https://" not in html  # nothing from elsewhere
        assert "X-API-Key" in client.get("/ui/core.js").text
        # the entry's modules are served, each as JavaScript
        from service.api.routes.pages import SCRIPTS

        for name in SCRIPTS:
            module = client.get(f"/ui/{name}")
            assert module.status_code == 200 and "javascript" in module.headers["content-type"]
        root = client.get("/", follow_redirects=False)
        assert root.status_code == 307 and root.headers["location"] == "/ui"
        # only the page's own files are public
        assert_problem(client.get("/ui/nothing.js"), 401)
        assert_problem(client.get("/ui/nothing.js", headers={"X-API-Key": "s3cret"}), 404)
        assert_problem(client.get("/v1/jobs/1/result/tree.svg"), 401)
        assert_problem(
            client.get("/v1/jobs/1/result/tree.svg", headers={"X-API-Key": "s3cret"}), 404
        )
        # the page is not part of the API's schema; the pictures are
        paths = client.get("/openapi.json").json()["paths"]
        assert "/ui" not in paths and "/" not in paths
        assert "/v1/jobs/{job_id}/result/subjects/{shape_id}/overlay.png" in paths


def test_a_name_no_font_can_draw_is_reported_in_a_header() -> None:
    """Characters without any installed font come out as boxes: the response says which."""
    from service.api.picture_cache import picture_response as _picture
    from service.plots import render_tree
    from tests.service.test_plots_cjk import document

    doc = document()
    doc["names"] = ["\U00013000" + n for n in doc["names"]]  # Egyptian hieroglyph A001
    for s in doc["subjects"]:
        s["name"] = "\U00013000" + s["name"]
    rendered = render_tree(doc, fmt="png")
    assert "\U00013000" in rendered.meta["missing_glyphs"]
    response = _picture(rendered, '"tag"')
    assert "U+13000" in response.headers["X-Missing-Glyphs"].split()

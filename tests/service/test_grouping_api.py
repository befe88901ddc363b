"""A grouping job over real HTTP (issue 11): scans uploaded as PNGs, grouped by mould, the
groups document, the pictures, and the refusals."""

from __future__ import annotations

import io
import json
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from registration.impressions import draw_strokes, simulate_impressions
from tests.service.conftest import assert_problem, create_collection, submit_job, wait_job

MOULDS = [
    [[0.2, 0.25, 0.8, 0.25], [0.5, 0.25, 0.5, 0.85], [0.25, 0.6, 0.75, 0.6]],
    [[0.15, 0.5, 0.85, 0.5], [0.5, 0.15, 0.5, 0.85], [0.2, 0.2, 0.4, 0.35]],
]


def png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


@pytest.fixture(scope="module")
def grouped(service: Any) -> dict[str, Any]:
    """Two moulds x 3 impressions uploaded as PNGs, grouped; ids by mould."""
    rng = np.random.default_rng(5)
    files, truth = [], []
    for k, strokes in enumerate(MOULDS):
        mould = draw_strokes(strokes, size=140, width=0.09)
        for j, img in enumerate(simulate_impressions(mould, 3, seed=rng)):
            files.append(("files", (f"m{k}_{j}.png", png(img), "image/png")))
            truth.append(k)
    with service.client() as client:
        cid = create_collection(client, "prints")
        r = client.post(f"/v1/collections/{cid}/shapes", files=files,
                        data={"mode": "contour", "target_points": "600"})
        assert r.status_code == 201, r.text
        ids = [int(i["id"]) for i in r.json()["items"]]
        response = client.post("/v1/jobs", json={"collection_id": cid, "method": "grouping"})
        assert response.status_code == 202, response.text
        job = wait_job(client, response.json()["id"], timeout=240)
    return {"cid": cid, "ids": ids, "truth": truth, "job": job}


def test_a_grouping_job_groups_uploaded_scans_by_mould(grouped, client: httpx.Client):
    job = grouped["job"]
    assert job["status"] == "succeeded", job
    assert job["method"] == "grouping"
    assert job["model_shape_id"] is None and job["model_name"] is None  # no model
    assert job["progress"]["stage"] in ("fields", "alignment", "pairs")
    doc = client.get(f"/v1/jobs/{job['id']}/groups").json()
    ids, truth = grouped["ids"], grouped["truth"]
    assert doc["kind"] == "grouping" and doc["shape_ids"] == ids
    labels = [doc["labels"][str(i)] for i in ids]
    assert labels[:3] == [labels[0]] * 3 and labels[3:] == [labels[3]] * 3
    assert labels[0] != labels[3] and doc["n_groups"] == 2
    for g in doc["groups"]:
        assert g["representative_shape_id"] in g["shape_ids"]
        assert {truth[ids.index(s)] for s in g["shape_ids"]} in ({0}, {1})
    assert all(0 < i["confidence"] <= 1 for i in doc["instances"])
    D = np.asarray(doc["distances"])
    assert D.shape == (6, 6) and np.allclose(D, D.T)
    assert len(doc["linkage"]) == 5


def test_a_grouping_has_no_registration_result_and_a_registration_no_groups(
        grouped, client: httpx.Client):
    job = grouped["job"]
    problem = assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 409)
    assert problem["type"] == "/problems/not-a-registration"
    assert f"/v1/jobs/{job['id']}/groups" in problem["detail"]
    for export in ("export.zip", "result.csv"):
        problem = assert_problem(client.get(f"/v1/jobs/{job['id']}/{export}"), 409)
        assert problem["type"] == "/problems/not-a-registration"


def test_a_grouping_given_a_model_still_has_none(grouped, client: httpx.Client):
    r = client.post("/v1/jobs", json={"collection_id": grouped["cid"], "method": "grouping",
                                      "model_shape_id": grouped["ids"][0]})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["model_shape_id"] is None and job["model_name"] is None
    client.post(f"/v1/jobs/{job['id']}/cancel")
    listed = client.get("/v1/jobs", params={"collection_id": grouped["cid"]}).json()["items"]
    assert {j["id"]: j["model_shape_id"] for j in listed}[job["id"]] is None


def test_a_registration_job_keeps_its_model(grouped, client: httpx.Client):
    job = submit_job(client, grouped["cid"], grouped["ids"][1], method="direct",
                     pose="as_given")
    client.post(f"/v1/jobs/{job['id']}/cancel")
    assert job["model_shape_id"] == grouped["ids"][1] and job["model_name"] == "m0_1"


@pytest.mark.parametrize("picture", ["gallery.png", "dendrogram.png"])
def test_group_pictures_are_pngs_with_etags(grouped, client: httpx.Client, picture):
    url = f"/v1/jobs/{grouped['job']['id']}/groups/{picture}"
    r = client.get(url)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert r.content[:8] == b"\x89PNG\r\n\x1a\n"
    again = client.get(url, headers={"If-None-Match": r.headers["etag"]})
    assert again.status_code == 304


def test_an_instance_beside_its_representative(grouped, client: httpx.Client):
    job_id, sid = grouped["job"]["id"], grouped["ids"][4]
    r = client.get(f"/v1/jobs/{job_id}/groups/instances/{sid}.png")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert_problem(client.get(f"/v1/jobs/{job_id}/groups/instances/999999.png"), 404)


@pytest.mark.parametrize(("body", "needle"), [
    ({"method": "dynamic_tree"}, "model_shape_id is required"),
    ({"method": "grouping", "group_threshold": -1}, "group_threshold"),
    ({"method": "direct", "model_shape_id": 1, "group_threshold": 0.1}, "grouping only"),
])
def test_bad_grouping_requests_are_422(grouped, client: httpx.Client, body, needle):
    problem = assert_problem(client.post("/v1/jobs", json={"collection_id": grouped["cid"],
                                                           **body}), 422)
    assert needle in str(problem)


def test_an_empty_collection_cannot_be_grouped(client: httpx.Client):
    cid = create_collection(client, "empty")
    problem = assert_problem(client.post("/v1/jobs", json={"collection_id": cid,
                                                           "method": "grouping"}), 422)
    assert "0 shape(s); a job needs at least two shapes" in problem["detail"]


def test_a_registration_job_has_no_groups(grouped, client: httpx.Client):
    job = submit_job(client, grouped["cid"], grouped["ids"][0], method="direct",
                     pose="as_given")
    client.post(f"/v1/jobs/{job['id']}/cancel")
    done = wait_job(client, job["id"])
    expected = 409
    problem = assert_problem(client.get(f"/v1/jobs/{job['id']}/groups"), expected)
    assert problem["type"] in ("/problems/not-a-grouping", "/problems/result-not-ready")
    assert done["status"] in ("succeeded", "cancelled")


def test_the_client_starts_a_grouping_and_reads_its_groups_and_pictures(grouped, service,
                                                                       tmp_path):
    from service.client import RegtreeClient

    with RegtreeClient(service.base_url) as rt:
        job = rt.wait(rt.start_grouping(grouped["cid"], threshold=10.0).id, timeout=240)
        assert job.model_shape_id is None and rt.get_job(job.id).model_shape_id is None
        doc = rt.groups(job.id)
        assert doc.n_groups == 1 and doc.threshold == 10.0
        assert doc.threshold_source == "given"
        data = rt.group_picture(job.id, "dendrogram", tmp_path / "d.png")
        assert data[:4] == b"\x89PNG" and (tmp_path / "d.png").read_bytes() == data
        assert rt.group_picture(job.id, grouped["ids"][1])[:4] == b"\x89PNG"


def test_regtree_group_prints_the_groups(grouped, service, tmp_path):
    from tests.service.test_cli_client import regtree

    proc = regtree("group", str(grouped["cid"]), "--gallery", str(tmp_path / "g.png"),
                   url=service.base_url, timeout=240)
    assert proc.returncode == 0, proc.stderr
    assert "2 groups of 6 shapes" in proc.stdout
    assert "representative" in proc.stdout and "m0_0" in proc.stdout
    assert (tmp_path / "g.png").read_bytes()[:4] == b"\x89PNG"
    proc = regtree("group", "prints", "--json", url=service.base_url, timeout=240)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["n_groups"] == 2


def test_a_running_grouping_is_cancelled_promptly(client: httpx.Client):
    from registration.impressions import impression_set
    from tests.registration.test_grouping import contour_points

    rng = np.random.default_rng(1)
    moulds = [draw_strokes(rng.uniform(0.15, 0.85, size=(3, 4)), size=120, width=0.1)
              for _ in range(8)]
    shapes, _ = impression_set(moulds, 5, to_points=lambda im: contour_points(im, 300), seed=2)
    cid = create_collection(client, "cancel-grouping")
    body = {"shapes": [{"name": f"s{k}", "points": p.tolist()} for k, p in enumerate(shapes)]}
    assert client.post(f"/v1/collections/{cid}/shapes", json=body).status_code == 201
    job = client.post("/v1/jobs", json={"collection_id": cid, "method": "grouping"}).json()
    wait_job(client, job["id"], timeout=120,
             until=lambda j: j["status"] != "queued" and (j["progress"] or {}).get("done", 0) > 0)
    response = client.post(f"/v1/jobs/{job['id']}/cancel")
    if response.status_code == 409:  # it finished first: nothing to cancel
        pytest.skip("the grouping finished before the cancel")
    done = wait_job(client, job["id"], timeout=60)
    assert done["status"] == "cancelled" and done["outcome"] == "aborted", done
    assert_problem(client.get(f"/v1/jobs/{job['id']}/groups"), 409)

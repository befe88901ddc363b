"""``/v1/jobs/{id}/result/*.png|svg`` (service/api/routes/pictures.py), in process."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.service.conftest import (
    assert_problem,
    circle,
    create_collection,
    submit_job,
    upload_family,
)
from tests.service.routes.conftest import Finished

PNG = b"\x89PNG\r\n\x1a\n"


def test_tree_and_summary_pictures(finished: Finished) -> None:
    client, base = finished.client, f"/v1/jobs/{finished.job_id}/result"
    svg = client.get(f"{base}/tree.svg")
    assert svg.status_code == 200
    assert svg.headers["content-type"].startswith("image/svg+xml")
    assert svg.text.lstrip().startswith(("<?xml", "<svg"))
    for name in finished.result["names"]:
        assert name in svg.text
    for path in ("tree.png", "summary.png"):
        response = client.get(f"{base}/{path}", params={"width": 600})
        assert response.status_code == 200, path
        assert response.headers["content-type"] == "image/png"
        assert response.content.startswith(PNG)
        assert response.headers["x-picture-size"].startswith("600x")


def test_etag_answers_304(finished: Finished) -> None:
    client, url = finished.client, f"/v1/jobs/{finished.job_id}/result/tree.svg"
    etag = client.get(url).headers["etag"]
    again = client.get(url, headers={"If-None-Match": etag})
    assert again.status_code == 304
    assert again.content == b""
    assert client.get(url, headers={"If-None-Match": '"other"'}).status_code == 200
    # another width is another picture
    assert client.get(url, params={"width": 800}).headers["etag"] != etag


def test_width_bounds_and_unknown_jobs(finished: Finished) -> None:
    client, base = finished.client, f"/v1/jobs/{finished.job_id}/result"
    for width in (10, 100_000):
        problem = assert_problem(client.get(f"{base}/tree.png", params={"width": width}), 422)
        assert problem["errors"][0]["loc"][-1] == "width"
    for path in ("tree.svg", "tree.png", "summary.png"):
        assert_problem(client.get(f"/v1/jobs/99999/result/{path}"), 404)


def test_pictures_of_an_unfinished_job_are_409(client: TestClient) -> None:
    cid = create_collection(client)
    ids = upload_family(client, cid, [("a", circle()), ("b", circle(r=2))])
    job_id = submit_job(client, cid, ids[0])["id"]
    for path in ("tree.svg", "summary.png", f"subjects/{ids[1]}/overlay.png"):
        problem = assert_problem(client.get(f"/v1/jobs/{job_id}/result/{path}"), 409)
        assert problem["type"] == "/problems/result-not-ready"


def test_overlay_then_410_once_the_shape_is_deleted(finished: Finished) -> None:
    client, base = finished.client, f"/v1/jobs/{finished.job_id}/result"
    sid = finished.result["subjects"][-1]["shape_id"]
    overlay = client.get(f"{base}/subjects/{sid}/overlay.png")
    assert overlay.status_code == 200
    assert overlay.content.startswith(PNG)
    assert_problem(client.get(f"{base}/subjects/{finished.shape_ids[0]}/overlay.png"), 404)
    # the job has ended, so its shapes may go; the stored result stays, the overlay cannot
    delete = client.delete(f"/v1/collections/{finished.collection_id}/shapes/{sid}")
    assert delete.status_code == 204
    problem = assert_problem(client.get(f"{base}/subjects/{sid}/overlay.png"), 410)
    assert problem["type"] == "/problems/shape-deleted"
    assert client.get(f"{base}/subjects/{sid}").status_code == 200

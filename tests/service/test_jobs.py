"""Jobs end to end: submit, poll, result, transform, cancel, concurrency."""

from __future__ import annotations

import io
import threading
from collections.abc import Callable
from typing import Any, get_args

import httpx
import numpy as np
import pytest

from tests.service.conftest import (
    Service,
    assert_problem,
    circle,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)


def test_job_runs_to_completion_and_result_reads_back(client: httpx.Client) -> None:
    shapes = family(n_chains=2, chain_length=3, n_points=60)
    cid = create_collection(client, "job")
    ids = upload_family(client, cid, shapes)
    job = submit_job(client, cid, ids[0], compare_direct=True)
    assert job["status"] == "queued" and job["n_shapes"] == len(ids)

    done = wait_job(client, job["id"])
    assert done["status"] == "succeeded", done
    assert done["attempts"] == 1 and done["finished_at"] and done["started_at"]
    assert done["progress"]["total"] > 0

    result = client.get(f"/v1/jobs/{job['id']}/result").json()
    assert result["job_id"] == job["id"] and result["root_shape_id"] == ids[0]
    assert result["method"] == "dynamic_tree"
    by_id = {s["shape_id"]: s for s in result["subjects"]}
    assert set(by_id) == set(ids[1:])
    assert all("warped" not in s for s in result["subjects"])
    attached = [s for s in result["subjects"] if s["attached"]]
    assert attached, result["summary"]
    for s in attached:
        assert s["path_shape_ids"][0] == ids[0] and s["path_shape_ids"][-1] == s["shape_id"]
        assert s["parent_shape_id"] in ids
        assert s["error"] >= 0

    full = client.get(f"/v1/jobs/{job['id']}/result", params={"full": "true"}).json()
    assert all("warped" in s for s in full["subjects"])

    subject = attached[0]
    detail = client.get(f"/v1/jobs/{job['id']}/result/subjects/{subject['shape_id']}").json()
    assert detail["shape_id"] == subject["shape_id"]
    assert len(detail["warped"]) == len(shapes[0][1])
    assert detail["transform"] and detail["direct_error"] is not None

    # The stored transform maps the model's points onto the subject: applied to the model
    # shape it gives the warped model.
    model_points = shapes[0][1]
    mapped = client.post(
        f"/v1/jobs/{job['id']}/result/subjects/{subject['shape_id']}/transform",
        json={"points": model_points.tolist()},
    )
    assert mapped.status_code == 200, mapped.text
    np.testing.assert_allclose(
        np.array(mapped.json()["points"]), np.array(detail["warped"]), atol=1e-6
    )

    assert_problem(
        client.post(
            f"/v1/jobs/{job['id']}/result/subjects/{subject['shape_id']}/transform",
            json={"points": []},
        ),
        422,
    )
    assert_problem(client.get(f"/v1/jobs/{job['id']}/result/subjects/{ids[0] + 10_000}"), 404)
    listed = client.get("/v1/jobs", params={"collection_id": cid, "status": "succeeded"}).json()
    assert [j["id"] for j in listed["items"]] == [job["id"]]


def test_stored_transforms_share_their_parents_steps_and_read_back_whole(
    client: httpx.Client, service: Service
) -> None:
    """A subject's stored transform holds only the steps after its parent's, with a
    ``base`` naming them; every route gives the whole chain, which maps the model onto the
    subject's warped model."""
    import json
    import sqlite3

    from registration import ChainTransform

    shapes = family(n_chains=2, chain_length=4, n_points=60, seed=3)
    cid = create_collection(client, "shared steps")
    ids = upload_family(client, cid, shapes)
    job = submit_job(client, cid, ids[0])
    assert wait_job(client, job["id"])["status"] == "succeeded"

    with sqlite3.connect(service.db_path) as con:
        stored = {sid: json.loads(doc)["transform"] for sid, doc in con.execute(
            "SELECT shape_id, document FROM result_subjects WHERE job_id = ?", (job["id"],))}
    based = {sid: t for sid, t in stored.items() if t and "base" in t}
    assert based, "no subject below layer 2 in a chained family of depth 4"

    full = client.get(f"/v1/jobs/{job['id']}/result", params={"full": "true"}).json()
    whole = {s["shape_id"]: s for s in full["subjects"]}
    model = shapes[0][1]
    for sid, t in based.items():
        detail = client.get(f"/v1/jobs/{job['id']}/result/subjects/{sid}").json()
        transform = detail["transform"]
        assert "base" not in transform and transform == whole[sid]["transform"]
        # the stored steps are the last ones of the whole chain, after the parent's
        base = t["base"]
        assert base["shape_id"] == detail["parent_shape_id"]
        assert len(transform["steps"]) == base["steps"] + len(t["steps"])
        assert transform["steps"][base["steps"]:] == t["steps"]
        parent = client.get(f"/v1/jobs/{job['id']}/result/subjects/{base['shape_id']}").json()
        assert transform["steps"][:base["steps"]] == parent["transform"]["steps"][:base["steps"]]
        np.testing.assert_allclose(ChainTransform.from_dict(transform).apply(model),
                                   np.array(detail["warped"]), atol=1e-8)
        mapped = client.post(f"/v1/jobs/{job['id']}/result/subjects/{sid}/transform",
                             json={"points": model.tolist()})
        assert mapped.status_code == 200, mapped.text
        np.testing.assert_allclose(np.array(mapped.json()["points"]),
                                   np.array(detail["warped"]), atol=1e-6)


def test_job_validation(client: httpx.Client) -> None:
    a = create_collection(client, "a")
    b = create_collection(client, "b")
    ids_a = upload_family(client, a, [("x", circle(20)), ("y", circle(20, 2.0))])
    ids_b = upload_family(client, b, [("z", circle(20))])
    problem = assert_problem(
        client.post("/v1/jobs", json={"collection_id": a, "model_shape_id": ids_b[0]}), 422
    )
    assert f"collection {b}" in problem["detail"]
    # A collection with only the model shape has nothing to register.
    assert_problem(
        client.post("/v1/jobs", json={"collection_id": b, "model_shape_id": ids_b[0]}), 422
    )
    # Same Idempotency-Key, same body: the same job; different body: 422.
    body = {"collection_id": a, "model_shape_id": ids_a[0], "method": "direct"}
    first = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "job-k"})
    again = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "job-k"})
    assert first.status_code == again.status_code == 202
    assert first.json()["id"] == again.json()["id"]
    assert_problem(
        client.post(
            "/v1/jobs", json={**body, "method": "static_tree"}, headers={"Idempotency-Key": "job-k"}
        ),
        422,
    )
    done = wait_job(client, first.json()["id"])
    assert done["status"] == "succeeded", done
    # Upright collections: max_rotation reaches the library and is bounded to [0, 180].
    # max_rotation alone means pose "upright" (see test_pose_option_and_defaults).
    upright = submit_job(client, a, ids_a[0], method="direct", max_rotation=30)
    assert upright["params"]["max_rotation"] == 30
    assert upright["params"]["pose"] == "upright"
    assert upright["params"]["pose_source"] == "request"
    assert wait_job(client, upright["id"])["status"] == "succeeded"
    options = client.get(f"/v1/jobs/{upright['id']}/result").json()["options"]
    assert options["max_rotation"] == 30 and options["pose"] == "upright"
    assert_problem(client.post("/v1/jobs", json={**body, "max_rotation": 200}), 422)
    # A finished job cannot be cancelled; a result of an unfinished one is a 409 problem.
    assert_problem(client.post(f"/v1/jobs/{done['id']}/cancel"), 409)


def png_ellipse(width: int = 90, height: int = 70, fmt: str = "PNG") -> bytes:
    from PIL import Image, ImageDraw

    image = Image.new("L", (width, height), 255)
    ImageDraw.Draw(image).ellipse((10, 12, width - 10, height - 12), fill=0)
    buffer = io.BytesIO()
    image.save(buffer, fmt)
    return buffer.getvalue()


def test_pose_modes_agree_with_the_library() -> None:
    from registration._pose import POSE_MODES
    from service.cli_client import POSES
    from service.client import Pose
    from service.schemas import PoseName

    assert get_args(PoseName) == get_args(Pose) == POSES == POSE_MODES


@pytest.mark.parametrize(
    ("params", "expected"),
    [
        ({"max_rotation": 20.0}, ("upright", 20.0)),  # a job queued before pose existed
        ({"max_rotation": None}, ("rotation", None)),
        ({"pose": "affine", "max_rotation": None, "pose_source": "request"}, ("affine", None)),
    ],
)
def test_runner_passes_the_pose_to_the_library(
    params: dict[str, Any], expected: tuple[str, float | None]
) -> None:
    from registration import SerialExecutor
    from service.jobs.runner import run_registration

    doc = run_registration(
        "direct", [circle(20), circle(20, 2.0)], ["a", "b"], 0, params,
        executor=SerialExecutor(), progress=None,
    )  # fmt: skip
    assert (doc["options"]["pose"], doc["options"]["max_rotation"]) == expected


def test_pose_option_and_defaults(client: httpx.Client) -> None:
    points = create_collection(client, "pose-points")
    ids = upload_family(client, points, [("x", circle(20)), ("y", circle(20, 2.0))])
    images = create_collection(client, "pose-images")
    files = [
        ("files", ("a.png", png_ellipse(90, 70), "image/png")),
        ("files", ("b.jpg", png_ellipse(80, 70, "JPEG"), "image/jpeg")),
    ]
    uploaded = client.post(
        f"/v1/collections/{images}/shapes", files=files, data={"target_points": "30"}
    )
    assert uploaded.status_code == 201, uploaded.text
    image_ids = [item["id"] for item in uploaded.json()["items"]]

    def pose_of(job: dict[str, Any]) -> tuple[str, float | None, str]:
        p = job["params"]
        return p["pose"], p["max_rotation"], p["pose_source"]

    # Defaults: the library's "rotation" for points, "upright" (30 degrees) when every
    # shape was made from an image. The job says which and why, and the library gets it.
    jobs = {
        "points": submit_job(client, points, ids[0], method="direct"),
        "images": submit_job(client, images, image_ids[0], method="direct"),
        "affine": submit_job(client, points, ids[0], method="direct", pose="affine"),
        "as_given": submit_job(client, images, image_ids[0], method="direct", pose="as_given"),
        "upright": submit_job(client, points, ids[0], method="direct", pose="upright"),
        "upright10": submit_job(
            client, points, ids[0], method="direct", pose="upright", max_rotation=10
        ),
    }
    expected = {
        "points": ("rotation", None, "default"),
        "images": ("upright", 30, "default for image collections"),
        "affine": ("affine", None, "request"),
        "as_given": ("as_given", None, "request"),
        "upright": ("upright", 30, "request"),
        "upright10": ("upright", 10, "request"),
    }
    assert {k: pose_of(j) for k, j in jobs.items()} == expected
    for key, job in jobs.items():
        assert wait_job(client, job["id"])["status"] == "succeeded", key
        options = client.get(f"/v1/jobs/{job['id']}/result").json()["options"]
        assert (options["pose"], options["max_rotation"]) == expected[key][:2], key

    # One shape not made from an image: the collection is no longer an image collection.
    upload_family(client, images, [("points", circle(20))])
    mixed = submit_job(client, images, image_ids[0], method="direct")
    assert pose_of(mixed) == ("rotation", None, "default")
    # An idempotent resubmission without pose matches; asking for a pose is a new request.
    body = {"collection_id": points, "model_shape_id": ids[0], "method": "direct"}
    idem = {"Idempotency-Key": "pose-k"}
    first = client.post("/v1/jobs", json=body, headers=idem)
    assert client.post("/v1/jobs", json=body, headers=idem).json()["id"] == first.json()["id"]
    assert_problem(client.post("/v1/jobs", json={**body, "pose": "affine"}, headers=idem), 422)

    # Invalid combinations, the library's own rule: a 422 problem naming the fields.
    for wrong in (
        {"pose": "rotation", "max_rotation": 30},
        {"pose": "affine", "max_rotation": 0},
        {"pose": "as_given", "max_rotation": 10},
    ):
        problem = assert_problem(client.post("/v1/jobs", json={**body, **wrong}), 422)
        assert "max_rotation" in problem["detail"] and "upright" in problem["detail"], problem
    problem = assert_problem(client.post("/v1/jobs", json={**body, "pose": "sideways"}), 422)
    assert problem["errors"][0]["loc"] == ["body", "pose"], problem
    assert_problem(client.post("/v1/jobs", json={**body, "pose": None, "max_rotation": -1}), 422)

    # The OpenAPI document lists the modes and explains them.
    schema = client.get("/openapi.json").json()["components"]["schemas"]["JobCreate"]
    pose = schema["properties"]["pose"]
    assert pose["anyOf"][0]["enum"] == ["as_given", "upright", "rotation", "affine"]
    for words in ("as_given:", "upright:", "rotation:", "affine:", "mirror", "PNG or JPEG"):
        assert words in pose["description"], words


def test_result_before_success_is_409(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0).start()
    with svc.client() as client:
        cid = create_collection(client)
        ids = upload_family(client, cid, family(1, 2, 30))
        job = submit_job(client, cid, ids[0])
        problem = assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 409)
        assert "queued" in problem["detail"]
        # Cancel of a queued job is immediate.
        cancelled = client.post(f"/v1/jobs/{job['id']}/cancel")
        assert cancelled.status_code == 202 and cancelled.json()["status"] == "cancelled"
        assert cancelled.json()["outcome"] == "cancelled"  # while queued: not "aborted"
        # A worker started afterwards does not run it.
        svc.start_worker()
        other = submit_job(client, cid, ids[0], method="direct")
        assert wait_job(client, other["id"])["status"] == "succeeded"
        assert client.get(f"/v1/jobs/{job['id']}").json()["status"] == "cancelled"
        assert client.get(f"/v1/jobs/{job['id']}").json()["attempts"] == 0


def test_cancel_running_job(client: httpx.Client) -> None:
    cid = create_collection(client, "cancel-running")
    ids = upload_family(client, cid, family(n_chains=4, chain_length=5, n_points=100))
    job = submit_job(client, cid, ids[0], compare_direct=True)
    wait_job(
        client,
        job["id"],
        until=lambda j: j["status"] == "running" and j["progress"]["done"] > 0,
        timeout=60,
    )
    response = client.post(f"/v1/jobs/{job['id']}/cancel")
    assert response.status_code == 202
    assert response.json()["cancel_requested"] is True
    assert response.json()["outcome"] is None  # not ended until its worker stops
    done = wait_job(client, job["id"], timeout=10)
    assert done["status"] == "cancelled" and done["outcome"] == "aborted", done
    assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 409)


def test_concurrent_uploads_while_a_job_runs(client: httpx.Client, service: Service) -> None:
    cid = create_collection(client, "busy")
    ids = upload_family(client, cid, family(n_chains=3, chain_length=4, n_points=80))
    job = submit_job(client, cid, ids[0])
    target = create_collection(client, "uploads")
    errors: list[str] = []
    created: list[int] = []
    lock = threading.Lock()

    def upload(i: int) -> None:
        with service.client() as c:
            r = c.post(
                f"/v1/collections/{target}/shapes",
                json={"name": f"s{i}", "points": circle(40, 1 + i).tolist()},
            )
            with lock:
                if r.status_code == 201:
                    created.append(r.json()["id"])
                else:
                    errors.append(r.text)

    threads = [threading.Thread(target=upload, args=(i,)) for i in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    listing = client.get(f"/v1/collections/{target}/shapes", params={"limit": 100}).json()
    assert listing["total"] == 20 and sorted(i["id"] for i in listing["items"]) == sorted(created)
    assert sorted(i["name"] for i in listing["items"]) == sorted(f"s{i}" for i in range(20))
    assert wait_job(client, job["id"])["status"] == "succeeded"

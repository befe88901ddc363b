"""service.client against the real service (``regtree serve`` subprocesses from conftest)."""

from __future__ import annotations

import itertools
import json
import socket
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image, ImageDraw

from service.client import (
    Conflict,
    JobFailed,
    JobStatus,
    NotFound,
    RegtreeClient,
    RegtreeConnectionError,
    RegtreeError,
    RegtreeTimeout,
    ServerError,
    Unauthorized,
    ValidationError,
)
from tests.service.conftest import Service, free_port


def write_family_folder(folder: Path) -> list[str]:
    """The chained family as .txt/.npy/.json files plus one PNG; returns names in upload order."""
    from registration.synthetic import chained_family

    fam = chained_family(n_chains=2, chain_length=3, n_points=60, seed=1)
    names = []
    for k, (name, pts) in enumerate(zip(fam.names, fam.shapes, strict=True)):
        stem = f"{k:02d}-{name}"
        kind = ("txt", "npy", "json")[k % 3]
        if kind == "txt":
            (folder / f"{stem}.txt").write_text("\n".join(f"{x:.9f} {y:.9f}" for x, y in pts))
        elif kind == "npy":
            np.save(folder / f"{stem}.npy", pts)
        else:
            (folder / f"{stem}.json").write_text(json.dumps(pts.tolist()))
        names.append(stem)
    image = Image.new("L", (120, 90), 255)
    ImageDraw.Draw(image).ellipse((15, 15, 105, 75), fill=0)
    image.save(folder / "99-ellipse.png")
    names.append("99-ellipse")
    (folder / "README.md").write_text("not a shape: skipped by upload_folder")
    return names


@pytest.fixture
def rt(service: Service) -> Iterator[RegtreeClient]:
    with RegtreeClient(service.base_url, timeout=30) as client:
        yield client


def test_folder_upload_job_progress_result_and_transform(rt: RegtreeClient, tmp_path: Path) -> None:
    names = write_family_folder(tmp_path)
    coll = rt.create_collection("client-family", "generated chained family")
    assert coll.name == "client-family" and coll.n_shapes == 0

    batches: list[tuple[int, int]] = []
    shapes = rt.upload_folder(
        coll.id,
        tmp_path,
        batch_size=3,
        target_points=80,
        on_batch=lambda d, t: batches.append((d, t)),
    )
    assert [s.name for s in shapes] == names
    assert batches == [(3, 8), (6, 8), (8, 8)]  # three multipart batches
    formats = [s.source_format for s in shapes]
    assert formats[:3] == ["txt", "npy", "json"] and formats[-1] == "png:contour"
    assert all(s.n_points == 60 for s in shapes[:-1]) and 3 <= shapes[-1].n_points <= 80
    assert {c.id: c.n_shapes for c in rt.list_collections()}[coll.id] == 8
    assert [s.id for s in rt.list_shapes(coll.id)] == [s.id for s in shapes]
    model = rt.get_shape(coll.id, shapes[0].id)
    assert model.points is not None and model.points.shape == (60, 2)

    # pattern filters by file name
    only_png = rt.create_collection("only-png")
    assert [s.name for s in rt.upload_folder(only_png.id, tmp_path, pattern="*.png")] == [
        "99-ellipse"
    ]

    job = rt.start_job(coll.id, shapes[0].id, compare_direct=True, idempotency_key="family-1")
    assert job.status in ("queued", "running") and job.n_shapes == 8
    seen: list[JobStatus] = []
    final = rt.wait(job.id, poll=0.02, timeout=90, on_progress=seen.append)
    assert final.status == "succeeded" and seen[-1] == final
    assert len(seen) >= 2, seen
    for before, after in itertools.pairwise(seen):
        assert (before.status, before.stage, before.done, before.total) != (
            after.status,
            after.stage,
            after.done,
            after.total,
        )  # called on changes only
        if before.stage == after.stage and before.total == after.total:
            assert after.done >= before.done
    assert final.done == final.total > 0 and seen[0].done < final.done
    # resubmitting with the same key gives the same job back
    again = rt.start_job(coll.id, shapes[0].id, compare_direct=True, idempotency_key="family-1")
    assert again.id == job.id

    result = rt.result(job.id)
    assert result.job_id == job.id and result.root_shape_id == shapes[0].id
    assert {s.shape_id for s in result.subjects} == {s.id for s in shapes[1:]}
    assert result.attached and all(s.layer is not None and s.layer >= 2 for s in result.attached)
    assert all(s.warped is None for s in result.subjects)  # light document
    assert result.summary["subjects"] == 7 and "per_layer" in result.summary
    assert result.document["subjects"][0]["shape_id"] == result.subjects[0].shape_id

    full = rt.result(job.id, full=True)
    attached = full.attached[-1]
    assert attached.warped is not None and attached.warped.shape == (60, 2)

    one = rt.subject(job.id, attached.shape_id)
    assert one.name == attached.name and one.layer == attached.layer
    assert one.correspondence is not None and one.correspondence.shape == (60,)
    assert one.direct is not None and one.direct.error == pytest.approx(one.direct_error)

    # the stored transform maps the model's points onto the warped model
    mapped = rt.apply_transform(job.id, one.shape_id, model.points)
    assert mapped.shape == (60, 2)
    assert one.warped is not None
    scale = float(np.ptp(one.warped, axis=0).max())
    assert np.abs(mapped - one.warped).max() < 1e-6 * scale

    # --- errors carry the server's problem document -------------------------------------
    with pytest.raises(NotFound) as nf:
        rt.get_job(987654)
    assert nf.value.status == 404 and nf.value.detail == "job 987654 not found"
    assert nf.value.type == "/problems/not-found" and nf.value.title
    with pytest.raises(NotFound):
        rt.subject(job.id, 987654)
    with pytest.raises(ValidationError) as bad_model:
        rt.start_job(only_png.id, shapes[0].id)
    assert bad_model.value.status == 422
    assert f"belongs to collection {coll.id}" in (bad_model.value.detail or "")
    with pytest.raises(ValidationError) as too_few:
        rt.upload_points(coll.id, "two", [[0.0, 0.0], [1.0, 1.0]])
    assert too_few.value.status == 422 and "2" in (too_few.value.detail or "")
    with pytest.raises(Conflict) as finished:
        rt.cancel(job.id)
    assert finished.value.detail == f"job {job.id} already succeeded"
    if result.unattached:
        with pytest.raises(Conflict) as no_transform:
            rt.apply_transform(job.id, result.unattached[0].shape_id, [[0.0, 0.0]])
        assert "no transform" in (no_transform.value.detail or "")

    # a refused batch names the file, and the earlier batches' shapes are reported as stored
    (tmp_path / "zz-broken.txt").write_text("1 2\nthree four\n")
    broken = rt.create_collection("broken")
    with pytest.raises(ValidationError) as refused:
        rt.upload_folder(broken.id, tmp_path, pattern="*.*", batch_size=4)
    assert "zz-broken.txt" in (refused.value.detail or "")
    assert [i["file"] for i in refused.value.problem["invalid"]] == ["zz-broken.txt"]
    assert [s.name for s in refused.value.stored] == names[:8]
    assert "batch 3 of 3" in "".join(refused.value.__notes__)
    assert rt.get_collection(broken.id).n_shapes == 8
    rt.delete_collection(broken.id)
    with pytest.raises(NotFound):
        rt.get_collection(broken.id)


def test_start_job_pose(rt: RegtreeClient, tmp_path: Path) -> None:
    for name, width in (("a", 90), ("b", 80)):
        image = Image.new("L", (width, 70), 255)
        ImageDraw.Draw(image).ellipse((10, 12, width - 10, 58), fill=0)
        image.save(tmp_path / f"{name}.png")
    scans = rt.create_collection("client-pose-scans")
    a, _ = rt.upload_folder(scans.id, tmp_path, pattern="*.png", target_points=30)
    points = rt.create_collection("client-pose-points")
    t = np.arange(20)
    s1 = rt.upload_points(points.id, "s1", np.c_[np.cos(t), np.sin(t)])
    rt.upload_points(points.id, "s2", np.c_[np.cos(t), 2 * np.sin(t)])

    def pose(job: JobStatus) -> tuple[str, float | None, str]:
        return job.params["pose"], job.params["max_rotation"], job.params["pose_source"]

    # No pose sent unless given: the server's default, as for any HTTP client.
    image_default = ("upright", 30, "default for image collections")
    assert pose(rt.start_job(scans.id, a.id, method="direct")) == image_default
    assert pose(rt.start_job(points.id, s1.id, method="direct")) == ("rotation", None, "default")
    job = rt.start_job(points.id, s1.id, method="direct", pose="as_given")
    assert pose(job) == ("as_given", None, "request")
    assert rt.wait(job.id, timeout=60).status == "succeeded"
    assert rt.result(job.id).document["options"]["pose"] == "as_given"
    narrow = rt.start_job(scans.id, a.id, method="direct", pose="upright", max_rotation=5)
    assert pose(narrow) == ("upright", 5, "request")
    alone = rt.start_job(scans.id, a.id, method="direct", max_rotation=45)
    assert pose(alone) == ("upright", 45, "request")  # max_rotation alone means upright
    with pytest.raises(ValidationError) as wrong:
        rt.start_job(points.id, s1.id, pose="rotation", max_rotation=10)
    assert wrong.value.status == 422 and "max_rotation" in (wrong.value.detail or "")


def test_api_key_wait_timeout_and_cancel(make_service) -> None:  # type: ignore[no-untyped-def]
    svc = make_service(workers=0, env={"REGTREE_API_KEY": "s3cret"}).start()
    with RegtreeClient(svc.base_url) as anonymous, pytest.raises(Unauthorized) as denied:
        anonymous.list_collections()
    assert denied.value.status == 401 and "X-API-Key" in (denied.value.detail or "")

    with RegtreeClient(svc.base_url, api_key="s3cret") as rt:
        coll = rt.create_collection("queued")
        a = rt.upload_points(coll.id, "a", np.c_[np.cos(np.arange(30)), np.sin(np.arange(30))])
        rt.upload_points(coll.id, "b", np.c_[np.cos(np.arange(30)), 2 * np.sin(np.arange(30))])
        job = rt.start_job(coll.id, a.id, cpd={"beta": 1.5})
        assert job.params["cpd"]["beta"] == 1.5

        # no worker: the job stays queued and wait gives up with the last status
        with pytest.raises(RegtreeTimeout) as waited:
            rt.wait(job.id, poll=0.05, timeout=0.3)
        assert waited.value.last_status is not None
        assert waited.value.last_status.status == "queued"
        assert isinstance(waited.value, TimeoutError)

        with pytest.raises(Conflict) as early:
            rt.result(job.id)
        assert "is queued" in (early.value.detail or "")

        cancelled = rt.cancel(job.id)
        assert cancelled.status == "cancelled"
        with pytest.raises(JobFailed) as failed:
            rt.wait(job.id, poll=0.05)
        assert failed.value.job.status == "cancelled"
        assert rt.wait(job.id, raise_on_failure=False).status == "cancelled"
        with pytest.raises(Conflict):
            rt.cancel(job.id)
        assert [j.id for j in rt.list_jobs(collection_id=coll.id, status="cancelled")] == [job.id]


def test_request_timeout_and_unreachable_server() -> None:
    with socket.socket() as silent:
        # accepts connections (backlog) but never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        port = silent.getsockname()[1]
        with RegtreeClient(f"http://127.0.0.1:{port}", timeout=0.3) as rt:
            with pytest.raises(RegtreeTimeout) as timed_out:
                rt.get_job(1)
    assert "no answer within the timeout" in str(timed_out.value)

    with RegtreeClient(f"http://127.0.0.1:{free_port()}", retries=0) as rt:
        with pytest.raises(RegtreeConnectionError) as unreachable:
            rt.list_collections()
    assert "cannot reach" in str(unreachable.value)


def test_retries_and_non_json_errors() -> None:
    calls: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(f"{request.method} {request.url.path}")
        if request.url.path == "/v1/jobs/1" and len(calls) == 1:
            return httpx.Response(503, text="busy")
        if request.url.path == "/v1/jobs/2":
            return httpx.Response(502, text="<html>bad gateway</html>")
        if request.url.path == "/v1/jobs/3":
            return httpx.Response(
                418,
                json={"type": "/x", "title": "Teapot", "status": 418, "detail": "short and stout"},
                headers={"content-type": "application/problem+json"},
            )
        return httpx.Response(
            200,
            json={
                "id": 1,
                "collection_id": 1,
                "model_shape_id": 1,
                "method": "dynamic_tree",
                "status": "running",
                "progress": {"stage": "similarity", "done": 3, "total": 10},
                "params": {},
            },
        )

    transport = httpx.MockTransport(handler)
    with RegtreeClient("http://x", transport=transport, retries=1) as rt:
        job = rt.get_job(1)  # 503 then 200: retried
        assert job.stage == "similarity" and job.fraction == pytest.approx(0.3)
        assert calls == ["GET /v1/jobs/1", "GET /v1/jobs/1"]
        with pytest.raises(ServerError) as gateway:
            rt.get_job(2)
        assert gateway.value.status == 502 and gateway.value.detail == "<html>bad gateway</html>"
        with pytest.raises(ValidationError) as teapot:
            rt.get_job(3)
        assert isinstance(teapot.value, RegtreeError) and teapot.value.detail == "short and stout"
        assert str(teapot.value) == "418 Teapot: short and stout (GET /v1/jobs/3)"
        with pytest.raises(ValueError, match=r"shape \(n, 2\)"):
            rt.apply_transform(1, 1, [1.0, 2.0])


def test_from_env(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(200, json={"items": [], "total": 0, "limit": 500, "offset": 0})

    monkeypatch.setenv("REGTREE_URL", "http://regtree.example:9000/")
    monkeypatch.setenv("REGTREE_API_KEY", "k3y")
    with RegtreeClient.from_env(transport=httpx.MockTransport(handler)) as rt:
        assert rt.list_collections() == []
    assert str(seen[0].url).startswith("http://regtree.example:9000/v1/collections?")
    assert seen[0].headers["x-api-key"] == "k3y"


def test_upload_folder_refuses_an_empty_match(tmp_path: Path) -> None:
    (tmp_path / "notes.md").write_text("x")
    with RegtreeClient("http://127.0.0.1:1") as rt, pytest.raises(FileNotFoundError):
        rt.upload_folder(1, tmp_path)

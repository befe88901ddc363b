"""Upload policy through real HTTP: degenerate shapes, existing names, default names, and job
errors that name the shape."""

from __future__ import annotations

import hashlib
import io
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image, ImageDraw

from tests.service.conftest import (
    Service,
    assert_problem,
    circle,
    create_collection,
    insert_legacy_shape,
    npy_bytes,
    submit_job,
    wait_job,
)


def png(width: int = 90) -> bytes:
    image = Image.new("L", (width, 70), 255)
    ImageDraw.Draw(image).ellipse((10, 12, width - 10, 58), fill=0)
    buffer = io.BytesIO()
    image.save(buffer, "PNG")
    return buffer.getvalue()


def shapes_of(client: httpx.Client, cid: int) -> dict[int, str]:
    items = client.get(f"/v1/collections/{cid}/shapes", params={"limit": 100}).json()["items"]
    return {int(i["id"]): i["name"] for i in items}


def points_of(client: httpx.Client, cid: int, sid: int) -> np.ndarray:
    return np.array(client.get(f"/v1/collections/{cid}/shapes/{sid}").json()["points"])


# --------------------------------------------------------------------------- degenerate shapes


@pytest.mark.parametrize(
    ("send", "phrase"),
    [
        (lambda c, u: c.post(u, json={"points": [[5, 5]] * 8}), "all 8 points are equal"),
        (
            lambda c, u: c.post(
                u, json={"points": [[5, 5 + 1e-12 * k] for k in range(8)], "name": "flat"}
            ),
            "the 8 points lie within",
        ),
        (
            lambda c, u: c.post(
                u, content=b"x,y\n2,3\n2,3\n2,3\n", headers={"content-type": "text/csv"}
            ),
            "all 3 points are equal",
        ),
        (
            lambda c, u: c.post(
                u,
                content=npy_bytes(np.full((5, 2), 7.0)),
                headers={"content-type": "application/octet-stream"},
            ),
            "all 5 points are equal",
        ),
        (
            lambda c, u: c.post(
                u, files=[("files", ("dot.json", b"[[1,1],[1,1],[1,1]]", "application/json"))]
            ),
            "dot.json: all 3 points are equal",
        ),
        (lambda c, u: c.post(u, json={"points": [[0, 0], [1, 1]]}), "at least 3 are required"),
        (
            lambda c, u: c.post(
                u, content=b"0 0\n1 0\nnan 1\n", headers={"content-type": "text/plain"}
            ),
            "non-finite coordinate",
        ),
    ],
    ids=["equal", "within-1e-12", "csv", "npy", "multipart", "too-few", "nan"],
)
def test_degenerate_shapes_are_refused_and_nothing_is_stored(
    client: httpx.Client, send: Callable[[httpx.Client, str], httpx.Response], phrase: str
) -> None:
    cid = create_collection(client, "degenerate")
    url = f"/v1/collections/{cid}/shapes"
    kept = client.post(url, json={"name": "kept", "points": circle(20).tolist()}).json()
    problem = assert_problem(send(client, url), 422)
    assert problem["type"] == "/problems/invalid-shape"
    assert phrase in problem["detail"], problem["detail"]
    if "equal" in phrase or "within" in phrase:
        assert "zero size" in problem["detail"]
    assert shapes_of(client, cid) == {kept["id"]: "kept"}


def test_a_batch_names_every_invalid_file_at_once_and_stores_none(client: httpx.Client) -> None:
    """A folder with several broken files is fixed in one go: the 422 lists each invalid file
    (name, position, why) in ``invalid``; its detail names the first and counts the rest;
    the batch's valid files are not stored either."""
    cid = create_collection(client, "broken-folder")
    url = f"/v1/collections/{cid}/shapes"
    kept = client.post(url, json={"name": "kept", "points": circle(20).tolist()}).json()
    files = [
        ("files", ("a-two.txt", b"1 2\n3 4\n", "text/plain")),
        ("files", ("b-ok.txt", b"0 0\n1 0\n1 1\n0 1\n", "text/plain")),
        ("files", ("c-nan.txt", b"0 0\n1 nan\n2 1\n3 3\n", "text/plain")),
        ("files", ("d-words.csv", b"hello world\n", "text/csv")),
    ]
    problem = assert_problem(client.post(url, files=files), 422)
    assert problem["type"] == "/problems/invalid-shape"
    assert [(i["file"], i["index"]) for i in problem["invalid"]] == [
        ("a-two.txt", 0), ("c-nan.txt", 2), ("d-words.csv", 3)
    ]
    assert "at least 3" in problem["invalid"][0]["detail"]
    assert "non-finite" in problem["invalid"][1]["detail"]
    assert problem["detail"].startswith("a-two.txt: ")
    assert problem["detail"].endswith("; 2 more of the 4 files are invalid too")
    assert (problem["file"], problem["index"]) == ("a-two.txt", 0)  # the first, as before
    assert shapes_of(client, cid) == {kept["id"]: "kept"}

    # a JSON batch the same way, by position
    body = {"shapes": [{"name": "fine", "points": circle(12).tolist()},
                       {"name": "two", "points": [[0, 0], [1, 1]]}, "not an object"]}
    problem = assert_problem(client.post(url, json=body), 422)
    assert [(i["shape"], i["index"]) for i in problem["invalid"]] == [
        ("shapes[1]", 1), ("shapes[2]", 2)
    ]
    assert problem["detail"].startswith("shapes[1]: ")
    assert "expected an object" in problem["invalid"][1]["detail"]
    assert shapes_of(client, cid) == {kept["id"]: "kept"}
    # one invalid file alone: the detail as before, nothing counted
    one = assert_problem(client.post(url, files=files[:2]), 422)
    assert one["detail"].startswith("a-two.txt: ") and "more of the" not in one["detail"]
    assert len(one["invalid"]) == 1


def test_a_shape_just_above_the_size_tolerance_registers(client: httpx.Client) -> None:
    """What the upload accepts, the library accepts: the upload's tolerance is the stricter."""
    from registration import normalise

    cid = create_collection(client, "small")
    tiny = np.array([[5.0, 5.0], [5.0, 5.0 + 2e-8], [5.0 + 2e-8, 5.0]])
    r = client.post(f"/v1/collections/{cid}/shapes", json={"name": "tiny", "points": tiny.tolist()})
    assert r.status_code == 201, r.text
    normalise(points_of(client, cid, r.json()["id"]))


def test_job_error_names_the_shape_not_its_position(client: httpx.Client, service: Service) -> None:
    cid = create_collection(client, "legacy")
    url = f"/v1/collections/{cid}/shapes"
    model = client.post(url, json={"name": "ring", "points": circle(30).tolist()}).json()["id"]
    client.post(url, json={"name": "oval", "points": circle(30, 2.0).tolist()})
    dot = insert_legacy_shape(service, cid, "dot 7", np.zeros((6, 2)))
    job = wait_job(client, submit_job(client, cid, model)["id"])
    assert job["status"] == "failed"
    assert f"shape {dot} 'dot 7' has zero size" in job["error"], job["error"]
    assert "shapes[" not in job["error"]


# --------------------------------------------------------------------------- existing names


def test_refuse_is_the_default_and_keeps_everything(client: httpx.Client) -> None:
    cid = create_collection(client, "refuse")
    url = f"/v1/collections/{cid}/shapes"
    files = [
        ("files", (f"{n}.csv", "\n".join(f"{x},{y}" for x, y in circle(12, r)), "text/csv"))
        for n, r in (("a", 1.0), ("b", 2.0))
    ]
    first = client.post(url, files=files).json()["items"]
    before = {s["id"]: points_of(client, cid, s["id"]) for s in first}
    # the same folder again: refused, naming the existing shapes, nothing stored
    problem = assert_problem(client.post(url, files=files), 409)
    assert problem["type"] == "/problems/name-conflict"
    assert problem["existing"] == [{"id": s["id"], "name": s["name"]} for s in first]
    assert f"'a' (id {first[0]['id']})" in problem["detail"]
    assert "on_conflict=replace" in problem["detail"] and "on_conflict=keep" in problem["detail"]
    # one new name and one old: still all or nothing
    mixed = [files[0], ("files", ("c.csv", "0,0\n1,0\n0,1\n", "text/csv"))]
    assert_problem(client.post(url, files=mixed), 409)
    raw = {"content-type": "text/plain"}
    assert_problem(
        client.post(url, params={"name": "b"}, content=b"0 0\n1 0\n0 1", headers=raw), 409
    )
    assert_problem(client.post(url, json={"name": "a", "points": circle(9).tolist()}), 409)
    assert shapes_of(client, cid) == {s["id"]: s["name"] for s in first}
    for sid, pts in before.items():
        np.testing.assert_array_equal(points_of(client, cid, sid), pts)
    # the same name in another collection is no conflict
    other = create_collection(client, "other")
    assert client.post(f"/v1/collections/{other}/shapes", files=files).status_code == 201


def test_replace_and_keep(client: httpx.Client) -> None:
    cid = create_collection(client, "policies")
    url = f"/v1/collections/{cid}/shapes"
    old = client.post(url, json={"name": "g", "points": circle(10).tolist()}).json()
    new = circle(14, 3.0)
    r = client.post(
        url, params={"on_conflict": "replace"}, json={"name": "g", "points": new.tolist()}
    )
    assert r.status_code == 201, r.text
    assert r.json()["id"] != old["id"] and r.headers["location"].endswith(f"/{r.json()['id']}")
    assert_problem(client.get(f"{url}/{old['id']}"), 404)
    np.testing.assert_allclose(points_of(client, cid, r.json()["id"]), new)
    assert shapes_of(client, cid) == {r.json()["id"]: "g"}

    kept = client.post(
        url, params={"on_conflict": "keep"}, json={"name": "g", "points": circle(8).tolist()}
    )
    assert kept.status_code == 201
    assert sorted(shapes_of(client, cid).values()) == ["g", "g"]
    # replace removes every shape of the name
    last = client.post(
        url,
        params={"on_conflict": "replace"},
        json={"shapes": [{"name": "g", "points": circle(5).tolist()}]},
    )
    assert last.status_code == 201
    assert shapes_of(client, cid) == {last.json()["items"][0]["id"]: "g"}


def test_duplicate_names_within_one_upload(client: httpx.Client) -> None:
    cid = create_collection(client, "twins")
    url = f"/v1/collections/{cid}/shapes"
    files = [
        ("files", ("a.csv", "0,0\n1,0\n0,1\n", "text/csv")),
        ("files", ("a.json", "[[0,0],[2,0],[0,2]]", "application/json")),
    ]
    for policy in ("refuse", "replace"):
        problem = assert_problem(client.post(url, files=files, params={"on_conflict": policy}), 422)
        assert problem["type"] == "/problems/duplicate-names"
        assert problem["files"] == ["a.csv", "a.json"] and problem["name"] == "a"
    assert shapes_of(client, cid) == {}
    r = client.post(url, files=files, params={"on_conflict": "keep"})
    assert [s["name"] for s in r.json()["items"]] == ["a", "a"]


def test_replace_is_refused_while_a_job_uses_the_shape(
    make_service: Callable[..., Service],
) -> None:
    svc = make_service(workers=0).start()  # no worker: the job stays queued
    with svc.client() as client:
        cid = create_collection(client, "busy")
        url = f"/v1/collections/{cid}/shapes"
        ids = [
            client.post(url, json={"name": n, "points": circle(12, r).tolist()}).json()["id"]
            for n, r in (("m", 1.0), ("s", 2.0))
        ]
        job = submit_job(client, cid, ids[0])
        r = client.post(
            url, params={"on_conflict": "replace"}, json={"name": "s", "points": circle(9).tolist()}
        )
        problem = assert_problem(r, 409)
        assert problem["type"] == "/problems/shape-in-use"
        assert f"shape {ids[1]} is used by unfinished job(s) [{job['id']}]" in problem["detail"]
        assert shapes_of(client, cid) == {ids[0]: "m", ids[1]: "s"}
        assert_problem(client.delete(f"{url}/{ids[1]}"), 409)


def test_invalid_policy_is_a_422(client: httpx.Client) -> None:
    cid = create_collection(client, "bad-policy")
    r = client.post(
        f"/v1/collections/{cid}/shapes",
        params={"on_conflict": "merge"},
        json={"name": "x", "points": circle(5).tolist()},
    )
    problem = assert_problem(r, 422)
    assert "on_conflict" in problem["detail"]


def test_idempotent_replay_of_a_replace(client: httpx.Client) -> None:
    cid = create_collection(client, "replay")
    url = f"/v1/collections/{cid}/shapes"
    client.post(url, json={"name": "g", "points": circle(10).tolist()})
    send = lambda: client.post(  # noqa: E731
        url,
        params={"on_conflict": "replace"},
        json={"name": "g", "points": circle(11).tolist()},
        headers={"Idempotency-Key": "replace-1"},
    )
    first, again = send(), send()
    assert first.status_code == again.status_code == 201
    assert first.json()["id"] == again.json()["id"]
    assert shapes_of(client, cid) == {first.json()["id"]: "g"}


# --------------------------------------------------------------------------- default names


def test_default_names(client: httpx.Client) -> None:
    cid = create_collection(client, "names")
    url = f"/v1/collections/{cid}/shapes"
    image = png()
    raw = client.post(
        url, content=image, headers={"content-type": "image/png"}, params={"target_points": 40}
    )
    assert raw.status_code == 201, raw.text
    pts = points_of(client, cid, raw.json()["id"])
    digest = hashlib.sha256(np.ascontiguousarray(pts, dtype="<f8").tobytes()).hexdigest()
    assert raw.json()["name"] == f"shape-{digest[:12]}"
    # the same picture again is the same name, so the default policy sees the repeat
    again = client.post(
        url, content=image, headers={"content-type": "image/png"}, params={"target_points": 40}
    )
    assert assert_problem(again, 409)["existing"] == [
        {"id": raw.json()["id"], "name": raw.json()["name"]}
    ]
    # multipart: the file name's stem, folders dropped
    multi = client.post(
        url,
        files=[("files", ("scans/glyph 12.png", png(80), "image/png"))],
        data={"target_points": "40"},
    )
    assert multi.json()["items"][0]["name"] == "glyph 12"
    # JSON without a name: the points' hash too, the same in every format
    square = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    named = client.post(url, json={"points": square.tolist()}).json()["name"]
    as_csv = client.post(url, content=b"0,0\n4,0\n4,4\n0,4\n", headers={"content-type": "text/csv"})
    assert (
        named.startswith("shape-") and assert_problem(as_csv, 409)["existing"][0]["name"] == named
    )


# --------------------------------------------------------------------------- client and CLI


def test_client_and_cli_upload_a_folder_twice(service: Service, tmp_path: Path) -> None:
    from service.client import Conflict, RegtreeClient
    from tests.service.test_cli_client import assert_error, regtree

    folder = tmp_path / "glyphs"
    folder.mkdir()
    for n, r in (("a", 1.0), ("b", 2.0)):
        np.savetxt(folder / f"{n}.txt", circle(12, r))
    with RegtreeClient(service.base_url) as rt:
        coll = rt.create_collection("twice")
        first = rt.upload_folder(coll.id, folder)
        with pytest.raises(Conflict) as refused:
            rt.upload_folder(coll.id, folder)
        assert refused.value.problem["existing"] == [{"id": s.id, "name": s.name} for s in first]
        assert [s.id for s in rt.list_shapes(coll.id)] == [s.id for s in first]
        replaced = rt.upload_folder(coll.id, folder, on_conflict="replace")
        assert [s.name for s in rt.list_shapes(coll.id)] == ["a", "b"]
        assert {s.id for s in replaced}.isdisjoint(s.id for s in first)
        with pytest.raises(Conflict):
            rt.upload_points(coll.id, "a", circle(7))
        rt.upload_points(coll.id, "a", circle(7), on_conflict="keep")
        assert [s.name for s in rt.list_shapes(coll.id)] == ["a", "b", "a"]

    url = service.base_url
    args = ("upload", str(folder), "--collection", "twice")
    assert_error(regtree(*args, url=url), 1, "already has shape(s) named", "--on-conflict")
    done = regtree(*args, "--on-conflict", "keep", url=url)
    assert done.returncode == 0, done.stderr
    assert "uploaded 2 shape(s)" in done.stdout and "now holds 5" in done.stdout

"""Results an integrator can use directly, through real HTTP: shape ids, the root's identity
transform, the inverse map, the similarity D, CSV, one ZIP, and their client and CLI."""

from __future__ import annotations

import csv
import io
import json
import sqlite3
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from service.client import Conflict, RegtreeClient, Subject
from service.contract.result import ResultDocument, SimilarityDocument, SubjectDetail
from service.jobs.document import json_safe
from tests.service.conftest import (
    REPO,
    Service,
    assert_problem,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)


@pytest.fixture(scope="module")
def job(service: Service) -> dict[str, Any]:
    with service.client() as client:
        coll = create_collection(client, "exports")
        ids = upload_family(client, coll, family(n_chains=2, chain_length=3, n_points=50))
        job = submit_job(client, coll, ids[0], compare_direct=True)
        done = wait_job(client, job["id"], timeout=120)
        assert done["status"] == "succeeded", done
        return {**done, "ids": ids}


def test_result_speaks_shape_ids(client: httpx.Client, job: dict[str, Any]) -> None:
    doc = client.get(f"/v1/jobs/{job['id']}/result", params={"full": "true"}).json()
    model = ResultDocument.model_validate(doc)
    ids = job["ids"]
    assert model.shape_ids == ids and model.root_shape_id == ids[0]
    assert model.tree is not None and model.tree[0].shape_id == ids[0]
    nodes = {n.shape_id: n for n in model.tree}
    for s in model.subjects:
        assert s.shape_id == ids[s.index or 0]  # positions stay, ids beside them
        assert s.path_shape_ids == [ids[p] for p in s.path]
        if s.attached:
            assert s.parent_shape_id == ids[s.parent or 0]
            assert s.shape_id in nodes[s.parent_shape_id].children_shape_ids
            assert s.transform is not None
            assert s.transform.path_shape_ids == s.path_shape_ids
            # one key scheme for every step
            for step in doc["subjects"][model.subjects.index(s)]["transform"]["steps"]:
                assert {"type", "kind", "version"} <= set(step)
        for a in s.attempts:
            assert a.member_shape_id == ids[a.member]


def test_the_root_has_the_identity_transform(
    client: httpx.Client, job: dict[str, Any]
) -> None:
    root = job["ids"][0]
    response = client.get(f"/v1/jobs/{job['id']}/result/subjects/{root}")
    assert response.status_code == 200, response.text
    subject = SubjectDetail.model_validate(response.json())
    assert subject.root and subject.layer == 1 and subject.error == 0.0 and subject.attached
    assert subject.transform is not None and subject.transform.steps == []
    model_points = np.asarray(client.get(f"/v1/collections/{job['collection_id']}/shapes/{root}")
                              .json()["points"])
    assert np.allclose(np.asarray(subject.warped), model_points)
    pts = [[0.5, -2.0], [10.0, 3.0]]
    for route in ("transform", "inverse-transform"):
        mapped = client.post(
            f"/v1/jobs/{job['id']}/result/subjects/{root}/{route}", json={"points": pts}
        )
        assert mapped.status_code == 200, mapped.text
        assert np.allclose(mapped.json()["points"], pts, rtol=0, atol=1e-9)
    missing = client.get(f"/v1/jobs/{job['id']}/result/subjects/{10**9}")
    assert_problem(missing, 404)


def test_the_inverse_maps_the_subject_back_onto_the_model(
    service: Service, job: dict[str, Any]
) -> None:
    with RegtreeClient(service.base_url) as rt:
        result = rt.result(job["id"])
        model = rt.get_shape(job["collection_id"], result.root_shape_id).points
        assert model is not None
        size = float(np.ptp(model, axis=0).max())
        deep = [s for s in result.subjects if s.attached and (s.layer or 0) >= 3]
        assert deep, "the family has chains: some subject is at layer 3"
        for s in deep[:2] + result.subjects[:1]:
            onto = rt.apply_transform(job["id"], s.shape_id, model)
            back = rt.inverse_transform(job["id"], s.shape_id, onto)
            assert np.isfinite(back).all()
            # the documented accuracy: 1e-6 of the shape's size (typically far better)
            assert np.abs(back - model).max() < 1e-6 * size, np.abs(back - model).max()
        # far from the shape the warp fades to its affine part: still invertible
        far = np.array([[1e4, -1e4]])
        back = rt.inverse_transform(job["id"], deep[0].shape_id, far)
        assert np.allclose(rt.apply_transform(job["id"], deep[0].shape_id, back), far)


def test_similarity_is_a_resource(client: httpx.Client, job: dict[str, Any]) -> None:
    response = client.get(f"/v1/jobs/{job['id']}/similarity", params={"k": 2})
    assert response.status_code == 200, response.text
    sim = SimilarityDocument.model_validate(response.json())
    ids = job["ids"]
    assert sim.shape_ids == ids and sim.D is not None
    D = np.array([[np.nan if v is None else v for v in row] for row in sim.D])
    assert np.allclose(np.diag(D), 0.0)
    assert sim.computed_pairs == int(np.isfinite(D).sum()) - len(ids) > 0
    doc = client.get(f"/v1/jobs/{job['id']}/result").json()
    for s in doc["subjects"]:  # the tree's edges use these very values, parent onto child
        if s["layer"] is not None:
            assert D[ids.index(s["parent_shape_id"]), ids.index(s["shape_id"])] == pytest.approx(
                s["similarity"], rel=1e-12
            )
    for entry in sim.nearest:
        values = [n.D for n in entry.nearest]
        assert len(values) <= 2 and values == sorted(values)
        assert entry.shape_id not in [n.shape_id for n in entry.nearest]
        column = D[:, ids.index(entry.shape_id)]
        if values:
            others = [v for i, v in enumerate(column) if ids[i] != entry.shape_id]
            assert values[0] == np.nanmin(others)
    light = client.get(f"/v1/jobs/{job['id']}/similarity", params={"matrix": "false"}).json()
    assert "D" not in light and light["nearest"]
    assert_problem(client.get(f"/v1/jobs/{job['id']}/similarity", params={"k": 0}), 422)


def test_result_csv(client: httpx.Client, job: dict[str, Any]) -> None:
    response = client.get(f"/v1/jobs/{job['id']}/result.csv")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(response.text)))
    doc = client.get(f"/v1/jobs/{job['id']}/result").json()
    assert [int(r["shape_id"]) for r in rows] == [s["shape_id"] for s in doc["subjects"]]
    for row, s in zip(rows, doc["subjects"], strict=True):
        assert row["name"] == s["name"] and row["status"] == s["status"]
        assert (float(row["error"]) if row["error"] else None) == s["error"]
        assert (float(row["direct_error"]) if row["direct_error"] else None) == s["direct_error"]
        assert row["path_shape_ids"].split() == [str(i) for i in s["path_shape_ids"]]
        assert (float(row["disagreement"]) if row["disagreement"] else None) == s["disagreement"]
    by_error = client.get(f"/v1/jobs/{job['id']}/result.csv", params={"sort": "-error"}).text
    errors = [float(r["error"]) for r in csv.DictReader(io.StringIO(by_error)) if r["error"]]
    assert errors == sorted(errors, reverse=True)
    assert_problem(client.get(f"/v1/jobs/{job['id']}/result.csv", params={"sort": "x"}), 422)


def test_result_sorted_by_disagreement(client: httpx.Client, job: dict[str, Any]) -> None:
    """``sort=-disagreement``: the subjects whose two registrations disagree most first,
    those without a value (the root) last; the client reads the field."""
    doc = client.get(f"/v1/jobs/{job['id']}/result", params={"sort": "-disagreement"}).json()
    values = [s["disagreement"] for s in doc["subjects"]]
    present = [v for v in values if v is not None]
    assert present, "the dynamic tree's polished subjects report a disagreement"
    assert present == sorted(present, reverse=True) and all(v > 0 for v in present)
    assert values[: len(present)] == present
    ascending = client.get(f"/v1/jobs/{job['id']}/result", params={"sort": "disagreement"})
    assert [s["disagreement"] for s in ascending.json()["subjects"]][: len(present)] == sorted(
        present
    )
    subject = next(s for s in doc["subjects"] if s["disagreement"] is not None)
    assert Subject.from_json(subject).disagreement == subject["disagreement"]


def test_export_zip(service: Service, job: dict[str, Any], tmp_path: Path) -> None:
    with RegtreeClient(service.base_url, timeout=120) as rt:
        data = rt.export_zip(job["id"], tmp_path / "job.zip", subject_pictures=True)
        csv_text = rt.result_csv(job["id"])
        sim = rt.similarity(job["id"])
    assert (tmp_path / "job.zip").read_bytes() == data
    archive = zipfile.ZipFile(io.BytesIO(data))
    prefix = f"job-{job['id']}/"
    names = set(archive.namelist())
    for name in ("result.json", "result.csv", "similarity.json", "job.json", "tree.svg",
                 "tree.png", "summary.png"):
        assert prefix + name in names, name
    subject_pictures = [n for n in names if n.startswith(prefix + "subjects/")]
    assert len(subject_pictures) == len(job["ids"]) - 1
    for name in [*subject_pictures, prefix + "tree.png"]:
        assert archive.read(name)[:8] == b"\x89PNG\r\n\x1a\n"
    result = json.loads(archive.read(prefix + "result.json"))
    assert all("transform" in s for s in result["subjects"])
    assert result["root_subject"]["root"] is True
    assert archive.read(prefix + "result.csv").decode() == csv_text
    stored = json.loads(archive.read(prefix + "similarity.json"))
    assert stored["D"] == json_safe(sim.D)


def _cli(service: Service, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args, "--url", service.base_url],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def test_cli_exports(service: Service, job: dict[str, Any], tmp_path: Path) -> None:
    done = _cli(service, "results", str(job["id"]), "--csv")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0].startswith("shape_id,name,position,status")
    assert len(done.stdout.splitlines()) == len(job["ids"])
    out = tmp_path / "j.zip"
    done = _cli(service, "export", str(job["id"]), "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert zipfile.ZipFile(out).testzip() is None and f"wrote {out}" in done.stdout
    done = _cli(service, "similarity", str(job["id"]), "--k", "2")
    assert done.returncode == 0, done.stderr
    assert len(done.stdout.splitlines()) == 2 + len(job["ids"])


def test_a_result_without_similarity_says_so(
    service: Service, client: httpx.Client, job: dict[str, Any]
) -> None:
    other = submit_job(client, job["collection_id"], job["ids"][1], method="direct")
    assert wait_job(client, other["id"])["status"] == "succeeded"
    with sqlite3.connect(service.db_path) as db:  # as stored before D was kept
        db.execute("UPDATE results SET similarity_npy = NULL WHERE job_id = ?", (other["id"],))
    body = assert_problem(client.get(f"/v1/jobs/{other['id']}/similarity"), 409)
    assert body["type"] == "/problems/no-similarity"
    with RegtreeClient(service.base_url) as rt, pytest.raises(Conflict):
        rt.similarity(other["id"])
    # the ZIP leaves it out instead of failing
    archive = zipfile.ZipFile(io.BytesIO(client.get(f"/v1/jobs/{other['id']}/export.zip")
                                         .content))
    assert not any(n.endswith("similarity.json") for n in archive.namelist())



def test_the_consensus_partner_speaks_shape_ids() -> None:
    """A polished subject's consensus names its partner by position (the library's key)
    and, in the service's document, by shape id beside it."""
    from registration import CPDOptions, SerialExecutor, build_dynamic_tree
    from registration._tree._polish import CONSENSUS_PARTNER_MIN_POINTS
    from registration.synthetic import chained_family
    from service.jobs.document import to_api_document

    fam = chained_family(n_chains=2, chain_length=5, n_points=CONSENSUS_PARTNER_MIN_POINTS,
                         step=0.3, seed=1)
    res = build_dynamic_tree(fam.shapes, 0, cpd=CPDOptions(max_iter=60),
                             executor=SerialExecutor())
    ids = [100 + 7 * k for k in range(len(fam.shapes))]
    light, full = to_api_document(1, res.to_dict(), ids)
    partners = []
    for subjects in (light["subjects"], full):
        for s in subjects:
            consensus = ((s.get("quality") or {}).get("polish") or {}).get("consensus")
            if consensus is not None:
                assert consensus["partner_shape_id"] == ids[consensus["partner"]]
                partners.append(consensus["partner"])
    assert partners and set(partners) - {0}, partners  # members as well as the root

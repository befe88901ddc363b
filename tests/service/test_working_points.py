"""Coarse-to-fine jobs: ``working_points`` through HTTP, the client and the CLI."""

from __future__ import annotations

import inspect
import re

import httpx
import pytest

from tests.service.conftest import (
    Service,
    assert_problem,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)
from tests.service.test_cli_client import regtree


def test_working_points_has_one_default_on_every_surface() -> None:
    from registration import build_dynamic_tree, build_static_tree, register_direct
    from registration._tree._resolution import DEFAULT_WORKING_POINTS as LIBRARY_DEFAULT
    from service.cli import _parser
    from service.client import RegtreeClient
    from service.contract.names import DEFAULT_WORKING_POINTS
    from service.schemas import JobCreate

    assert DEFAULT_WORKING_POINTS == LIBRARY_DEFAULT == 400
    for fn in (build_dynamic_tree, build_static_tree, register_direct, RegtreeClient.start_job):
        assert inspect.signature(fn).parameters["working_points"].default == 400, fn
    assert JobCreate.model_fields["working_points"].default == 400
    parser = _parser()
    base = ["run", "--collection", "c", "--model", "m"]
    assert parser.parse_args(base).working_points == 400
    assert parser.parse_args([*base, "--working-points", "150"]).working_points == 150
    assert parser.parse_args([*base, "--working-points", "0"]).working_points is None
    with pytest.raises(SystemExit):
        parser.parse_args([*base, "--working-points", "many"])


def test_working_points_round_trip_over_http(client: httpx.Client) -> None:
    shapes = family(n_chains=1, chain_length=3, n_points=120)
    cid = create_collection(client, "working-points")
    ids = upload_family(client, cid, shapes)

    job = submit_job(client, cid, ids[0], method="direct", working_points=40)
    assert job["params"]["working_points"] == 40
    done = wait_job(client, job["id"])
    assert done["status"] == "succeeded", done
    result = client.get(f"/v1/jobs/{job['id']}/result", params={"full": "true"}).json()
    assert result["options"]["working_points"] == 40
    for s in result["subjects"]:
        # decided on 40 points, reported at the stored 120
        assert len(s["warped"]) == 120 and len(s["correspondence"]) == 120
        assert max(s["correspondence"]) >= 40
        assert s["quality"]["working_error"] > 0

    default = submit_job(client, cid, ids[0], method="direct")
    assert default["params"]["working_points"] == 400
    full = submit_job(client, cid, ids[0], method="direct", working_points=None)
    assert full["params"]["working_points"] is None
    zero = submit_job(client, cid, ids[0], method="direct", working_points=0)
    assert zero["params"]["working_points"] is None
    for bad in (5, -1, 2.5, "many"):
        response = client.post("/v1/jobs", json={"collection_id": cid, "model_shape_id": ids[0],
                                                 "working_points": bad})
        assert_problem(response, 422)
    for j in (default, full, zero):
        assert wait_job(client, j["id"])["status"] == "succeeded"


def test_working_points_through_the_client_and_the_cli(service: Service) -> None:
    from service.client import RegtreeClient

    with RegtreeClient(service.base_url) as rt:
        coll = rt.create_collection("wp-client")
        shapes = [rt.upload_points(coll.id, n, p) for n, p in family(1, 2, 80)]
        job = rt.start_job(coll.id, shapes[0].id, method="direct", working_points=30)
        assert job.params["working_points"] == 30
        assert rt.start_job(coll.id, shapes[0].id, method="direct").params[
            "working_points"] == 400
        assert rt.start_job(coll.id, shapes[0].id, method="direct",
                            working_points=None).params["working_points"] is None
        run = regtree("run", "--collection", "wp-client", "--model", shapes[0].name,
                      "--method", "direct", "--working-points", "30", "-q",
                      url=service.base_url)
        assert run.returncode == 0, run.stderr
        cli_job = rt.get_job(int(re.findall(r"\d+", run.stdout)[-1]))
        assert cli_job.params["working_points"] == 30
        done = rt.wait(cli_job.id)
        assert done.status == "succeeded"
        assert rt.result(cli_job.id).document["options"]["working_points"] == 30

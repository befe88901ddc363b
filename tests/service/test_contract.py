"""The result contract: one vocabulary, one set of result models, used by every surface."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, get_args

import httpx
import pytest

import registration
from service.contract.names import (
    IMAGE_MODES,
    METHOD_FUNCTIONS,
    METHODS,
    SUBJECT_SORTS,
    ProblemType,
    is_attached,
    subject_status,
)
from service.contract.result import ResultDocument, SubjectDetail
from tests.service.conftest import REPO


def test_every_method_has_its_library_function() -> None:
    assert tuple(METHOD_FUNCTIONS) == METHODS
    for method, name in METHOD_FUNCTIONS.items():
        assert callable(getattr(registration, name)), method


def test_the_surfaces_take_the_vocabulary_from_the_contract() -> None:
    from service import cli_client, client, schemas

    assert get_args(schemas.JobCreate.model_fields["method"].annotation) == METHODS
    assert cli_client.METHODS is METHODS and cli_client.IMAGE_MODES is IMAGE_MODES
    assert client.SUBJECT_SORTS is SUBJECT_SORTS
    # no other module spells the lists out again (ingest and the shapes route are being
    # reorganised on another branch: they take IMAGE_MODES from here when that lands)
    pending = {"service/ingest.py", "service/api/routes/shapes.py"}
    for path in (REPO / "service").rglob("*.py"):
        if path.parent.name == "contract" or str(path.relative_to(REPO)) in pending:
            continue
        text = path.read_text()
        for names in (METHODS, IMAGE_MODES, SUBJECT_SORTS):
            spelled = ", ".join(f'"{n}"' for n in names)
            assert spelled not in text, f"{path.relative_to(REPO)} restates {names}"


def test_regtree_run_passes_its_options_to_start_job_by_name() -> None:
    import inspect

    from service.cli import _parser
    from service.cli_client.parser import RUN_JOB_OPTIONS
    from service.client import RegtreeClient

    start_job = inspect.signature(RegtreeClient.start_job).parameters
    args = _parser().parse_args(["run", "--collection", "c", "--model", "m"])
    for name in RUN_JOB_OPTIONS:
        assert start_job[name].kind is inspect.Parameter.KEYWORD_ONLY, name
        assert hasattr(args, name), name


def test_every_problem_type_in_the_service_is_declared() -> None:
    declared = {t.value for t in ProblemType}
    used = {
        m.group(0)
        for path in (REPO / "service").rglob("*.py")
        for m in re.finditer(r"/problems/[a-z-]+", path.read_text())
    }
    assert used <= declared, used - declared


@pytest.mark.parametrize(
    ("subject", "attached", "status"),
    [
        ({"layer": 2, "parent": 0}, True, "tree"),  # a document from before "attached"
        ({"layer": None, "parent": None}, False, "unattached"),
        ({"attached": True, "layer": 3, "leaf": True}, True, "leaf"),
        ({"attached": False, "layer": None, "leaf": False}, False, "unattached"),
    ],
)
def test_one_attached_rule(subject: dict[str, Any], attached: bool, status: str) -> None:
    assert is_attached(subject) is attached
    assert subject_status(subject) == status
    model = SubjectDetail.model_validate({"shape_id": 5, **subject})
    assert (model.attached, model.status) == (attached, status)


def test_the_library_document_validates_against_the_contract() -> None:
    from registration.synthetic import chained_family
    from service.jobs.document import json_safe as _json_safe
    from service.jobs.document import to_api_document

    fam = chained_family(n_chains=1, chain_length=3, n_points=40, seed=2)
    result = registration.build_dynamic_tree(fam.shapes, root=0, compare_direct=True)
    ids = [10 + k for k in range(len(fam.shapes))]
    document, subjects = to_api_document(7, _json_safe(result.to_dict()), ids)
    light = ResultDocument.model_validate(document)
    assert light.root_shape_id == 10 and [s.shape_id for s in light.subjects] == ids[1:]
    assert light.summary.subjects == len(ids) - 1
    for raw, lib in zip(subjects, result.subjects, strict=True):
        full = SubjectDetail.model_validate(raw)
        assert full.attached is lib.attached
        assert full.transform is not None and full.direct is not None
        assert [s.type for s in full.transform.steps] == [
            step["type"] for step in raw["transform"]["steps"]
        ]
        # the document round-trips: what the models dump is what the library wrote
        dumped = full.model_dump(mode="json", exclude_unset=True)
        assert [list(p) for p in dumped["warped"]] == raw["warped"]
        assert dumped["quality"] == raw["quality"]


def test_plots_take_e_statistics_from_the_library() -> None:
    from service.plots import layer_statistics

    doc = {
        "root_shape_id": 1,
        "subjects": [
            {"shape_id": 2, "layer": 2, "error": 0.1, "direct_error": 0.3},
            {"shape_id": 3, "layer": 2, "error": 0.2},
            {"shape_id": 4, "layer": 3, "error": 0.4, "direct": {"error": 0.5}},
            {"shape_id": 5, "layer": None, "error": 9.0},
        ],
    }
    tree, direct = layer_statistics(doc)
    assert tree == {
        2: registration.error_statistics([0.1, 0.2]),
        3: registration.error_statistics([0.4]),
    }
    assert direct[2] == registration.error_statistics([0.3])
    assert direct[3] == registration.error_statistics([0.5])


def test_openapi_describes_the_result_and_its_subject(client: httpx.Client) -> None:
    spec = client.get("/openapi.json").json()
    paths, schemas = spec["paths"], spec["components"]["schemas"]

    def body(path: str) -> dict[str, Any]:
        content = paths[path]["get"]["responses"]["200"]["content"]["application/json"]
        schema: dict[str, Any] = content["schema"]
        return schema

    assert body("/v1/jobs/{job_id}/result")["$ref"].endswith("/ResultDocument")
    assert body("/v1/jobs/{job_id}/result/subjects/{shape_id}")["$ref"].endswith(
        "/SubjectDetail"
    )
    subject = schemas["SubjectDetail"]["properties"]
    for key in ("shape_id", "parent_shape_id", "path_shape_ids", "confidence", "leaf",
                "attached", "status", "quality", "transform", "warped"):
        assert key in subject, key
    assert set(schemas["Summary"]["properties"]) >= {"subjects", "attached", "per_layer"}
    # the pose each subject started from, what each start reached and the margin it needed
    assert set(schemas["Quality"]["properties"]) >= {"pose", "pose_errors", "pose_margin"}
    assert "discriminator" in str(schemas["ChainTransformDoc"])


def test_the_client_reads_results_through_the_contract(client: httpx.Client) -> None:
    from service.client import JobResult

    old = {  # a result stored before attached, status and leaf existed
        "job_id": 3,
        "method": "dynamic_tree",
        "root_shape_id": 1,
        "summary": {"subjects": 2, "attached": 1},
        "subjects": [
            {"shape_id": 2, "name": "b", "layer": 2, "parent_shape_id": 1, "error": 0.1},
            {"shape_id": 3, "name": "c", "layer": None, "error": None},
        ],
    }
    result = JobResult.from_json(old)
    assert [s.attached for s in result.subjects] == [True, False]
    assert [s.status for s in result.subjects] == ["tree", "unattached"]
    assert result.model is not None and result.model.summary.attached == 1
    with pytest.raises(ValueError, match="shape_id"):
        JobResult.from_json({**old, "subjects": [{"name": "no id"}]})


def test_app_js_reads_the_servers_attached_and_status() -> None:
    from service.api.routes.pages import SCRIPTS

    text = "\n".join((Path(REPO) / "service" / "static" / n).read_text() for n in SCRIPTS)
    assert "const isAttached = (s) => s.attached === true;" in text
    assert "s.layer !== null" not in text


def test_client_and_cli_are_split_by_section_under_600_lines() -> None:
    import service.cli_client
    import service.client

    for package in (service.client, service.cli_client):
        folder = Path(package.__file__).parent
        for path in folder.glob("*.py"):
            assert len(path.read_text().splitlines()) <= 600, path
    # the public import paths hold
    from service.cli_client import COMMANDS, main  # noqa: F401
    from service.client import JobResult, RegtreeClient, Similarity, find_shape_files  # noqa: F401

    assert RegtreeClient.__doc__ and "base_url" in RegtreeClient.__doc__
    assert {"export", "similarity"} <= set(COMMANDS)


def test_compare_direct_has_one_default_on_every_surface() -> None:
    # the library, the job schema, the client and the CLI all default to no comparison
    import inspect

    from registration import build_dynamic_tree, build_static_tree
    from service.cli import _parser
    from service.client import RegtreeClient
    from service.contract.names import DEFAULT_COMPARE_DIRECT
    from service.schemas import JobCreate

    assert DEFAULT_COMPARE_DIRECT is False
    for fn in (build_dynamic_tree, build_static_tree, RegtreeClient.start_job):
        assert inspect.signature(fn).parameters["compare_direct"].default is False, fn
    assert JobCreate.model_fields["compare_direct"].default is False
    parser = _parser()
    assert parser.parse_args(["run", "--collection", "c", "--model", "m"]).compare_direct is False
    args = parser.parse_args(["run", "--collection", "c", "--model", "m", "--compare-direct"])
    assert args.compare_direct is True


def test_json_safe_replaces_every_non_finite_float_with_none() -> None:
    """Scalars, flat lists, points, nested containers and numpy values: each NaN or
    infinity becomes None (not valid JSON otherwise); everything else is kept."""
    import math

    import numpy as np

    from service.jobs.document import json_safe

    nan, inf = float("nan"), float("inf")
    value = {
        1: nan, "flat": [1.0, nan, -inf, 2.0], "mixed": [1, 2.5, "a", None, inf],
        "points": [[0.5, 1.5], [nan, 2.0], [3.0, inf]], "ragged": [[1.0, 2.0, nan], [1.0]],
        "nested": {"t": (1.0, (inf, 2)), "a": np.array([[1.0, np.nan], [2.0, 3.0]])},
        "g": np.float32(np.inf), "i": np.int64(3), "ok": 4.0,
    }
    assert json_safe(value) == {
        "1": None, "flat": [1.0, None, None, 2.0], "mixed": [1, 2.5, "a", None, None],
        "points": [[0.5, 1.5], [None, 2.0], [3.0, None]], "ragged": [[1.0, 2.0, None], [1.0]],
        "nested": {"t": [1.0, [None, 2]], "a": [[1.0, None], [2.0, 3.0]]},
        "g": None, "i": 3, "ok": 4.0,
    }
    big = [[float(k), math.pi] for k in range(1000)] + [[nan, 1.0]]
    assert json_safe(big)[-1] == [None, 1.0] and json_safe(big)[:-1] == big[:-1]
    # lists of finite numbers and points pass as they are (checked in one C pass); any
    # other entry sends them the slow way
    finite = [[float(k), math.pi] for k in range(1000)]
    assert json_safe(finite) is finite
    assert json_safe((1.0, 2, 3.5)) == [1.0, 2, 3.5]
    assert json_safe([[1.0, 2.0], [3.0, None], [inf, 1.0]]) == [[1.0, 2.0], [3.0, None],
                                                                 [None, 1.0]]
    assert json_safe([[1.0, 2.0], "a", {"k": nan}]) == [[1.0, 2.0], "a", {"k": None}]
    assert json_safe([1, 10**400, nan]) == [1, 10**400, None]  # beyond a float: no C pass
    assert json_safe([[1.0, 2.0], {3.0: nan}]) == [[1.0, 2.0], {"3.0": None}]

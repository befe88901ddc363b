"""The tests of ``test_schemathesis.py`` (the OpenAPI fuzz and its regressions), against a
scratch PostgreSQL database (``[postgresql]``; skipped unless ``REGTREE_TEST_POSTGRES_URL``
is set). A file of its own so that pytest-xdist, which runs a file on one worker at a time
(``--dist loadfile``), runs it beside the SQLite fuzz rather than after it: the two are the
longest files of the suite, and both have few tests, so the scheduler takes them last."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

pytest.importorskip("schemathesis", reason="schemathesis is not installed")

from tests.service import test_schemathesis as fuzz
from tests.service.conftest import POSTGRES_SKIP_REASON, POSTGRES_URL

# The module's fixtures and tests, the fuzz first (pytest runs a module's tests in the
# order its names were bound: test_fuzz_reached_every_operation reads what the fuzz saw).
seeded = fuzz.seeded
api_schema = fuzz.api_schema
_node_id_shim = fuzz._node_id_shim
test_openapi_fuzz = fuzz.test_openapi_fuzz
test_fuzz_reached_every_operation = fuzz.test_fuzz_reached_every_operation
test_ids_past_64_bits_are_422_not_500 = fuzz.test_ids_past_64_bits_are_422_not_500
test_job_ids_past_64_bits_are_422_not_500 = fuzz.test_job_ids_past_64_bits_are_422_not_500


@pytest.fixture(
    scope="module",
    params=[
        pytest.param(
            "postgresql", marks=pytest.mark.skipif(not POSTGRES_URL, reason=POSTGRES_SKIP_REASON)
        )
    ],
)
def database_url(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[str]:
    """A scratch PostgreSQL database for the fuzzed server."""
    yield from fuzz.fuzzed_database(request.param, tmp_path_factory)

"""Fixtures shared by the tests of ``bench/``'s helpers."""

from __future__ import annotations

import importlib
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"

#: The test files that take longest, longest first (seconds of one session's
#: ``--durations`` on the 2-core machine, bench/RESULTS.md 10.2). The suite runs a file
#: per worker at a time (``--dist loadfile``), and xdist would order the files by their
#: number of tests, which puts these few-test files last: the suite then ended on one of
#: them with the other worker idle. They go first, the rest after them by number of
#: tests, as xdist would (``--no-loadscope-reorder`` keeps this order), so the many
#: short files fill in at the end.
SLOW_FILES = (
    "tests/service/test_schemathesis.py",  # 290 (SQLite; again on PostgreSQL in CI)
    "tests/service/test_resilience.py",  # 190
    "tests/service/test_page_states.py",  # 115
    "tests/service/test_cli_client.py",  # 110
    "tests/service/test_cancel.py",  # 95
    "tests/service/test_page_browser.py",  # 85
    "tests/service/test_page_big_tree.py",  # 80
    "tests/service/test_callbacks.py",  # 75
    "tests/service/test_dask_jobs.py",  # 70
    "tests/service/test_demo.py",  # 70
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Run :data:`SLOW_FILES` first, then the other files by their number of tests; each
    file's tests keep their order (a stable sort on a key of the file alone)."""
    def file_of(item: pytest.Item) -> str:
        return item.nodeid.split("::", 1)[0]

    rank = {name: i for i, name in enumerate(SLOW_FILES)}
    count = Counter(file_of(item) for item in items)
    items.sort(key=lambda item: (rank.get(file_of(item), len(rank)), -count[file_of(item)],
                                 file_of(item)))


@pytest.fixture()
def bench_module(monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[[str], ModuleType]]:
    """Import a module of ``bench/`` by name (the scripts import each other as siblings,
    so ``bench/`` goes on the path); the modules loaded are forgotten after the test."""
    monkeypatch.syspath_prepend(str(BENCH))
    loaded: list[str] = []

    def load(name: str) -> ModuleType:
        loaded.append(name)
        return importlib.import_module(name)

    yield load
    for name in loaded:
        sys.modules.pop(name, None)


@pytest.fixture()
def bg(bench_module: Callable[[str], ModuleType]) -> ModuleType:
    """``bench/bench_groundtruth.py``, whose families' constructions the bench tests check."""
    return bench_module("bench_groundtruth")


@pytest.fixture()
def latin_font(bg: Any) -> Path:
    """A font of the bench's that draws 'a' on this machine (else the test is skipped)."""
    font = next((f for f in bg.FONTS.values() if f.exists() and bg.has_glyph("a", f)), None)
    if font is None:
        pytest.skip("no font of the bench's draws 'a' here")
    return font

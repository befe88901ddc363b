"""Every benchmark script imports against today's library.

The scripts in ``bench/`` reach into private modules (``registration._tree._rules``,
``registration._points`` ...) that move as the library is reorganised; a moved helper
otherwise shows up only when someone next runs the benchmark. Importing a script runs no
benchmark (each one works under ``if __name__ == "__main__"``) and reads no shared data.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py"))


def test_there_are_benchmarks() -> None:
    assert {"bench_groundtruth", "bench_cpd", "bench_service"} <= set(SCRIPTS)


@pytest.mark.parametrize("name", SCRIPTS)
def test_bench_script_imports(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(BENCH))  # the scripts import each other as siblings
    monkeypatch.setattr(sys, "argv", [f"{name}.py"])
    module = importlib.import_module(name)
    if name.startswith(("bench_", "calibrate_")):  # the rest are helpers the scripts import
        assert callable(getattr(module, "main", None)), f"bench/{name}.py has no main()"

"""The linters as tests: mypy and ruff over the code, clean as `.ci/run` requires them.

Run inside the suite, mypy's cold run (about 45 s of one core) shares the two pytest-xdist
workers with the rest of the suite instead of following it in `.ci/run`, whose own mypy then
reads the cache this run leaves (bench/RESULTS.md 10.3). Skipped where the tools are not
installed (they come with the ``test`` extra).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_tool(name: str, *args: str) -> subprocess.CompletedProcess[str]:
    tool = Path(sys.executable).parent / name
    if not tool.exists():
        pytest.skip(f"{name} is not installed beside {sys.executable} (the 'test' extra)")
    return subprocess.run(
        [str(tool), *args], cwd=ROOT, capture_output=True, text=True, timeout=300, check=False
    )


def test_mypy_is_clean() -> None:
    done = run_tool("mypy")
    assert done.returncode == 0, done.stdout + done.stderr


def test_ruff_is_clean() -> None:
    done = run_tool("ruff", "check", ".")
    assert done.returncode == 0, done.stdout + done.stderr

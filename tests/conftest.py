"""Fixtures shared by the tests of ``bench/``'s helpers."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


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

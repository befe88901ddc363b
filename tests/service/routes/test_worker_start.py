"""A worker says at start whether CPD's compiled E-step is in use (and with which instruction
set), and warns when not."""

from __future__ import annotations

import logging
import types
from pathlib import Path

import pytest

from registration._cpd import _switch
from service.worker import Worker

from .conftest import make_settings


@pytest.mark.parametrize("compiled", [True, False])
def test_worker_start_reports_the_compiled_kernel(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch,
        compiled: bool) -> None:
    fake = types.SimpleNamespace(simd=lambda: "x86-64-v3")
    monkeypatch.setattr(_switch, "CKERNEL", fake if compiled else None)
    worker = Worker(make_settings(tmp_path), worker_id="w-test")
    with caplog.at_level(logging.INFO, logger="regtree"):
        worker.run(burst=True)
    started = [r for r in caplog.records if r.getMessage() == "worker started"]
    assert len(started) == 1 and started[0].compiled_kernel is compiled  # type: ignore[attr-defined]
    assert started[0].simd == ("x86-64-v3" if compiled else None)  # type: ignore[attr-defined]
    warned = [r for r in caplog.records if "numpy's passes" in r.getMessage()]
    assert len(warned) == (0 if compiled else 1)
    if warned:
        assert warned[0].levelno == logging.WARNING

"""default_executor (registration/_executor.py): serial for small work or one CPU, else a
process pool that runs every task and can be closed."""

from __future__ import annotations

import os

import pytest

from registration import LocalProcessExecutor, SerialExecutor, default_executor


def _square(x: int) -> int:
    return x * x


def test_small_work_runs_serially_in_this_process() -> None:
    ex = default_executor(10)
    assert isinstance(ex, SerialExecutor)
    assert list(ex.map_unordered(_square, [3, 1, 2])) == [(0, 9), (1, 1), (2, 4)]
    assert isinstance(default_executor(63), SerialExecutor)
    assert isinstance(default_executor(5, min_parallel_tasks=6), SerialExecutor)


@pytest.mark.skipif(
    len(os.sched_getaffinity(0)) < 2, reason="a pool needs at least two usable CPUs"
)
def test_large_work_gets_a_pool_that_runs_every_task() -> None:
    ex = default_executor(64)
    assert isinstance(ex, LocalProcessExecutor)
    assert isinstance(default_executor(5, min_parallel_tasks=5), LocalProcessExecutor)
    with ex:
        out = dict(ex.map_unordered(_square, list(range(20))))
    assert out == {i: i * i for i in range(20)}  # each position once, unordered


def test_one_cpu_always_runs_serially(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: {0})
    assert isinstance(default_executor(10_000), SerialExecutor)

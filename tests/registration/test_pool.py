"""The library's process pool (LocalProcessExecutor) with each start method, and the stop
half of the Executor protocol. The service's cancel tests (tests/service/test_cancel.py)
run the same pool through a job."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time

import pytest

from registration import (
    Executor,
    LocalProcessExecutor,
    SerialExecutor,
    default_executor,
    start_fork_server,
)

METHODS = [
    m for m in ("fork", "forkserver", "spawn") if m in multiprocessing.get_all_start_methods()
]


def _square(x: int) -> int:
    return x * x


def _sleep(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def _parent_pid(_: int) -> int:
    return os.getppid()


class Stop(BaseException):
    pass


@pytest.mark.parametrize("method", METHODS)
def test_results_come_back_by_position_and_a_check_kills_the_tasks(method: str) -> None:
    deadline = float("inf")

    def check() -> None:
        if time.monotonic() > deadline:
            raise Stop

    pool = LocalProcessExecutor(2, check=check, poll_seconds=0.05, start_method=method)
    try:
        assert dict(pool.map_unordered(_square, list(range(7)))) == {i: i * i for i in range(7)}
        processes = pool.processes
        assert len(processes) == 2
        deadline = time.monotonic() + 0.3
        with pytest.raises(Stop):
            list(pool.map_unordered(_sleep, [30.0] * 4))
        assert pool.processes == []
        for process in processes:
            process.join(5)
            assert not process.is_alive()
        deadline = float("inf")
        assert dict(pool.map_unordered(_square, [3])) == {0: 9}  # new processes
    finally:
        pool.close()


def test_a_fork_server_started_ahead_serves_the_pools_started_beside_threads() -> None:
    if "forkserver" not in multiprocessing.get_all_start_methods():
        assert start_fork_server() is False
        return
    assert start_fork_server() is True
    from multiprocessing import forkserver

    server = forkserver._forkserver._forkserver_pid  # type: ignore[attr-defined]
    assert server is not None
    assert start_fork_server() is True  # already running: the same server
    assert forkserver._forkserver._forkserver_pid == server  # type: ignore[attr-defined]
    release = threading.Event()
    thread = threading.Thread(target=release.wait, daemon=True)
    thread.start()  # beside a thread the pool takes its processes from the fork server
    try:
        with LocalProcessExecutor(2) as pool:
            parents = {pid for _, pid in pool.map_unordered(_parent_pid, range(4))}
    finally:
        release.set()
    assert parents == {server}


def test_a_forked_process_sees_the_end_of_its_pipe() -> None:
    """A forked process holds copies of the pool's ends of the pipes created before it: it
    closes them, so each process ends once the pool's end of its own pipe is closed."""
    pool = LocalProcessExecutor(2, start_method="fork")
    try:
        dict(pool.map_unordered(_square, [1, 2]))
        first = pool.processes[0]
        pool._slots[0].connection.close()
        first.join(10)
        assert not first.is_alive() and first.exitcode == 0
    finally:
        pool.terminate()


def test_terminate_and_close_are_the_protocol_for_every_executor() -> None:
    executors: list[Executor] = [SerialExecutor(), LocalProcessExecutor(1), default_executor(1)]
    for executor in executors:
        assert dict(executor.map_unordered(_square, [2, 3])) == {0: 4, 1: 9}
        executor.terminate()
        assert dict(executor.map_unordered(_square, [4])) == {0: 16}
        executor.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_workers": 0}, "max_workers must be an integer >= 1; got 0"),
        ({"max_workers": 1.5}, "max_workers must be an integer >= 1; got 1.5"),
        ({"poll_seconds": 0}, "poll_seconds must be > 0; got 0"),
        ({"start_method": "thread"}, "start_method must be one of"),
    ],
)
def test_bad_pool_options(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LocalProcessExecutor(**kwargs)  # type: ignore[arg-type]


def _blas_threads(_: object) -> list[int]:
    from threadpoolctl import threadpool_info

    return [int(lib["num_threads"]) for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_pool_processes_share_the_cpus_out_for_the_blas(method: str) -> None:
    """Each process keeps its BLAS to the CPUs divided between the processes: one thread
    with the default one process per CPU, so the pool does not oversubscribe the machine."""
    pytest.importorskip("threadpoolctl")
    from registration._pool import available_cpus

    cpus = available_cpus()
    for workers in sorted({1, cpus}):
        with LocalProcessExecutor(max_workers=workers, start_method=method) as ex:
            found = [threads for _, threads in ex.map_unordered(_blas_threads, range(workers))]
        want = max(1, cpus // workers)
        assert found and all(t and max(t) <= want for t in found), (workers, found)
        if workers == cpus:
            assert all(max(t) == 1 for t in found)

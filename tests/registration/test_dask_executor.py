"""The Dask executor on a LocalCluster: results, cancel, a lost worker, no worker at all."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

distributed = pytest.importorskip(
    "distributed", reason="dask[distributed] is not installed (the 'dask' extra)")

from registration import (  # noqa: E402
    DaskClusterError,
    DaskExecutor,
    SerialExecutor,
    similarity_matrix,
)
from registration.synthetic import chained_family  # noqa: E402


def _square(x: int) -> int:
    return x * x


def _slow_square(x: int) -> int:
    time.sleep(0.3)
    return x * x


def _pid(_: int) -> int:
    time.sleep(0.2)
    return os.getpid()


def _die(_: int) -> int:
    os.kill(os.getpid(), signal.SIGKILL)
    return 0


class Stop(Exception):
    pass


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=":0") as c:
        yield c


def test_map_unordered_gives_every_result(cluster) -> None:
    with DaskExecutor(cluster.scheduler_address) as ex:
        out = dict(ex.map_unordered(_square, list(range(20))))
    assert out == {k: k * k for k in range(20)}


def test_similarity_on_dask_equals_serial(cluster) -> None:
    shapes = chained_family(n_chains=2, chain_length=3, n_points=60, seed=1).shapes
    with DaskExecutor(cluster.scheduler_address) as ex:
        on_dask = similarity_matrix(shapes, executor=ex)
    serial = similarity_matrix(shapes, executor=SerialExecutor())
    np.testing.assert_allclose(on_dask.D, serial.D)


def test_caller_client_is_not_closed(cluster) -> None:
    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        ex = DaskExecutor(client)
        assert dict(ex.map_unordered(_square, [3])) == {0: 9}
        ex.close()
        assert client.status == "running"


def test_check_cancels_the_tasks_not_finished(cluster) -> None:
    calls = {"n": 0}

    def check() -> None:
        calls["n"] += 1
        if calls["n"] > 3:
            raise Stop

    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        ex = DaskExecutor(client, check=check, poll_seconds=0.05)
        got = []
        with pytest.raises(Stop):
            for k, r in ex.map_unordered(_slow_square, list(range(40))):
                got.append((k, r))
        assert len(got) < 40
        # the cancelled tasks leave the cluster: none still waits to run
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            processing = client.processing()
            if not any(processing.values()):
                break
            time.sleep(0.1)
        assert not any(client.processing().values())


def test_consumer_leaving_cancels(cluster) -> None:
    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        ex = DaskExecutor(client)
        it = ex.map_unordered(_slow_square, list(range(40)))
        next(it)
        it.close()
        deadline = time.monotonic() + 10
        while any(client.processing().values()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(client.processing().values())


def test_no_worker_fails_clearly() -> None:
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as c:
        ex = DaskExecutor(c.scheduler_address, no_worker_seconds=0.5)
        with pytest.raises(DaskClusterError, match="no worker"):
            list(ex.map_unordered(_square, [1, 2]))
        ex.terminate()


def test_task_exception_propagates(cluster) -> None:
    with DaskExecutor(cluster.scheduler_address) as ex, pytest.raises(ZeroDivisionError):
        list(ex.map_unordered(lambda x: 1 / x, [1, 0]))


def test_unreachable_scheduler() -> None:
    with pytest.raises(DaskClusterError, match="cannot reach"):
        DaskExecutor("tcp://127.0.0.1:9", connect_seconds=1)


def test_bad_scheduler_argument() -> None:
    with pytest.raises(ValueError, match="scheduler"):
        DaskExecutor("")


@pytest.mark.timeout(180)
def test_lost_worker_tasks_run_elsewhere() -> None:
    """A worker process killed mid-run: its tasks are reassigned and the run completes."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as c:
        with distributed.Client(c.scheduler_address, set_as_default=False) as client:
            pids = set(client.run(os.getpid).values())
            ex = DaskExecutor(client)
            results = {}
            killed = False
            for k, r in ex.map_unordered(_pid, list(range(30))):
                results[k] = r
                if not killed:
                    os.kill(r, signal.SIGKILL)  # the worker that ran the first task
                    killed = True
            assert sorted(results) == list(range(30))
            assert set(results.values()) <= pids | set(client.run(os.getpid).values())


@pytest.mark.timeout(180)
def test_worker_killed_every_time_fails_clearly() -> None:
    """A task that kills its workers more often than the scheduler allows fails the run
    with a message, not a hang."""
    import dask

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), \
            distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                     dashboard_address=":0") as c:
        ex = DaskExecutor(c.scheduler_address)
        with pytest.raises(DaskClusterError, match="died"):
            list(ex.map_unordered(_die, [0]))
        ex.terminate()

"""The worker's process pool: registrations that stop as soon as their job must.

The library runs every heavy task (similarity, registrations) through an executor's
``map_unordered`` and reports progress only when a task completes, so a run stopped from the
progress callback goes on until the next registration ends, and a pool closed the ordinary
way waits for the registrations still running: many seconds with large shapes. This pool
instead

* waits for results in short slices and calls ``check`` between them (the job's
  :meth:`~service.jobs.runner.JobControl.check`, which raises once the job was cancelled,
  its lease was lost or the worker is shutting down), so the run stops within a slice;
* kills its processes when the run stops early (interrupted, a task failed, or the consumer
  left), instead of waiting for the registrations in progress: their results are not wanted.

It implements the library's ``Executor`` protocol (``registration._executor``), like
``LocalProcessExecutor``, whose internals it does not touch.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

logger = logging.getLogger("regtree.executor")


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class InterruptibleProcessExecutor:
    """A local process pool for one job, stopped at once when ``check`` raises.

    Parameters
    ----------
    check : callable
        Called in the calling thread between waits; whatever it raises stops the run (the
        pool's processes are killed, and the exception propagates out of the library).
    max_workers : int, optional
        Processes; the CPUs available by default.
    poll_seconds : float
        Longest wait for a result between two calls of ``check``.
    max_pending : int, optional
        Tasks submitted ahead of completion (``2 * max_workers`` by default): few, so that
        little is queued when the run stops.
    """

    def __init__(
        self,
        check: Callable[[], None],
        *,
        max_workers: int | None = None,
        poll_seconds: float = 0.1,
        max_pending: int | None = None,
    ) -> None:
        self.max_workers = max_workers if max_workers is not None else available_cpus()
        if self.max_workers < 1:
            raise ValueError(f"max_workers must be at least 1; got {self.max_workers}")
        self.check = check
        self.poll_seconds = poll_seconds
        self.max_pending = max_pending if max_pending is not None else 2 * self.max_workers
        self._pool: ProcessPoolExecutor | None = None

    def _ensure_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            # The worker runs threads (heartbeat, parent watch) and holds database
            # connections, so no plain fork: a fork server with the library preloaded.
            methods = multiprocessing.get_all_start_methods()
            method = "forkserver" if "forkserver" in methods else "spawn"
            context = multiprocessing.get_context(method)
            if method == "forkserver":
                context.set_forkserver_preload(["registration"])
            self._pool = ProcessPoolExecutor(max_workers=self.max_workers, mp_context=context)
        return self._pool

    def map_unordered(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R]]:
        """``(position, fn(item))`` in completion order; see the library's ``Executor``."""
        self.check()
        pool = self._ensure_pool()
        pending: dict[Future[R], int] = {}
        next_item = 0
        finished = False
        try:
            while next_item < len(items) or pending:
                while next_item < len(items) and len(pending) < self.max_pending:
                    pending[pool.submit(fn, items[next_item])] = next_item
                    next_item += 1
                done, _ = wait(
                    list(pending), timeout=self.poll_seconds, return_when=FIRST_COMPLETED
                )
                for future in done:
                    position = pending.pop(future)
                    yield position, future.result()
                self.check()
            finished = True
        finally:
            if not finished:
                # Interrupted, a task failed, or the consumer stopped (its progress callback
                # raised): nothing still running is wanted.
                for future in pending:
                    future.cancel()
                self.terminate()

    def terminate(self) -> None:
        """Kill the pool's processes now (tasks in progress are lost) and release it."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        kill_workers = getattr(pool, "kill_workers", None)  # Python 3.14
        if callable(kill_workers):
            kill_workers()
        else:
            for process in _pool_processes(pool):
                if process.is_alive():
                    process.kill()
        # With its processes gone the pool is broken: shutting it down fails what was
        # queued and returns without waiting for any task.
        pool.shutdown(wait=True, cancel_futures=True)

    def close(self) -> None:
        """Release the pool when the job is done (nothing runs any more)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def __repr__(self) -> str:
        return f"InterruptibleProcessExecutor(max_workers={self.max_workers})"


def _pool_processes(pool: ProcessPoolExecutor) -> list[Any]:
    """The pool's worker processes (``ProcessPoolExecutor`` keeps them in ``_processes``
    until Python 3.14 gives it ``kill_workers``)."""
    for _ in range(3):
        try:
            return list((getattr(pool, "_processes", None) or {}).values())
        except RuntimeError:  # the pool's manager thread changed the dict meanwhile
            continue
    logger.warning("could not list the pool's processes; waiting for its tasks instead")
    return []

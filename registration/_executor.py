"""Executors: where the heavy, independent tasks of a collection run.

The algorithms only ever call :meth:`Executor.map_unordered` with a picklable top-level
function and a list of picklable items, and consume ``(position, result)`` pairs as they
complete. A local process pool is the default; a distributed engine (for example Dask's
``Client.map`` with ``as_completed``) plugs in by implementing the same one method.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Protocol, TypeVar

T = TypeVar("T")
R = TypeVar("R")

__all__ = [
    "Executor",
    "LocalProcessExecutor",
    "SerialExecutor",
    "default_executor",
    "owned_executor",
]


class Executor(Protocol):
    """Runs independent tasks; results come back as they complete."""

    def map_unordered(
        self, fn: Callable[[T], R], items: Sequence[T]
    ) -> Iterator[tuple[int, R]]:
        """Yield ``(position in items, fn(item))`` for every item, in completion order.

        If the consumer stops early (for example because a progress callback raised to
        cancel the run), tasks not yet started must not run.
        """
        ...


# The interruption check of the task running in this thread (see SerialExecutor).
_CHECK: ContextVar[Callable[[], None] | None] = ContextVar("regtree_check", default=None)


def checkpoint() -> None:
    """Let the executor running the current task stop it here.

    Long loops of the library (CPD's EM iterations) call this once per iteration. Under a
    :class:`SerialExecutor` given a `check`, it calls that check, whose exception aborts
    the task and propagates to the caller; elsewhere (pool processes) it does nothing.
    """
    check = _CHECK.get()
    if check is not None:
        check()


class SerialExecutor:
    """Runs every task in the calling process, in order.

    Parameters
    ----------
    check : callable, optional
        Called before each task and at every :func:`checkpoint` inside it (each CPD
        iteration); an exception it raises stops the run there and propagates. This is
        how a caller cancels a serial run promptly, without waiting for the registration
        in progress.
    """

    def __init__(self, check: Callable[[], None] | None = None) -> None:
        self.check = check

    def map_unordered(
        self, fn: Callable[[T], R], items: Sequence[T]
    ) -> Iterator[tuple[int, R]]:
        for i, item in enumerate(items):
            if self.check is not None:
                self.check()
            token = _CHECK.set(self.check)
            try:
                result = fn(item)
            finally:
                _CHECK.reset(token)
            yield i, result

    def __repr__(self) -> str:
        return "SerialExecutor()" if self.check is None else f"SerialExecutor(check={self.check!r})"


class LocalProcessExecutor:
    """A pool of local worker processes (``concurrent.futures``, spawn-safe).

    Parameters
    ----------
    max_workers : int, optional
        Number of processes; defaults to the CPUs available to this process.
    max_pending : int, optional
        Tasks submitted ahead of completion (bounded so a cancelled run stops quickly);
        defaults to ``4 * max_workers``.
    start_method : {"fork", "forkserver", "spawn"}, optional
        How worker processes start. Default: "fork" where available while the calling
        process runs a single thread (works in notebooks and in scripts without a
        ``__main__`` guard), else "forkserver" (safe beside threads, but the calling
        script must guard its entry point with ``if __name__ == "__main__":``).

    Notes
    -----
    The pool is created on first use and reused until :meth:`close` (or the end of a
    ``with`` block), so a collection's stages share one set of warm processes.
    """

    def __init__(
        self,
        max_workers: int | None = None,
        *,
        max_pending: int | None = None,
        start_method: str | None = None,
    ):
        n = max_workers if max_workers is not None else _available_cpus()
        if n < 1:
            raise ValueError(f"max_workers must be at least 1; got {n}")
        methods = multiprocessing.get_all_start_methods()
        if start_method is not None and start_method not in methods:
            raise ValueError(f"start_method must be one of {methods}; got {start_method!r}")
        self.start_method = start_method
        self.max_workers = n
        self.max_pending = max_pending if max_pending is not None else 4 * n
        self._pool: ProcessPoolExecutor | None = None

    def _ensure_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            method = self.start_method
            if method is None:
                single = threading.active_count() == 1
                method = "fork" if single and "fork" in multiprocessing.get_all_start_methods() \
                    else "forkserver"
            ctx = multiprocessing.get_context(method)
            self._pool = ProcessPoolExecutor(max_workers=self.max_workers, mp_context=ctx)
        return self._pool

    def map_unordered(
        self, fn: Callable[[T], R], items: Sequence[T]
    ) -> Iterator[tuple[int, R]]:
        pool = self._ensure_pool()
        pending: dict[Future[R], int] = {}
        next_item = 0
        try:
            while next_item < len(items) or pending:
                while next_item < len(items) and len(pending) < self.max_pending:
                    pending[pool.submit(fn, items[next_item])] = next_item
                    next_item += 1
                done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                for fut in done:
                    pos = pending.pop(fut)
                    yield pos, fut.result()
        finally:
            for fut in pending:
                fut.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> LocalProcessExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"LocalProcessExecutor(max_workers={self.max_workers})"


def _available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def default_executor(n_tasks: int, *, min_parallel_tasks: int = 64) -> Executor:
    """Serial for small jobs (a pool's start-up would dominate), else a local pool.

    A returned :class:`LocalProcessExecutor` holds processes until it is closed; prefer
    :func:`owned_executor`, which closes what it creates.

    Parameters
    ----------
    n_tasks : int
        Number of tasks (or a proxy for the work) the executor will run.
    min_parallel_tasks : int
        Below this, or on a single-CPU machine, the work runs serially.

    Returns
    -------
    Executor
        :class:`SerialExecutor` or :class:`LocalProcessExecutor`.
    """
    if n_tasks < min_parallel_tasks or _available_cpus() < 2:
        return SerialExecutor()
    return LocalProcessExecutor()


@contextmanager
def owned_executor(executor: Executor | None, n_tasks: int) -> Iterator[Executor]:
    """The caller's executor as it is, or a default one for `n_tasks` tasks that is
    closed (its processes stopped) when the block ends."""
    if executor is not None:
        yield executor
        return
    created = default_executor(n_tasks)
    try:
        yield created
    finally:
        if isinstance(created, LocalProcessExecutor):
            created.close()

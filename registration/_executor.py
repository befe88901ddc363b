"""Executors: where the heavy, independent tasks of a collection run.

The algorithms only ever call :meth:`Executor.map_unordered` with a picklable top-level
function and a list of picklable items, and consume ``(position, result)`` pairs as they
complete. A local process pool (:class:`LocalProcessExecutor`, in :mod:`._pool`) is the
default; a distributed engine (for example Dask's ``Client.map`` with ``as_completed``) plugs
in by implementing the same protocol: that method, and :meth:`Executor.close` and
:meth:`Executor.terminate`, which say how its owner stops it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Protocol, TypeVar

from ._pool import LocalProcessExecutor, WorkerProcessDied, available_cpus, start_fork_server

T = TypeVar("T")
R = TypeVar("R")

__all__ = [
    "Executor",
    "LocalProcessExecutor",
    "SerialExecutor",
    "WorkerProcessDied",
    "available_cpus",
    "default_executor",
    "owned_executor",
    "start_fork_server",
]


class Executor(Protocol):
    """Runs independent tasks; results come back as they complete; stops when told.

    A run is stopped early in one of two ways, and must then not start the tasks not yet
    started: the consumer leaves the iteration of :meth:`map_unordered` (the library's
    progress callback raised), or the executor's own check raises (``check`` of
    :class:`LocalProcessExecutor` and :class:`SerialExecutor`). Who stops the executor
    calls :meth:`terminate` if its tasks are not wanted any more, :meth:`close` when the
    work is done.
    """

    def map_unordered(
        self, fn: Callable[[T], R], items: Sequence[T]
    ) -> Iterator[tuple[int, R]]:
        """Yield ``(position in items, fn(item))`` for every item, in completion order."""
        ...

    def close(self) -> None:
        """Release the executor's resources (processes, ...) once its work is done."""
        ...

    def terminate(self) -> None:
        """Stop now: abandon the tasks in progress (kill or cancel them) and release the
        resources. Must not wait for tasks to finish."""
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

    def close(self) -> None:
        """Nothing to release."""

    def terminate(self) -> None:
        """Nothing runs in the background: a task in progress stops at its next
        :func:`checkpoint` when ``check`` raises."""

    def __repr__(self) -> str:
        return "SerialExecutor()" if self.check is None else f"SerialExecutor(check={self.check!r})"


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
    if n_tasks < min_parallel_tasks or available_cpus() < 2:
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
        created.close()

"""The local process pool: tasks in worker processes, stopped at once when they are not wanted.

The library reports progress only when a task completes, so a run stopped from the progress
callback would go on until the next registration ends, and a pool closed the ordinary way
waits for the registrations still running: many seconds with large shapes. This pool instead

* waits for results in short slices and calls its ``check`` between them (the service passes
  its job's check, which raises once the job was cancelled, its lease was lost or the worker
  is shutting down), so a run stops within a slice;
* kills its processes when a run stops early (interrupted, a task failed, or the consumer
  left), instead of waiting for the registrations in progress: their results are not wanted.

It is built on plain ``multiprocessing`` processes, one pipe each and one task at a time per
process, with nothing but the calling thread writing to the pipes. (Killing the processes of
a ``concurrent.futures.ProcessPoolExecutor`` is not safe: its feeder thread can be blocked
for ever writing a large task into a queue that nobody reads any more, and its shutdown then
never returns.) A process that dies while running a task fails the run with
:class:`WorkerProcessDied`.
"""

from __future__ import annotations

import logging
import multiprocessing
import numbers
import os
import pickle
import signal
import threading
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from typing import Any, Self, TypeVar

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["LocalProcessExecutor", "WorkerProcessDied", "available_cpus", "start_fork_server"]

logger = logging.getLogger("regtree.executor")


def available_cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class WorkerProcessDied(RuntimeError):
    """A process of the pool ended while it ran a task (killed, out of memory, crashed)."""


def _limit_blas_threads(threads: int) -> None:
    """Keep this process's BLAS to `threads` threads for its whole life.

    A pool runs one process per CPU (by default), each with one task at a time: a BLAS
    that also starts a thread per CPU in each of them oversubscribes the CPUs, measured
    5-10x slower than one thread (see ``_cpd._nonrigid.BLAS_THREADS``, which covers CPD
    itself). Outside CPD, the warps, their Jacobians at the stored resolution, the
    similarity's ICP and the errors use the BLAS too: 65 ms against 3 ms for the kernel
    product of one stored-resolution warp on a busy 2-core machine.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional at run time: then the BLAS keeps its own setting
        return
    threadpool_limits(limits=threads, user_api="blas")


def _serve(connection: Connection, inherited: list[Connection], blas_threads: int) -> None:
    """A pool process: run ``(fn, item)`` tasks until the pipe closes or a ``None`` comes."""
    _limit_blas_threads(blas_threads)
    # A forked process holds copies of the pool's ends of every pipe: close them, so that
    # this process sees the end of its pipe when the pool's process goes away.
    for other in inherited:
        other.close()
    # Ctrl-C reaches the whole process group: the pool's owner decides what stops, and
    # kills this process if it must.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        try:
            task = connection.recv()
        except (EOFError, OSError):
            return
        if task is None:
            return
        fn, item = task
        try:
            reply: tuple[bool, Any, str] = (True, fn(item), "")
        except Exception as e:
            reply = (False, e, "".join(traceback.format_exception(e)))
        try:
            connection.send(reply)
        except (EOFError, OSError):
            return
        except Exception as e:  # a result or an exception that does not pickle
            text = "".join(traceback.format_exception(e))
            connection.send((False, RuntimeError(f"cannot send the task's outcome: {e}"), text))


@dataclass
class _Slot:
    process: BaseProcess
    connection: Connection
    position: int | None = None  # the task it runs, if any


def _context(method: str | None) -> Any:
    """The multiprocessing context (a SpawnContext-like object) for a start method."""
    methods = multiprocessing.get_all_start_methods()
    if method is None:
        if threading.active_count() == 1 and "fork" in methods:
            method = "fork"
        else:  # no fork beside threads (they may hold locks): a fork server, else spawn
            method = "forkserver" if "forkserver" in methods else "spawn"
    context: Any = multiprocessing.get_context(method)
    if method == "forkserver":
        context.set_forkserver_preload(["registration"])
    return context


def start_fork_server() -> bool:
    """Start the fork server that pools started beside threads take their processes from
    (see :class:`LocalProcessExecutor`), with the library preloaded, now rather than at
    the first pool's first task.

    The first pool of a process with threads (a service worker: its job's heartbeat
    thread runs) otherwise waits for the server to start and import the library, about
    0.75 s on a 2-core machine against 0.02-0.03 s for every later pool
    (bench/RESULTS.md 7.24). The server imports the library in its own process: this call
    returns at once, and a pool started meanwhile waits only for what is left of it.
    Calling it again while the server runs does nothing.

    Returns
    -------
    bool
        True when the fork server runs; False where the platform has none (pools then
        spawn their processes).
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return False
    from multiprocessing import forkserver

    _context("forkserver")  # sets the preload, as every pool does
    forkserver.ensure_running()
    return True


class ClosedOnExit:
    """``with executor:`` closes the executor (its ``close``) on the way out, however it
    leaves; the executors that hold processes or a connection share this."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalProcessExecutor(ClosedOnExit):
    """A pool of local worker processes, stopped at once when ``check`` raises.

    Parameters
    ----------
    max_workers : int, optional
        Number of processes; defaults to the CPUs available to this process.
    check : callable, optional
        Called in the calling thread between waits for results, at most ``poll_seconds``
        apart; whatever it raises stops the run: the processes are killed, and the
        exception propagates out of the library. This is how a caller cancels a run
        promptly, registrations in progress included.
    poll_seconds : float
        Longest wait for a result between two calls of ``check``.
    start_method : {"fork", "forkserver", "spawn"}, optional
        How worker processes start. Default: "fork" where available while the calling
        process runs a single thread (works in notebooks and in scripts without a
        ``__main__`` guard), else "forkserver" with the library preloaded (safe beside
        threads, but the calling script must guard its entry point with
        ``if __name__ == "__main__":``), else "spawn".

    Notes
    -----
    The processes start on first use and are reused until :meth:`close` (or the end of a
    ``with`` block), so a collection's stages share one set of warm processes. A run that
    stops early (``check`` raised, a task failed, the consumer left) kills them
    (:meth:`terminate`); the next run starts new ones.
    """

    def __init__(
        self,
        max_workers: int | None = None,
        *,
        check: Callable[[], None] | None = None,
        poll_seconds: float = 0.1,
        start_method: str | None = None,
    ) -> None:
        n = max_workers if max_workers is not None else available_cpus()
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
            raise ValueError(f"max_workers must be an integer >= 1; got {n!r}")
        methods = multiprocessing.get_all_start_methods()
        if start_method is not None and start_method not in methods:
            raise ValueError(f"start_method must be one of {methods}; got {start_method!r}")
        if not poll_seconds > 0:
            raise ValueError(f"poll_seconds must be > 0; got {poll_seconds!r}")
        self.max_workers: int = int(n)
        self.check: Callable[[], None] | None = check
        self.poll_seconds: float = poll_seconds
        self.start_method: str | None = start_method
        self._slots: list[_Slot] = []

    @property
    def processes(self) -> list[BaseProcess]:
        """The pool's processes (none before the first task, nor after it was stopped)."""
        return [slot.process for slot in self._slots]

    def _start(self) -> None:
        if self._slots:
            return
        context = _context(self.start_method)
        forked = context.get_start_method() == "fork"
        # the CPUs shared out between the processes
        blas_threads = max(1, available_cpus() // self.max_workers)
        try:
            for k in range(self.max_workers):
                ours, theirs = context.Pipe(duplex=True)
                inherited = [ours] + [s.connection for s in self._slots] if forked else []
                process = context.Process(
                    target=_serve, args=(theirs, inherited, blas_threads),
                    name=f"regtree-task-{k}", daemon=True
                )
                process.start()
                theirs.close()
                self._slots.append(_Slot(process, ours))
        except BaseException:
            self.terminate()
            raise

    def map_unordered(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R]]:
        """``(position, fn(item))`` in completion order; see :class:`~registration.Executor`."""
        if self.check is not None:
            self.check()
        if not items:
            return
        self._start()
        timeout = self.poll_seconds if self.check is not None else None
        next_item = 0
        running = 0
        finished = False
        try:
            while next_item < len(items) or running:
                for slot in self._slots:
                    if slot.position is None and next_item < len(items):
                        self._send(slot, (fn, items[next_item]), next_item)
                        slot.position = next_item
                        next_item += 1
                        running += 1
                busy = [slot for slot in self._slots if slot.position is not None]
                ready = wait(
                    [s.connection for s in busy] + [s.process.sentinel for s in busy],
                    timeout=timeout,
                )
                for slot in busy:
                    if slot.connection in ready or slot.process.sentinel in ready:
                        position, result = self._collect(slot)
                        running -= 1
                        yield position, result
                if self.check is not None:
                    self.check()
            finished = True
        finally:
            if not finished:
                # Interrupted, a task failed, or the consumer stopped (its progress callback
                # raised): nothing still running is wanted.
                self.terminate()

    def _send(self, slot: _Slot, task: tuple[Any, Any], position: int) -> None:
        try:
            slot.connection.send(task)
        except (BrokenPipeError, ConnectionResetError) as e:
            slot.process.join(1.0)
            raise WorkerProcessDied(
                f"a pool process (pid {slot.process.pid}) ended with exit code "
                f"{slot.process.exitcode} before it could take task {position}"
            ) from e

    def _collect(self, slot: _Slot) -> tuple[int, Any]:
        """The outcome of the task ``slot`` runs: its result, or its exception raised."""
        position, slot.position = slot.position, None
        assert position is not None
        try:
            ok, value, remote = slot.connection.recv()
        except (EOFError, OSError, pickle.UnpicklingError) as e:
            slot.process.join(1.0)
            raise WorkerProcessDied(
                f"a pool process (pid {slot.process.pid}) ended with exit code "
                f"{slot.process.exitcode} while it ran task {position}"
            ) from e
        if not ok:
            if remote and isinstance(value, BaseException):
                value.add_note(f"in the pool process:\n{remote}")
            raise value
        return position, value

    def terminate(self) -> None:
        """Stop now: kill the processes; tasks in progress are lost. The pool can be used
        again (new processes start)."""
        slots, self._slots = self._slots, []
        for slot in slots:
            if slot.process.is_alive():
                slot.process.kill()
        for slot in slots:
            slot.process.join(5.0)
            slot.connection.close()
            if slot.process.is_alive():  # pragma: no cover - SIGKILL not delivered
                logger.warning("pool process did not stop", extra={"pid": slot.process.pid})

    def close(self) -> None:
        """Stop when the work is done: idle processes exit, busy ones are killed."""
        slots, self._slots = self._slots, []
        for slot in slots:
            if slot.position is None:
                try:
                    slot.connection.send(None)
                except (OSError, ValueError):
                    pass
        for slot in slots:
            slot.process.join(0 if slot.position is not None else 5.0)
            if slot.process.is_alive():
                slot.process.kill()
                slot.process.join(5.0)
            slot.connection.close()

    def __repr__(self) -> str:
        return f"LocalProcessExecutor(max_workers={self.max_workers})"

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

It is built on plain ``multiprocessing`` processes, one pipe each and one task at a time
per process, with nothing but the calling thread writing to the pipes. (Killing the
processes of a ``concurrent.futures.ProcessPoolExecutor`` is not safe: its feeder thread can
be blocked for ever writing a large task into a queue that nobody reads any more, and its
shutdown then never returns.) A process that dies while running a task fails the run with
:class:`WorkerProcessDied`.

It implements the library's ``Executor`` protocol (``registration._executor``), like
``LocalProcessExecutor``.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

logger = logging.getLogger("regtree.executor")


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class WorkerProcessDied(RuntimeError):
    """A process of the pool ended while it ran a task (killed, out of memory, crashed)."""


def _serve(connection: Connection) -> None:
    """A pool process: run ``(fn, item)`` tasks until the pipe closes or a ``None`` comes."""
    # Ctrl-C reaches the whole process group: the worker above decides what stops, and
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
    """

    def __init__(
        self,
        check: Callable[[], None],
        *,
        max_workers: int | None = None,
        poll_seconds: float = 0.1,
    ) -> None:
        self.max_workers = max_workers if max_workers is not None else available_cpus()
        if self.max_workers < 1:
            raise ValueError(f"max_workers must be at least 1; got {self.max_workers}")
        self.check = check
        self.poll_seconds = poll_seconds
        self._slots: list[_Slot] = []

    @property
    def processes(self) -> list[BaseProcess]:
        """The pool's processes (none before the first task, nor after it was stopped)."""
        return [slot.process for slot in self._slots]

    def _start(self) -> None:
        if self._slots:
            return
        # The worker runs threads (heartbeat, parent watch) and holds database connections,
        # so no plain fork: a fork server with the library preloaded, else spawn.
        methods = multiprocessing.get_all_start_methods()
        method = "forkserver" if "forkserver" in methods else "spawn"
        context: Any = multiprocessing.get_context(method)  # a SpawnContext-like context
        if method == "forkserver":
            context.set_forkserver_preload(["registration"])
        try:
            for k in range(self.max_workers):
                ours, theirs = context.Pipe(duplex=True)
                process = context.Process(
                    target=_serve, args=(theirs,), name=f"regtree-task-{k}", daemon=True
                )
                process.start()
                theirs.close()
                self._slots.append(_Slot(process, ours))
        except BaseException:
            self.terminate()
            raise

    def map_unordered(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R]]:
        """``(position, fn(item))`` in completion order; see the library's ``Executor``."""
        self.check()
        if not items:
            return
        self._start()
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
                    timeout=self.poll_seconds,
                )
                for slot in busy:
                    if slot.connection in ready or slot.process.sentinel in ready:
                        position, result = self._collect(slot)
                        running -= 1
                        yield position, result
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
        """Kill the pool's processes now; tasks in progress are lost."""
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
        """Stop the pool when the job is done: idle processes exit, busy ones are killed."""
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
        return f"InterruptibleProcessExecutor(max_workers={self.max_workers})"

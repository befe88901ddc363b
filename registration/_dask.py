"""An :class:`~registration.Executor` on a Dask distributed cluster (optional: ``dask`` extra).

The tasks of a run are submitted at once (``Client.map``) and their results consumed as they
complete, like the local pool's. What a distributed run adds, and how it is handled:

* **Cancel.** The executor waits for results in slices of ``poll_seconds`` and calls its
  ``check`` between them; when ``check`` raises, or the consumer leaves, or a task fails,
  every task not yet finished is cancelled on the cluster (``Client.cancel(force=True)``):
  queued ones never start. A task already running on a worker thread cannot be interrupted
  by Dask; it runs to its end (one registration, seconds at most) and its result is dropped.
* **A worker lost.** The scheduler reassigns the tasks of a worker that dies to the others
  (Dask's ``distributed.scheduler.allowed-failures``, 3 by default: a task whose workers
  died more often than that is taken as the cause and fails with ``KilledWorker``). Such a
  failure, and a cluster left without any worker for ``no_worker_seconds``, end the run
  with :class:`DaskClusterError`, which says what happened; a run never hangs waiting.
* **The scheduler lost.** The client's connection errors end the run with
  :class:`DaskClusterError` too.

The functions and items must pickle (the library's are top-level functions and dataclasses)
and every Dask worker must be able to import ``registration`` (the same version).
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from ._pool import ClosedOnExit

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["DaskClusterError", "DaskExecutor"]

_INSTALL = "the Dask executor needs dask[distributed]: pip install 'regtree[dask]'"


class DaskClusterError(RuntimeError):
    """The Dask cluster could not run a task: its workers died, none is left, or the
    scheduler is unreachable."""


def _distributed() -> Any:
    try:
        import distributed
    except ImportError as e:  # pragma: no cover - exercised only without the extra
        raise ImportError(_INSTALL) from e
    return distributed


class DaskExecutor(ClosedOnExit):
    """Runs the tasks of a collection on a Dask distributed cluster.

    Parameters
    ----------
    scheduler : str or distributed.Client
        The scheduler's address (``"tcp://host:8786"``), or a client the caller owns (it
        is then neither closed nor shut down here).
    check : callable, optional
        Called between waits for results, at most ``poll_seconds`` apart; whatever it
        raises stops the run: the run's tasks are cancelled on the cluster and the
        exception propagates out of the library.
    poll_seconds : float
        Longest wait for a result between two calls of ``check``.
    retries : int
        Extra attempts Dask gives a task that raised (a task on a worker that died is
        reassigned regardless, up to the scheduler's ``allowed-failures``). Default 0:
        the library's tasks are deterministic, an exception repeats.
    no_worker_seconds : float
        A run fails with :class:`DaskClusterError` when the cluster has had no worker for
        this long while tasks wait.
    connect_seconds : float
        Time allowed to connect to the scheduler.
    """

    def __init__(
        self,
        scheduler: Any,
        *,
        check: Callable[[], None] | None = None,
        poll_seconds: float = 0.1,
        retries: int = 0,
        no_worker_seconds: float = 60.0,
        connect_seconds: float = 30.0,
    ) -> None:
        if not poll_seconds > 0:
            raise ValueError(f"poll_seconds must be > 0; got {poll_seconds!r}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0; got {retries!r}")
        if not no_worker_seconds > 0:
            raise ValueError(f"no_worker_seconds must be > 0; got {no_worker_seconds!r}")
        distributed = _distributed()
        self.check = check
        self.poll_seconds = poll_seconds
        self.retries = retries
        self.no_worker_seconds = no_worker_seconds
        self._owns_client = not isinstance(scheduler, distributed.Client)
        if self._owns_client:
            if not isinstance(scheduler, str) or not scheduler:
                raise ValueError(
                    f"scheduler must be a Dask scheduler address or a Client; got {scheduler!r}"
                )
            try:
                self.client = distributed.Client(
                    scheduler, timeout=connect_seconds, set_as_default=False
                )
            except OSError as e:
                raise DaskClusterError(
                    f"cannot reach the Dask scheduler at {scheduler}: {e}") from e
        else:
            self.client = scheduler
        self._futures: list[Any] = []

    def map_unordered(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R]]:
        """``(position, fn(item))`` in completion order; see :class:`~registration.Executor`."""
        if self.check is not None:
            self.check()
        if not items:
            return
        try:
            futures = self.client.map(fn, list(items), pure=False, retries=self.retries)
        except OSError as e:
            raise DaskClusterError(f"cannot submit tasks to the Dask scheduler: {e}") from e
        self._futures = futures
        position = {f.key: k for k, f in enumerate(futures)}
        ready: queue.SimpleQueue[Any] = queue.SimpleQueue()
        for f in futures:
            f.add_done_callback(ready.put)  # called in a thread of the client's
        remaining = len(futures)
        finished = False
        idle_since: float | None = None
        last_look = time.monotonic()
        try:
            while remaining:
                try:
                    f = ready.get(timeout=self.poll_seconds)
                except queue.Empty:
                    f = None
                if f is not None:
                    remaining -= 1
                    yield position[f.key], self._outcome(f, position[f.key])
                if self.check is not None:
                    self.check()
                now = time.monotonic()
                if f is None and now - last_look >= 1.0:
                    last_look = now
                    idle_since = self._watch_workers(idle_since, now)
            finished = True
        finally:
            self._futures = []
            if not finished:
                self._cancel(futures)

    def _outcome(self, future: Any, position: int) -> Any:
        """A finished task's result, or its exception raised (a cluster failure as
        :class:`DaskClusterError`)."""
        distributed = _distributed()
        if future.status == "error":
            exc = future.exception()
            if isinstance(exc, distributed.KilledWorker):
                raise DaskClusterError(
                    f"task {position} was running on Dask workers that died (every "
                    f"attempt the scheduler allows; distributed.scheduler.allowed-failures): "
                    f"{exc}"
                ) from exc
            raise exc
        if future.status == "cancelled":
            raise DaskClusterError(
                f"task {position} was cancelled on the Dask cluster (scheduler restarted or "
                "lost?)")
        try:
            return future.result()
        except (OSError, distributed.CancelledError) as e:
            raise DaskClusterError(f"lost the result of task {position}: {e}") from e

    def _watch_workers(self, idle_since: float | None, now: float) -> float | None:
        """Fail when the cluster has had no worker for ``no_worker_seconds``; returns since
        when it has had none (None: it has some)."""
        try:
            workers = self.client.scheduler_info(n_workers=-1).get("workers", {})
        except TypeError:  # older distributed: no n_workers argument
            workers = self.client.scheduler_info().get("workers", {})
        except OSError as e:
            raise DaskClusterError(f"lost the Dask scheduler: {e}") from e
        if workers:
            return None
        since = now if idle_since is None else idle_since
        if now - since >= self.no_worker_seconds:
            raise DaskClusterError(
                f"the Dask cluster has had no worker for {self.no_worker_seconds:.0f} s; "
                "start workers (dask worker <scheduler address>) and run the job again")
        return since

    def _cancel(self, futures: list[Any]) -> None:
        if not futures:
            return
        try:
            self.client.cancel(futures, force=True)
        except Exception:  # the cluster may be gone already: nothing left to cancel
            pass

    def terminate(self) -> None:
        """Stop now: cancel the tasks still queued or running (a running task finishes on
        its worker, its result dropped) and release the connection."""
        futures, self._futures = self._futures, []
        self._cancel(futures)
        self.close()

    def close(self) -> None:
        """Close the connection to the scheduler if this executor opened it; the cluster
        itself keeps running."""
        if self._owns_client:
            try:
                self.client.close()
            except Exception:  # already closed, or the scheduler is gone
                pass

    def __repr__(self) -> str:
        return f"DaskExecutor({self.client.scheduler.address!r})"

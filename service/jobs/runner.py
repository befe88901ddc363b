"""Run one claimed registration job: load its shapes, call the library, store the result.

:class:`JobControl` stops a run that was cancelled, whose lease was lost, or whose worker is
shutting down, by raising from :meth:`JobControl.check`. A background thread heartbeats the
lease every ``worker_heartbeat_seconds`` (carrying the latest progress, so progress writes
stay at a bounded rate) and in between looks for a cancel request every
``cancel_poll_seconds``. ``check`` runs in the library's progress callback (after each
completed task) and, with the process executor, every 0.1 s while the pool works (the
library's ``LocalProcessExecutor(check=...)``), whose processes are then killed; with the
serial executor, at every CPD iteration (``SerialExecutor(check=...)``); with the Dask
executor, every 0.1 s while the cluster works (``DaskExecutor(check=...)``), whose queued
tasks are then cancelled (a task running on a Dask worker ends on its own, its result
dropped). Either way a cancel stops the job within about ``cancel_poll_seconds``,
registrations in progress included, and frees the worker for its next job.

A cancel accepted while the job runs always ends it ``cancelled``: whatever the run raises
once a cancel was seen is taken as the cancel, and :meth:`JobQueue.complete` turns a late
success into ``cancelled`` too (outcome ``aborted``).

A failure is transient (:func:`service.jobs.queue.is_transient`: the database was busy or
locked) or not: a transient one gives the job back for another attempt after a backoff, any
other (a ``ValueError`` from the library: bad input) fails it at once with its message.
"""

from __future__ import annotations

import logging
import re
import threading
import time
import traceback
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import select

from service.contract.names import GROUPING_METHOD, METHOD_FUNCTIONS, METHODS
from service.core.config import Settings
from service.jobs.document import json_safe, similarity_npy, to_api_document
from service.jobs.grouping import run_grouping
from service.jobs.queue import Claim, JobQueue, Outcome, is_transient
from service.models import Job, Shape
from service.progress import FractionTracker

if TYPE_CHECKING:
    from registration import CollectionResult, Executor

logger = logging.getLogger("regtree.runner")


class JobInterrupted(BaseException):
    """Raised from the progress callback to stop a run.

    A ``BaseException`` so that no ``except Exception`` on the way up swallows it.
    """


class Cancelled(JobInterrupted):
    pass


class LeaseLost(JobInterrupted):
    pass


class WorkerShutdown(JobInterrupted):
    pass


class JobControl:
    """Progress callback, heartbeat thread, and the flags that interrupt a run."""

    def __init__(
        self,
        queue: JobQueue,
        claim: Claim,
        settings: Settings,
        shutdown: threading.Event | None = None,
        tracker: FractionTracker | None = None,
    ) -> None:
        self.queue = queue
        self.tracker = tracker  # the overall share done, written with the progress
        self._fraction: float | None = None
        self.claim = claim
        self.settings = settings
        self.shutdown = shutdown or threading.Event()
        self.cancel = threading.Event()
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._latest: tuple[str, int, int] | None = None
        self._last_write = 0.0
        self._thread = threading.Thread(
            target=self._heartbeat_loop, name=f"heartbeat-{claim.job_id}", daemon=True
        )

    # -- lifecycle ------------------------------------------------------------------------

    def __enter__(self) -> JobControl:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=self.settings.worker_heartbeat_seconds + 5)

    def done(self) -> None:
        """The run is over and its outcome is about to be written: stop watching the lease.
        Once the job is marked succeeded (or failed, or released) the lease is no longer
        held, and a poll that saw that before the pool had closed logged a false "lease
        lost"."""
        self._stop.set()

    def _apply(self, state: Outcome) -> None:
        if state is Outcome.lost:
            self.lost.set()
        elif state is Outcome.cancel_requested:
            self.cancel.set()

    def _heartbeat_loop(self) -> None:
        """Heartbeat every ``worker_heartbeat_seconds``; in between, look for a cancel
        request every ``cancel_poll_seconds`` (a read)."""
        beat = self.settings.worker_heartbeat_seconds
        poll = min(self.settings.cancel_poll_seconds, beat)
        next_beat = time.monotonic() + beat
        while not self._stop.wait(max(0.0, min(poll, next_beat - time.monotonic()))):
            try:
                if time.monotonic() >= next_beat - 1e-3:
                    next_beat = time.monotonic() + beat
                    with self._lock:
                        latest, fraction = self._latest, self._fraction
                    state = self.queue.heartbeat(self.claim, progress=latest,
                                                 fraction=fraction)
                elif self.cancel.is_set():
                    continue  # already seen: the run is stopping
                else:
                    state = self.queue.peek(self.claim)
            except Exception:
                logger.exception("heartbeat failed", extra={"job_id": self.claim.job_id})
                continue
            if self._stop.is_set():  # the outcome is being written: the lease ends here
                return
            self._apply(state)
            if self.lost.is_set():
                logger.warning("lease lost", extra={"job_id": self.claim.job_id})
                return

    @property
    def latest(self) -> tuple[str, int, int] | None:
        """The last progress reported by the library."""
        with self._lock:
            return self._latest

    # -- the library's progress callback --------------------------------------------------

    def reason(self) -> JobInterrupted | None:
        """Why the run must stop (lease lost, cancelled, shutting down), or None."""
        if self.lost.is_set():
            return LeaseLost(f"job {self.claim.job_id}: lease lost")
        if self.cancel.is_set():
            return Cancelled(f"job {self.claim.job_id}: cancelled")
        if self.shutdown.is_set():
            return WorkerShutdown(f"job {self.claim.job_id}: worker shutting down")
        return None

    def check(self) -> None:
        """Raise the reason to stop, if there is one; called from the running thread."""
        reason = self.reason()
        if reason is not None:
            raise reason

    def progress(self, stage: str, done: int, total: int) -> None:
        self.check()
        now = time.monotonic()
        with self._lock:
            self._latest = (str(stage), int(done), int(total))
            if self.tracker is not None:
                self._fraction = self.tracker.update(str(stage), int(done), int(total))
            fraction = self._fraction
            due = now - self._last_write >= self.settings.progress_min_interval_seconds
            if due:
                self._last_write = now
        if due:
            state = self.queue.heartbeat(self.claim, progress=(str(stage), int(done), int(total)),
                                         fraction=fraction)
            self._apply(state)
            self.check()


def _executor(settings: Settings, control: JobControl) -> Executor:
    """The job's executor; its ``check`` is the job's, so a cancel stops the registrations
    in progress: at every CPD iteration (serial) or within 0.1 s (the pool is killed)."""
    from registration import DaskExecutor, LocalProcessExecutor, SerialExecutor

    if settings.executor == "serial":
        return SerialExecutor(check=control.check)
    if settings.executor == "dask":
        # A cancel cancels the job's tasks on the cluster; a lost Dask worker's tasks are
        # reassigned by the scheduler; a cluster that cannot run them fails the job.
        return DaskExecutor(
            settings.dask_scheduler, check=control.check, poll_seconds=0.1,
            connect_seconds=settings.dask_connect_seconds,
            no_worker_seconds=settings.dask_no_worker_seconds,
        )
    # The pool starts its processes inside JobControl, whose heartbeat thread runs: beside
    # threads it uses a fork server with the library preloaded, never a plain fork.
    return LocalProcessExecutor(
        settings.executor_processes, check=control.check, poll_seconds=0.1
    )


#: The key under which :func:`run_registration` hands the similarity D (an ndarray, not
#: JSON) to :func:`run_claimed`, which stores it apart from the document.
SIMILARITY_KEY = "_similarity"


def run_registration(*args: Any, **kwargs: Any) -> dict[str, Any]:
    """:func:`run_library`'s result as its document (``to_dict()``), with the similarity D
    under :data:`SIMILARITY_KEY`."""
    result = run_library(*args, **kwargs)
    # each subject's transform refers to its parent's steps instead of repeating them; the
    # result routes expand them (service.api.routes.results.expanded)
    doc: dict[str, Any] = result.to_dict(shared_steps=True)
    doc[SIMILARITY_KEY] = result.similarity
    return doc


def run_library(
    job_method: str,
    shapes: list[np.ndarray],
    names: list[str],
    root: int,
    params: dict[str, Any],
    *,
    executor: Any,
    progress: Any,
) -> CollectionResult:
    """Call the library for one job and return its result."""
    import registration

    if job_method not in METHOD_FUNCTIONS or job_method == GROUPING_METHOD:
        raise ValueError(f"unknown method {job_method!r}; expected one of {', '.join(METHODS)}")
    build = getattr(registration, METHOD_FUNCTIONS[job_method])
    result = build(
        shapes,
        root=root,
        similarity_threshold=params.get("similarity_threshold"),
        error_threshold=params.get("error_threshold"),
        cpd=registration.CPDOptions(**params.get("cpd", {})),
        names=names,
        executor=executor,
        progress=progress,
        compare_direct=bool(params.get("compare_direct", False)),
        # Jobs queued before pose existed have only max_rotation: the library reads a
        # number as "upright" and None as its default.
        pose=params.get("pose"),
        max_rotation=params.get("max_rotation"),
        # Jobs queued before working_points existed asked for the stored resolution.
        working_points=params.get("working_points"),
    )
    collection_result: CollectionResult = result
    return collection_result


_POSITION = re.compile(r"\bshapes\[(\d+)\]")


def name_shapes(message: str, shape_ids: list[int], names: list[str]) -> str:
    """``message`` with the library's ``shapes[k]`` (a position in the job's input) written
    as ``shape ID 'NAME'``, which the user can find in the collection."""

    def named(match: re.Match[str]) -> str:
        k = int(match[1])
        return f"shape {shape_ids[k]} {names[k]!r}" if k < len(shape_ids) else match[0]

    return _POSITION.sub(named, message)


def _stop(executor: Executor | None) -> None:
    """Stop an executor's tasks now, without waiting for them (a pool is killed)."""
    if executor is None:
        return
    try:
        executor.terminate()
    except Exception:
        logger.exception("could not stop the executor")


def _interrupted(queue: JobQueue, claim: Claim, interruption: JobInterrupted) -> Outcome:
    """Settle a job whose run was interrupted."""
    if isinstance(interruption, Cancelled):
        return queue.abort(claim)
    if isinstance(interruption, WorkerShutdown):
        return queue.release(claim)
    return Outcome.lost


def _cluster_failure(exc: Exception) -> bool:
    """A Dask cluster that could not run the job's tasks (workers died, none left, the
    scheduler unreachable): worth another attempt after a backoff, like a busy database."""
    from registration import DaskClusterError

    return isinstance(exc, DaskClusterError)


def _failed(
    queue: JobQueue,
    claim: Claim,
    exc: Exception,
    log: dict[str, Any],
    shape_ids: list[int] | None = None,
    names: list[str] | None = None,
) -> Outcome:
    """Settle a job whose run raised: another attempt if transient, else failed at once.
    With the job's ``shape_ids`` and ``names``, the message names a shape by id and name
    where the library gave its position."""
    transient = is_transient(exc) or _cluster_failure(exc)
    logger.error("job failed", exc_info=exc, extra={**log, "transient": transient})
    message = f"{type(exc).__name__}: {exc}"
    if shape_ids is not None and names is not None:
        message = name_shapes(message, shape_ids, names)
    if not str(exc):
        message += "\n" + "".join(traceback.format_exception(exc)[-3:])
    return queue.fail(claim, message, transient=transient)


def run_claimed(
    queue: JobQueue, settings: Settings, claim: Claim, shutdown: threading.Event | None = None
) -> Outcome:
    """Run a claimed job to its end; returns its outcome."""
    log = {"job_id": claim.job_id, "attempt": claim.attempt, "owner": claim.owner}
    try:
        with queue.db.read() as session:
            job = session.get(Job, claim.job_id)
            if job is None:
                return Outcome.lost
            method, params, model_id = job.method, dict(job.params), job.model_shape_id
            wanted = list(job.shape_ids)
            rows = {
                s.id: s for s in session.scalars(select(Shape).where(Shape.id.in_(wanted))).all()
            }
            shape_ids = [sid for sid in wanted if sid in rows]
            shapes = [rows[sid].points for sid in shape_ids]
            names = [rows[sid].name for sid in shape_ids]
    except Exception as exc:
        return _failed(queue, claim, exc, log)

    grouping = method == GROUPING_METHOD
    root = shape_ids.index(model_id) if model_id in shape_ids else None
    if root is None and not grouping:  # a grouping has no model
        return queue.fail(claim, f"model shape {model_id} was deleted before the job ran")
    if len(shape_ids) < 2:
        return queue.fail(claim, "fewer than 2 shapes are left in the collection")

    started = time.monotonic()
    executor: Executor | None = None
    completed = False
    tracker = FractionTracker(method, params, len(shape_ids))
    with JobControl(queue, claim, settings, shutdown, tracker) as control:
        try:
            control.check()
            executor = _executor(settings, control)
            if grouping:
                document = run_grouping(claim.job_id, shapes, names, shape_ids, params,
                                        executor=executor, progress=control.progress)
                completed = True
                control.check()
                control.done()
                outcome = queue.complete(claim, json_safe(document), [],
                                         progress=control.latest)
                return _finished(outcome, log, started)
            assert root is not None
            doc = run_registration(
                method,
                shapes,
                names,
                root,
                params,
                executor=executor,
                progress=control.progress,
            )
            completed = True
            control.check()
            similarity = doc.pop(SIMILARITY_KEY, None)
            document, subjects = to_api_document(claim.job_id, json_safe(doc), shape_ids)
            control.done()
            outcome = queue.complete(
                claim,
                document,
                subjects,
                progress=control.latest,
                similarity=similarity_npy(similarity, len(shape_ids)),
            )
        except JobInterrupted as interruption:
            control.done()
            outcome = _interrupted(queue, claim, interruption)
        except Exception as exc:
            control.done()
            reason = control.reason()
            # Stopping may surface as any error (a task whose process was killed, say): the
            # reason is the interruption, never a failure of the job.
            if reason is not None:
                outcome = _interrupted(queue, claim, reason)
            else:
                outcome = _failed(queue, claim, exc, log, shape_ids, names)
        finally:
            if completed and executor is not None:  # the pool is idle: close it the ordinary way
                executor.close()
            else:  # interrupted or failed: its tasks are not wanted, kill them
                _stop(executor)
    return _finished(outcome, log, started)


def _finished(outcome: Outcome, log: dict[str, Any], started: float) -> Outcome:
    logger.info(
        "job finished",
        extra={**log, "outcome": outcome, "seconds": round(time.monotonic() - started, 3)},
    )
    return outcome

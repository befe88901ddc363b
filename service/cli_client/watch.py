"""``regtree upload``, ``run``, ``watch`` and ``cancel``."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from service.contract.names import ProblemType

if TYPE_CHECKING:
    from service.client import RegtreeClient

from service.cli_client._common import (
    CLIError,
    Exit,
    _fail,
    _out,
    describe_error,
    find_collection,
    find_shape,
)
from service.cli_client.parser import RUN_JOB_OPTIONS
from service.progress import Progress, outcome_line

# --- upload ------------------------------------------------------------------------------


def _shape_files(folder: Path, pattern: str, recursive: bool) -> list[Path]:
    from service.client import find_shape_files

    try:
        return find_shape_files(folder, pattern=pattern, recursive=recursive)
    except FileNotFoundError as exc:
        raise CLIError(str(exc), Exit.USAGE) from None


def cmd_upload(args: argparse.Namespace, rt: RegtreeClient) -> int:
    from service.client import RegtreeError

    files = _shape_files(args.folder, args.pattern, args.recursive)
    if args.create:
        existing = [c for c in rt.list_collections() if c.name == args.collection]
        if existing:
            raise CLIError(
                f"a collection named {args.collection!r} exists already (id "
                f"{existing[0].id}, {existing[0].n_shapes} shapes); leave out --create to add "
                "shapes to it",
                Exit.FAILED,
            )
        collection = rt.create_collection(args.collection, args.description)
        _out(f"created collection {collection.name!r} (id {collection.id})")
    else:
        collection = find_collection(rt, args.collection)
    _out(
        f"uploading {len(files)} file(s) from {args.folder} to collection "
        f"{collection.name!r} (id {collection.id})"
    )
    started = time.monotonic()
    batches = 0
    uploaded = 0

    def on_batch(done: int, total: int) -> None:
        nonlocal batches, uploaded
        batches += 1
        uploaded = done
        _out(f"batch {batches}: {done}/{total} files uploaded ({time.monotonic() - started:.1f} s)")

    try:
        shapes = rt.upload_files(
            collection.id,
            files,
            mode=args.mode,
            target_points=args.target_points,
            on_conflict=args.on_conflict,
            batch_size=args.batch_size,
            on_batch=on_batch,
        )
    except RegtreeError as e:
        code = Exit.FAILED if e.status is not None else Exit.CONNECTION
        # the client's note on what earlier batches stored is said below, for the CLI
        message = describe_error(e, notes=False) if e.status is not None else f"{e}"
        if e.type == ProblemType.NAME_CONFLICT:
            message += "; to upload anyway: --on-conflict replace or --on-conflict keep"
        if e.status is not None:  # the service answered: it stored none of that batch
            message += "; nothing of the refused batch was stored"
        raise CLIError(
            f"{message}; collection {collection.name!r} (id {collection.id}) keeps the "
            f"{len(e.stored)} shape(s) of the earlier batches",
            code,
        ) from e
    except KeyboardInterrupt:
        raise CLIError(
            f"interrupted; {uploaded} file(s) of {len(files)} were uploaded to collection "
            f"{collection.name!r} (id {collection.id}) before",
            Exit.INTERRUPTED,
        ) from None
    total = rt.get_collection(collection.id).n_shapes
    _out(
        f"uploaded {len(shapes)} shape(s) to collection {collection.name!r} (id "
        f"{collection.id}), which now holds {total}"
    )
    if shapes:
        _out(f"next, e.g.: regtree run --collection {collection.id} --model {shapes[0].id} --wait")
    return Exit.OK


# --- run and watch -------------------------------------------------------------------------


def _pose_text(params: Mapping[str, Any]) -> str:
    """What a job's params say about its pose, e.g. ", pose upright +-30 deg (request)"."""
    pose = params.get("pose")
    if not pose:
        return ""
    text = f", pose {pose}"
    if isinstance(params.get("max_rotation"), int | float):
        text += f" +-{params['max_rotation']:g} deg"
    if params.get("pose_source"):
        text += f" ({params['pose_source']})"
    return text


def cmd_run(args: argparse.Namespace, rt: RegtreeClient) -> int:
    collection = find_collection(rt, args.collection)
    model = find_shape(rt, collection, args.model)
    options = {name: getattr(args, name) for name in RUN_JOB_OPTIONS}
    job = rt.start_job(collection.id, model.id, **options)
    if args.quiet:
        _out(str(job.id))
    else:
        _out(
            f"job {job.id} {job.status}: {job.method} on collection {collection.name!r} "
            f"(id {collection.id}, {job.n_shapes or collection.n_shapes} shapes), model "
            f"{model.name!r} (id {model.id}){_pose_text(job.params)}"
        )
        if not args.wait:
            _out(f"follow it: regtree watch {job.id}")
    if not args.wait:
        return Exit.OK
    return watch_job(rt, job.id, poll=args.poll, cancel_on_interrupt=args.cancel_on_interrupt)


def cmd_watch(args: argparse.Namespace, rt: RegtreeClient) -> int:
    return watch_job(rt, args.job, poll=args.poll, cancel_on_interrupt=args.cancel_on_interrupt)


def watch_job(
    rt: RegtreeClient,
    job_id: int,
    *,
    poll: float = 0.5,
    cancel_on_interrupt: bool = False,
    out: TextIO | None = None,
    sleep: Callable[[float], None] = time.sleep,
) -> int:
    """Follow a job until it ends; 0 succeeded, 1 failed / cancelled, 130 on Ctrl-C."""
    from service.client import RegtreeError

    stream = out or sys.stdout
    progress = Progress(job_id, stream)
    try:
        while True:
            state = rt.get_job(job_id)
            progress.update(state)
            if state.finished:
                break
            sleep(poll)
    except KeyboardInterrupt:
        progress.end_line()
        return _interrupted(rt, job_id, cancel_on_interrupt)
    except BaseException:
        progress.end_line()
        raise
    progress.end_line()
    if state.status != "succeeded":
        _out(outcome_line(state), stream)
        reason = f": {state.error}" if state.error else ""
        return _fail(f"job {job_id} {state.status}{reason}", Exit.FAILED)
    try:
        summary = rt.result(job_id).summary
    except RegtreeError:  # the job succeeded: say so even if its summary cannot be read
        summary = {}
    _out(outcome_line(state, summary), stream)
    _out(f"pictures and numbers: regtree results {job_id} --out DIR", stream)
    return Exit.OK


def _interrupted(rt: RegtreeClient, job_id: int, cancel: bool) -> int:
    from service.client import Conflict

    if not cancel:
        return _fail(
            f"interrupted; job {job_id} keeps running on the server (follow it again with "
            f"`regtree watch {job_id}`, stop it with `regtree cancel {job_id}`)",
            Exit.INTERRUPTED,
        )
    try:
        state = rt.cancel(job_id)
    except Conflict as e:
        return _fail(f"interrupted; not cancelled: {e.detail}", Exit.INTERRUPTED)
    return _fail(
        f"interrupted; cancel requested for job {job_id} (now {state.status})", Exit.INTERRUPTED
    )


def cmd_cancel(args: argparse.Namespace, rt: RegtreeClient) -> int:
    state = rt.cancel(args.job)
    if state.status == "cancelled":
        _out(f"job {args.job} cancelled")
    else:
        _out(f"job {args.job} {state.status}: cancel requested, it stops at its next report")
    return Exit.OK

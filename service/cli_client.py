"""The client-side ``regtree`` commands: drive a running service from a shell.

::

    regtree upload glyphs/ --collection yong --create --pattern '*.png' --target-points 300
    regtree run --collection yong --model 00-root --wait
    regtree watch 12
    regtree results 12 --out results/yong
    regtree results 12 --sort=-confidence --min-confidence 0.5
    regtree cancel 12

They talk HTTP through :class:`service.client.RegtreeClient`: ``--url`` (default
``$REGTREE_URL``, else ``http://127.0.0.1:8000``), ``--api-key`` (default
``$REGTREE_API_KEY``) and ``--timeout`` (seconds per request) go before or after the
command name.

Exit codes: 0 success; 1 the service refused the request or the job failed / was cancelled
(the server's explanation on stderr); 2 usage errors (bad arguments, a missing folder, an
ambiguous name); 3 the service could not be reached (the URL is named); 130 interrupted by
Ctrl-C (a job keeps running on the server unless ``--cancel-on-interrupt``). Expected errors
are one ``regtree: error: ...`` line on stderr, never a traceback.

This module imports only :mod:`argparse` at import time: ``regtree serve`` builds the same
parser and must be able to limit BLAS threads before numpy is imported.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from service.client import Collection, JobStatus, RegtreeClient, RegtreeError, Shape

COMMANDS = ("upload", "run", "watch", "results", "cancel")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_CONNECTION = 3
EXIT_INTERRUPTED = 130

DEFAULT_URL = "http://127.0.0.1:8000"
METHODS = ("dynamic_tree", "static_tree", "direct")
IMAGE_MODES = ("contour", "edges", "skeleton")
POSES = ("as_given", "upright", "rotation", "affine")
#: Orders of a result's subjects: the service's ``sort`` (``service.client.SUBJECT_SORTS``).
SUBJECT_SORTS = ("position", "confidence", "-confidence", "error", "-error")


class CLIError(Exception):
    """An expected failure: printed as one ``regtree: error:`` line, exit ``code``."""

    def __init__(self, message: str, code: int = EXIT_FAILED) -> None:
        super().__init__(message)
        self.code = code


# --- argument parsing (argparse only) ----------------------------------------------------


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _job_id(text: str) -> int:
    try:
        value = int(text.strip().removeprefix("#"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a job id is a number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"a job id is a positive number, got {text!r}")
    return value


def _confidence(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number from 0 to 1, got {text!r}") from None
    if not 0.0 <= value <= 1.0:  # NaN too
        raise argparse.ArgumentTypeError(f"expected a number from 0 to 1, got {text!r}")
    return value


def _subject_sort(text: str) -> str:
    if text not in SUBJECT_SORTS:
        raise argparse.ArgumentTypeError(
            f"expected one of {', '.join(SUBJECT_SORTS)}, got {text!r}"
        )
    return text


def join_option_values(argv: Sequence[str]) -> list[str]:
    """``--sort -confidence`` as ``--sort=-confidence``: argparse takes a value starting
    with "-" for an option of its own, so a descending order is joined to its option."""
    out: list[str] = []
    args = list(argv)
    k = 0
    while k < len(args):
        if args[k] == "--sort" and k + 1 < len(args) and args[k + 1] in SUBJECT_SORTS:
            out.append(f"--sort={args[k + 1]}")
            k += 2
            continue
        out.append(args[k])
        k += 1
    return out


def _subjects_choice(text: str) -> str | int:
    if text in ("all", "attached"):
        return text
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected all, attached or a number of subjects, got {text!r}"
        ) from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"the number of subjects must be >= 0, got {text!r}")
    return value


def add_connection_options(parser: argparse.ArgumentParser, *, suppress: bool) -> None:
    """``--url``, ``--api-key``, ``--timeout``.

    On the top-level parser (``suppress=False``) they get their defaults; on each client
    command (``suppress=True``) they default to "not given" so that a value given before the
    command name is not overwritten by the subparser's default.
    """
    group = parser.add_argument_group(
        "service connection" + ("" if suppress else " (upload, run, watch, results, cancel)")
    )

    def default(value: Any) -> Any:
        return argparse.SUPPRESS if suppress else value

    group.add_argument(
        "--url",
        default=default(None),
        help=f"the service's base URL (default $REGTREE_URL, else {DEFAULT_URL})",
    )
    group.add_argument(
        "--api-key",
        default=default(None),
        help="sent as X-API-Key (default $REGTREE_API_KEY)",
    )
    group.add_argument(
        "--timeout",
        type=_positive_float,
        default=default(60.0),
        metavar="SECONDS",
        help="seconds per HTTP request (default 60; raise it for big upload batches)",
    )


def add_commands(sub: Any) -> None:
    """Register the client commands on ``regtree``'s subparsers action."""

    def command(name: str, **kwargs: Any) -> argparse.ArgumentParser:
        parser: argparse.ArgumentParser = sub.add_parser(name, **kwargs)
        add_connection_options(parser, suppress=True)
        return parser

    upload = command(
        "upload",
        help="upload a folder of shapes (point files, images) to a collection",
        description="Upload every point file (.txt .csv .json .npy) and image (.png .jpg "
        ".jpeg) in DIR whose name matches --pattern, sorted by name, in batches. The shape "
        "name is the file name without its extension.",
    )
    upload.add_argument("folder", metavar="DIR", type=Path)
    upload.add_argument(
        "--collection",
        required=True,
        metavar="NAME",
        help="the collection's name (or id); it must exist unless --create",
    )
    upload.add_argument(
        "--create",
        action="store_true",
        help="create the collection (refused if one with this name exists)",
    )
    upload.add_argument("--description", default="", help="with --create: its description")
    upload.add_argument("--pattern", default="*", metavar="GLOB", help="file names (default *)")
    upload.add_argument("--recursive", action="store_true", help="also look in subfolders")
    upload.add_argument(
        "--mode",
        choices=IMAGE_MODES,
        default="contour",
        help="how images become points (default contour)",
    )
    upload.add_argument(
        "--target-points",
        type=_positive_int,
        metavar="N",
        help="at most N points per image (default: the service's)",
    )
    upload.add_argument(
        "--batch-size", type=_positive_int, default=100, metavar="N", help="files per request"
    )

    run = command(
        "run",
        help="start a registration job",
        description="Queue a job registering the model shape onto every shape of the "
        "collection, and print its id (with --wait, follow it like `regtree watch`).",
    )
    run.add_argument("--collection", required=True, metavar="NAME|ID")
    run.add_argument(
        "--model", required=True, metavar="SHAPE_NAME|ID", help="the model (root) shape"
    )
    run.add_argument("--method", choices=METHODS, default="dynamic_tree")
    run.add_argument(
        "--similarity-threshold",
        type=_positive_float,
        metavar="X",
        help="largest similarity distance D for a tree edge (default: automatic)",
    )
    run.add_argument(
        "--error-threshold",
        type=_positive_float,
        metavar="X",
        help="largest registration error e to accept (default: automatic)",
    )
    run.add_argument(
        "--pose",
        choices=POSES,
        help="which poses the affine pre-alignment may give a shape: as_given = only the "
        "shapes as uploaded; upright = rotations within +-DEG (--max-rotation, 30 by "
        "default) of them, no mirror images (glyph scans, aligned outlines); rotation = any "
        "rotation, no mirror images; affine = any affine map, mirror images included. "
        "Default: the service's, upright if every shape of the collection was uploaded as an "
        "image, else rotation",
    )
    run.add_argument(
        "--max-rotation",
        type=float,
        metavar="DEG",
        help="with --pose upright (or alone, which means upright): consider only rotations "
        "within +-DEG degrees of the uploaded shapes (default 30)",
    )
    run.add_argument(
        "--no-compare-direct",
        dest="compare_direct",
        action="store_false",
        help="do not also register every subject directly from the model",
    )
    run.add_argument(
        "--callback-url",
        metavar="URL",
        help="POST a signed JSON notice (job id, state, result URL) to URL when the job ends; "
        "the server must allow its host (setting callback_allowed_hosts)",
    )
    run.add_argument("--wait", action="store_true", help="follow the job until it ends")
    run.add_argument("-q", "--quiet", action="store_true", help="print only the job id")
    _watch_options(run)

    watch = command(
        "watch",
        help="follow a job's progress until it ends",
        description="Show the job's stage and done/total until it ends (a live bar on a "
        "terminal, one line per change otherwise). Exit 0 if it succeeded, 1 if it failed or "
        "was cancelled, 130 on Ctrl-C (the job keeps running unless --cancel-on-interrupt).",
    )
    watch.add_argument("job", metavar="JOB", type=_job_id)
    _watch_options(watch)

    results = command(
        "results",
        help="print a job's result; download it and draw its pictures",
        description="Print the summary table and one line per subject (layer, parent, e, "
        "direct e, confidence, status: tree, leaf for a low-confidence leaf, or unattached). "
        "With --out, also write OUT/result.json (the full result document), tree.svg, "
        "tree.png, summary.png and subjects/<name>.png (the model warped onto each subject, "
        "beside direct CPD's). --sort, --min-confidence, --only-leaves and --no-leaves choose "
        "and order the subject lines and the subject pictures (the service does it); "
        "result.json, the tree and the summary always cover every subject.",
    )
    results.add_argument("job", metavar="JOB", type=_job_id)
    results.add_argument(
        "--out", type=Path, metavar="DIR", help="write the result and its pictures here"
    )
    results.add_argument(
        "--subjects",
        type=_subjects_choice,
        default="all",
        metavar="all|attached|N",
        help="which subject pictures to draw: all (default), attached ones, or the first N "
        "of the subject lines (0: none)",
    )
    results.add_argument(
        "--sort",
        type=_subject_sort,
        default=None,
        metavar="KEY",
        help="order of the subjects: position (default, the job's shape order), confidence, "
        "error, or descending with a leading - (-confidence, -error); subjects without the "
        "value come last",
    )
    results.add_argument(
        "--min-confidence",
        type=_confidence,
        default=None,
        metavar="X",
        help="only subjects whose confidence is at least X (0 to 1); leaves out unattached ones",
    )
    leaves = results.add_mutually_exclusive_group()
    leaves.add_argument(
        "--only-leaves",
        dest="leaf",
        action="store_const",
        const=True,
        default=None,
        help="only the low-confidence leaves",
    )
    leaves.add_argument(
        "--no-leaves",
        dest="leaf",
        action="store_const",
        const=False,
        help="leave out the low-confidence leaves",
    )
    results.add_argument(
        "--format",
        choices=("png", "svg"),
        default="png",
        help="format of the subject pictures (default png)",
    )
    results.add_argument(
        "--y-up",
        action="store_true",
        help="draw subjects with y growing upwards (default: downwards, as in images)",
    )

    cancel = command("cancel", help="cancel a queued or running job")
    cancel.add_argument("job", metavar="JOB", type=_job_id)


def _watch_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--poll",
        type=_positive_float,
        default=0.5,
        metavar="SECONDS",
        help="seconds between status requests (default 0.5)",
    )
    parser.add_argument(
        "--cancel-on-interrupt",
        action="store_true",
        help="on Ctrl-C, cancel the job instead of leaving it running",
    )


# --- running -----------------------------------------------------------------------------


def main(args: argparse.Namespace) -> int:
    """Run a client command; return the exit code. Expected errors never raise."""
    from service.client import (
        JobFailed,
        RegtreeClient,
        RegtreeConnectionError,
        RegtreeError,
        RegtreeTimeout,
        Unauthorized,
    )

    url = (args.url or os.environ.get("REGTREE_URL") or DEFAULT_URL).strip()
    api_key = args.api_key if args.api_key is not None else os.environ.get("REGTREE_API_KEY")
    try:
        _check_url(url)
        with RegtreeClient(url, api_key=api_key or None, timeout=args.timeout) as rt:
            return int(HANDLERS[args.command](args, rt))
    except CLIError as e:
        return _fail(str(e), e.code)
    except KeyboardInterrupt:
        return _fail("interrupted", EXIT_INTERRUPTED)
    except BrokenPipeError:  # e.g. `regtree results ... | head`: stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_FAILED
    except RegtreeConnectionError as e:
        return _fail(
            f"{e} (is the service running there? set --url or REGTREE_URL)", EXIT_CONNECTION
        )
    except RegtreeTimeout as e:
        return _fail(f"{e} [service at {url}]", EXIT_CONNECTION)
    except JobFailed as e:
        return _fail(str(e), EXIT_FAILED)
    except RegtreeError as e:
        message = describe_error(e)
        if isinstance(e, Unauthorized):
            message += " (give the key with --api-key or REGTREE_API_KEY)"
        return _fail(message, EXIT_FAILED)
    except Exception as e:
        import httpx

        if isinstance(e, httpx.HTTPError):  # e.g. a scheme httpx does not speak
            return _fail(f"cannot talk to {url}: {e}", EXIT_CONNECTION)
        raise


def _check_url(url: str) -> None:
    if not re.match(r"^https?://[^/\s:]+", url):
        raise CLIError(
            f"--url must look like http://HOST:PORT (got {url!r}; default $REGTREE_URL)",
            EXIT_USAGE,
        )


def _fail(message: str, code: int) -> int:
    sys.stdout.flush()
    print(f"regtree: error: {message}", file=sys.stderr, flush=True)
    return code


def describe_error(e: RegtreeError) -> str:
    """``<title>: <detail> (HTTP <status>)``, field errors after the first, and notes."""
    if e.status is None:
        return str(e)
    text = str(e.title or "Error")
    if e.detail:
        text += f": {e.detail}"
    text += f" (HTTP {e.status})"
    for error in (e.errors or [])[1:]:
        where = ".".join(str(part) for part in error.get("loc") or [])
        text += f"; {where}: {error.get('msg')}" if where else f"; {error.get('msg')}"
    for note in getattr(e, "__notes__", []):
        text += f"; {note}"
    return text


def _out(text: str = "", file: TextIO | None = None) -> None:
    print(text, file=file or sys.stdout, flush=True)


# --- names or ids --------------------------------------------------------------------------


def _pick(kind: str, value: str, items: Sequence[Any], *, where: str = "") -> Any:
    """The one item whose name is ``value`` or, for a number, whose id it is.

    No match: CLIError exit 1 (listing a few names); several: exit 2 (give the id)."""
    matches = [item for item in items if item.name == value]
    if value.strip().isdigit():
        matches += [item for item in items if item.id == int(value) and item not in matches]
    if len(matches) == 1:
        return matches[0]
    if not matches:
        known = ", ".join(repr(item.name) for item in items[:8])
        more = f", ... ({len(items)} in all)" if len(items) > 8 else ""
        hint = f"; there are: {known}{more}" if items else f"; there are no {kind}s{where} yet"
        what = f"named {value!r}"
        if value.strip().isdigit():
            what += f" or with id {int(value)}"
        raise CLIError(f"no {kind} {what}{where}{hint}", EXIT_FAILED)
    ids = ", ".join(f"id {item.id} ({item.name!r})" for item in matches)
    raise CLIError(
        f"{value!r} is ambiguous: {len(matches)} {kind}s{where} match ({ids}); give the id",
        EXIT_USAGE,
    )


def find_collection(rt: RegtreeClient, value: str) -> Collection:
    collection: Collection = _pick("collection", value, rt.list_collections())
    return collection


def find_shape(rt: RegtreeClient, collection: Collection, value: str) -> Shape:
    where = f" in collection {collection.name!r} (id {collection.id})"
    shape: Shape = _pick("shape", value, rt.list_shapes(collection.id), where=where)
    return shape


# --- upload ------------------------------------------------------------------------------


def _shape_files(folder: Path, pattern: str, recursive: bool) -> list[Path]:
    from service.client import find_shape_files

    try:
        return find_shape_files(folder, pattern=pattern, recursive=recursive)
    except FileNotFoundError as exc:
        raise CLIError(str(exc), EXIT_USAGE) from None


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
                EXIT_FAILED,
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
            batch_size=args.batch_size,
            on_batch=on_batch,
        )
    except RegtreeError as e:
        code = EXIT_FAILED if e.status is not None else EXIT_CONNECTION
        message = describe_error(e) if e.status is not None else f"{e}"
        raise CLIError(
            f"{message}; collection {collection.name!r} (id {collection.id}) keeps the "
            f"{len(e.stored)} shape(s) of the earlier batches",
            code,
        ) from e
    except KeyboardInterrupt:
        raise CLIError(
            f"interrupted; {uploaded} file(s) of {len(files)} were uploaded to collection "
            f"{collection.name!r} (id {collection.id}) before",
            EXIT_INTERRUPTED,
        ) from None
    total = rt.get_collection(collection.id).n_shapes
    _out(
        f"uploaded {len(shapes)} shape(s) to collection {collection.name!r} (id "
        f"{collection.id}), which now holds {total}"
    )
    if shapes:
        _out(f"next, e.g.: regtree run --collection {collection.id} --model {shapes[0].id} --wait")
    return EXIT_OK


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
    job = rt.start_job(
        collection.id,
        model.id,
        method=args.method,
        similarity_threshold=args.similarity_threshold,
        error_threshold=args.error_threshold,
        pose=args.pose,
        max_rotation=args.max_rotation,
        compare_direct=args.compare_direct,
        callback_url=args.callback_url,
    )
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
        return EXIT_OK
    return watch_job(rt, job.id, poll=args.poll, cancel_on_interrupt=args.cancel_on_interrupt)


def cmd_watch(args: argparse.Namespace, rt: RegtreeClient) -> int:
    return watch_job(rt, args.job, poll=args.poll, cancel_on_interrupt=args.cancel_on_interrupt)


def _clock(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def progress_text(state: JobStatus) -> str:
    """``running layer 3 4/7 (57%)``: status, stage and done/total when known."""
    text = state.status
    if state.cancel_requested and not state.finished:
        text += " (cancel requested)"
    if state.stage:
        text += f" {state.stage}"
    if state.total:
        text += f" {state.done}/{state.total} ({100 * state.done // state.total}%)"
    return text


class Progress:
    """Draws a job's progress: one redrawn line with a bar on a terminal, else one plain line
    per change (status, stage, done or total) and at least one every ``heartbeat`` seconds."""

    heartbeat = 30.0

    def __init__(self, job_id: int, out: TextIO, *, tty: bool | None = None) -> None:
        self.job_id = job_id
        self.out = out
        self.tty = out.isatty() if tty is None else tty
        self.started = time.monotonic()
        self._last_key: tuple[Any, ...] | None = None
        self._last_line = self.started
        self._drawn = False

    def elapsed(self) -> float:
        return time.monotonic() - self.started

    def update(self, state: JobStatus) -> None:
        if self.tty:
            self._draw_line(state)
            return
        key = (state.status, state.stage, state.done, state.total, state.cancel_requested)
        now = time.monotonic()
        if key != self._last_key or now - self._last_line >= self.heartbeat:
            self._last_key = key
            self._last_line = now
            self.out.write(f"[{self.elapsed():7.1f} s] job {self.job_id} {progress_text(state)}\n")
            self.out.flush()

    def _draw_line(self, state: JobStatus) -> None:
        columns = shutil.get_terminal_size((80, 24)).columns
        head = f"job {self.job_id} {state.status}"
        if state.cancel_requested and not state.finished:
            head += " (cancel requested)"
        if state.stage:
            head += f" · {state.stage}"
        tail = f" {_clock(self.elapsed())}"
        if state.total:
            tail = f" {state.done}/{state.total}" + tail
            width = max(10, min(30, columns - len(head) - len(tail) - 5))
            filled = round(width * min(1.0, state.done / state.total))
            bar = f" [{'#' * filled}{'.' * (width - filled)}]"
        else:
            bar = ""
        line = (head + bar + tail)[: max(1, columns - 1)]
        self.out.write("\r\x1b[K" + line)
        self.out.flush()
        self._drawn = True

    def end_line(self) -> None:
        """Leave the redrawn line (before printing anything else)."""
        if self.tty and self._drawn:
            self.out.write("\r\x1b[K")
            self.out.flush()
            self._drawn = False


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
    took = ""
    if state.started_at is not None and state.finished_at is not None:
        took = f" after {(state.finished_at - state.started_at).total_seconds():.1f} s"
    if state.status != "succeeded":
        _out(f"job {job_id} {state.status}{took}", stream)
        reason = f": {state.error}" if state.error else ""
        return _fail(f"job {job_id} {state.status}{reason}", EXIT_FAILED)
    try:
        summary = rt.result(job_id).summary
    except RegtreeError:  # the job succeeded: say so even if its summary cannot be read
        summary = {}
    line = f"job {job_id} succeeded{took}"
    if summary:
        line += f": {summary.get('attached')} of {summary.get('subjects')} subjects attached"
        if summary.get("leaves"):
            line += f" ({summary['leaves']} as low-confidence leaves)"
        line += f", tree depth {summary.get('depth')}"
    _out(line, stream)
    _out(f"pictures and numbers: regtree results {job_id} --out DIR", stream)
    return EXIT_OK


def _interrupted(rt: RegtreeClient, job_id: int, cancel: bool) -> int:
    from service.client import Conflict

    if not cancel:
        return _fail(
            f"interrupted; job {job_id} keeps running on the server (follow it again with "
            f"`regtree watch {job_id}`, stop it with `regtree cancel {job_id}`)",
            EXIT_INTERRUPTED,
        )
    try:
        state = rt.cancel(job_id)
    except Conflict as e:
        return _fail(f"interrupted; not cancelled: {e.detail}", EXIT_INTERRUPTED)
    return _fail(
        f"interrupted; cancel requested for job {job_id} (now {state.status})", EXIT_INTERRUPTED
    )


def cmd_cancel(args: argparse.Namespace, rt: RegtreeClient) -> int:
    state = rt.cancel(args.job)
    if state.status == "cancelled":
        _out(f"job {args.job} cancelled")
    else:
        _out(f"job {args.job} {state.status}: cancel requested, it stops at its next report")
    return EXIT_OK


# --- results -----------------------------------------------------------------------------


def _file_stem(name: str) -> str:
    stem = re.sub(r"[^\w.+-]+", "_", name).strip("._") or "shape"
    return stem[:120]


def select_subjects(subjects: Sequence[Mapping[str, Any]], which: str | int) -> list[Any]:
    if which == "all":
        return list(subjects)
    if which == "attached":
        return [s for s in subjects if s.get("attached", s.get("layer") is not None)]
    return list(subjects[: int(which)])


def subject_status(subject: Mapping[str, Any]) -> str:
    """The subject's status: leaf (a low-confidence leaf), tree (a member) or unattached."""
    if subject.get("leaf"):
        return "leaf"
    if subject.get("attached", subject.get("layer") is not None) and subject.get("layer"):
        return "tree"
    return "unattached"


def _cell(text: str, width: int) -> str:
    text = text if len(text) <= width else text[: width - 1] + "…"
    return f"{text:<{width}}"


def subjects_table(doc: Mapping[str, Any], subjects: Sequence[Mapping[str, Any]]) -> list[str]:
    """One line per subject, in the given order: shape id, name, layer, parent, e, direct e,
    confidence and status ("tree", "leaf" for a low-confidence leaf, "unattached")."""
    names = dict(zip(doc.get("shape_ids") or [], doc.get("names") or [], strict=False))
    for s in doc.get("subjects") or []:
        if isinstance(s, Mapping) and "shape_id" in s and s.get("name") is not None:
            names[s["shape_id"]] = s["name"]
    width = min(32, max([4, *(len(str(s.get("name", ""))) for s in subjects)]))
    lines = [
        f"{'shape':>8}  {_cell('name', width)}  {'layer':>5}  {_cell('parent', 16)}"
        f" {'e':>11} {'direct e':>11} {'confidence':>10}  status"
    ]
    for s in subjects:
        layer = s.get("layer")
        parent = s.get("parent_shape_id")
        confidence = s.get("confidence")
        lines.append(
            f"{s.get('shape_id', '?'):>8}  {_cell(str(s.get('name', '')), width)}"
            f"  {('-' if layer is None else layer):>5}"
            f"  {_cell('-' if parent is None else str(names.get(parent, parent)), 16)}"
            f" {_num(s.get('error'))} {_num(s.get('direct_error'))}"
            + (
                f" {confidence:10.3f}"
                if isinstance(confidence, int | float) and not isinstance(confidence, bool)
                else f" {'-':>10}"
            )
            + f"  {subject_status(s)}"
        )
    return lines


def _subject_query(args: argparse.Namespace) -> dict[str, Any]:
    """The options of ``regtree results`` that the service's result query takes."""
    query: dict[str, Any] = {}
    if args.sort is not None:
        query["sort"] = args.sort
    if args.min_confidence is not None:
        query["min_confidence"] = args.min_confidence
    if args.leaf is not None:
        query["leaf"] = args.leaf
    return query


def _query_text(query: Mapping[str, Any]) -> str:
    parts = []
    if "min_confidence" in query:
        parts.append(f"confidence >= {query['min_confidence']:g}")
    if query.get("leaf") is True:
        parts.append("low-confidence leaves only")
    elif query.get("leaf") is False:
        parts.append("no low-confidence leaves")
    if query.get("sort") not in (None, "position"):
        key = str(query["sort"])
        direction = "descending" if key.startswith("-") else "ascending"
        parts.append(f"by {key.removeprefix('-')}, {direction}")
    return "; ".join(parts)


def _num(value: Any) -> str:
    return f"{value:11.4g}" if isinstance(value, int | float) else f"{'-':>11}"


def summary_table(doc: Mapping[str, Any]) -> list[str]:
    """Per-layer counts with mean / p95 of e, then layer >= 3 and all attached, for the tree
    and for direct CPD (``-`` where the job did not compare with it)."""
    from service.plots import layer_statistics

    subjects = [s for s in doc.get("subjects") or [] if isinstance(s, Mapping)]
    summary = doc.get("summary") or {}
    direct = summary.get("direct") or {}
    names = dict(zip(doc.get("shape_ids") or [], doc.get("names") or [], strict=False))
    root = doc.get("root_shape_id")
    counts: dict[int, int] = {}
    unattached = 0
    for s in subjects:
        if s.get("attached", s.get("layer") is not None) and s.get("layer") is not None:
            counts[int(s["layer"])] = counts.get(int(s["layer"]), 0) + 1
        else:
            unattached += 1
    tree_stats, direct_stats = layer_statistics(doc)
    leaves = sum(1 for s in subjects if s.get("leaf"))
    as_leaves = f" ({leaves} as low-confidence leaves)" if leaves else ""
    lines = [
        f"job {doc.get('job_id')}: {doc.get('method')}, model {names.get(root, root)!r} "
        f"(shape {root}); {len(subjects)} subjects, {sum(counts.values())} attached"
        f"{as_leaves}, {unattached} unattached, depth "
        f"{summary.get('depth', max(counts, default=1))}"
    ]
    thresholds = doc.get("thresholds") or {}
    for key in ("similarity", "error"):
        if isinstance(thresholds.get(key), int | float):
            lines.append(
                f"{key} threshold {thresholds[key]:.4g}  {thresholds.get(key + '_rule', '')}"
            )
    header = f"{'layer':>12} {'subjects':>8} {'tree mean':>11} {'tree p95':>11}"
    header += f" {'direct mean':>11} {'direct p95':>11}"
    lines += ["", "e (eq. 10) per layer", header, f"{1:>12} {1:>8}  (the model)"]
    for layer in sorted(counts):
        t, d = tree_stats.get(layer) or {}, direct_stats.get(layer) or {}
        lines.append(
            f"{layer:>12} {counts[layer]:>8} {_num(t.get('mean'))} {_num(t.get('p95'))}"
            f" {_num(d.get('mean'))} {_num(d.get('p95'))}"
        )
    if unattached:
        lines.append(f"{'unattached':>12} {unattached:>8}")
    lines += [
        "",
        f"{'':>12} {'count':>8} {'tree mean':>11} {'tree p95':>11}"
        f" {'direct mean':>11} {'direct p95':>11}",
    ]
    for label, key in (("layer >= 3", "layer_ge_3"), ("all attached", "all")):
        t, d = summary.get(key) or {}, direct.get(key) or {}
        lines.append(
            f"{label:>12} {t.get('count', 0):>8} {_num(t.get('mean'))} {_num(t.get('p95'))}"
            f" {_num(d.get('mean'))} {_num(d.get('p95'))}"
        )
    if not direct:
        lines.append("(direct CPD was not compared: the job ran with --no-compare-direct)")
    return lines


def cmd_results(args: argparse.Namespace, rt: RegtreeClient) -> int:
    job = rt.get_job(args.job)
    out: Path | None = args.out
    # every subject, for the summary, result.json and the tree; the full one to draw from
    doc = rt.result_document(args.job, full=out is not None)
    query = _subject_query(args)
    # the subject lines (and pictures): chosen and ordered by the service
    listed = rt.result_document(args.job, **query)["subjects"] if query else doc["subjects"]
    if out is None:
        for line in summary_table(doc):
            _out(line)
        _print_subjects(doc, listed, query)
        return EXIT_OK
    return _write_results(args, rt, job, doc, listed, query, out)


def _print_subjects(
    doc: Mapping[str, Any], listed: Sequence[Mapping[str, Any]], query: Mapping[str, Any]
) -> None:
    total = len(doc.get("subjects") or [])
    chosen = _query_text(query)
    _out("")
    _out(f"subjects ({chosen}): {len(listed)} of {total}" if chosen else f"subjects: {total}")
    for line in subjects_table(doc, listed):
        _out(line)
    if any(s.get("leaf") for s in listed):
        _out(
            "leaf: a low-confidence leaf, which the tree could not accept; it got its best "
            "registration anyway and is never a parent (its reason is in result.json)"
        )


def _write_results(
    args: argparse.Namespace,
    rt: RegtreeClient,
    job: JobStatus,
    doc: dict[str, Any],
    listed: Sequence[Mapping[str, Any]],
    query: Mapping[str, Any],
    out: Path,
) -> int:
    from service.plots import render_subject, render_summary, render_tree

    written: list[Path] = []
    problems: list[str] = []

    def write(path: Path, data: bytes) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        except OSError as e:
            raise CLIError(f"cannot write {path}: {e.strerror or e}", EXIT_FAILED) from e
        written.append(path)

    write(out / "result.json", json.dumps(doc, indent=1, ensure_ascii=False).encode("utf-8"))
    for name, draw in (
        ("tree.svg", lambda: render_tree(doc, fmt="svg")),
        ("tree.png", lambda: render_tree(doc, fmt="png")),
        ("summary.png", lambda: render_summary(doc, fmt="png")),
    ):
        try:
            write(out / name, draw().data)
        except (ValueError, KeyError, TypeError) as e:
            problems.append(f"{name}: {e}")

    full = {s.get("shape_id"): s for s in doc.get("subjects") or [] if isinstance(s, Mapping)}
    ordered = [full.get(s.get("shape_id"), s) for s in listed]
    chosen = select_subjects(ordered, args.subjects)
    used: set[str] = set()
    tty = sys.stdout.isatty()
    for number, subject in enumerate(chosen, start=1):
        shape_id = int(subject["shape_id"])
        name = str(subject.get("name", shape_id))
        stem = _file_stem(name)
        if stem in used:
            stem = f"{stem}-{shape_id}"
        used.add(stem)
        path = out / "subjects" / f"{stem}.{args.format}"
        try:
            points = rt.get_shape(job.collection_id, shape_id).points
            if points is None:
                raise ValueError("the service sent no points")
            picture = render_subject(
                subject, points, fmt=args.format, method=job.method, y_down=not args.y_up
            )
        except (ValueError, KeyError, TypeError) as e:
            problems.append(f"subject {name!r} (shape {shape_id}): {e}")
            continue
        write(path, picture.data)
        if tty:
            sys.stdout.write(f"\r\x1b[Ksubject pictures {number}/{len(chosen)}")
            sys.stdout.flush()
    if tty and chosen:
        sys.stdout.write("\r\x1b[K")

    for line in summary_table(doc):
        _out(line)
    _print_subjects(doc, listed, query)
    _out("")
    subject_files = [p for p in written if p.parent.name == "subjects"]
    for path in written:
        if path.parent.name != "subjects":
            _out(f"wrote {path}")
    if subject_files:
        _out(f"wrote {len(subject_files)} subject picture(s) in {out / 'subjects'}")
    if problems:
        for problem in problems:
            print(f"regtree: warning: not drawn: {problem}", file=sys.stderr)
        return _fail(f"{len(problems)} picture(s) could not be drawn", EXIT_FAILED)
    return EXIT_OK


HANDLERS: dict[str, Callable[[argparse.Namespace, RegtreeClient], int]] = {
    "upload": cmd_upload,
    "run": cmd_run,
    "watch": cmd_watch,
    "results": cmd_results,
    "cancel": cmd_cancel,
}

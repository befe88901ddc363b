"""The client commands' arguments (argparse only: ``regtree serve`` builds the same
parser before numpy is imported)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from service.contract.names import (
    DEFAULT_COMPARE_DIRECT,
    DEFAULT_IMAGE_MODE,
    DEFAULT_METHOD,
    DEFAULT_ON_CONFLICT,
    DEFAULT_WORKING_POINTS,
    IMAGE_MODES,
    METHODS,
    ON_CONFLICT_POLICIES,
    POSES,
    SUBJECT_SORTS,
)

if TYPE_CHECKING:
    pass

from service.cli_client._common import COMMANDS, DEFAULT_URL

N = TypeVar("N", int, float)

#: ``regtree run``'s options that it passes on as ``RegtreeClient.start_job``'s keyword
#: arguments of the same name.
RUN_JOB_OPTIONS = (
    "method", "similarity_threshold", "error_threshold", "pose", "max_rotation",
    "compare_direct", "working_points", "callback_url",
)

# --- argument parsing (argparse only) ----------------------------------------------------


def _checked(
    convert: Callable[[str], N], ok: Callable[[N], bool], expected: str, *, bad: str = ""
) -> Callable[[str], N]:
    """An argparse ``type``: ``convert`` the text, then refuse a value that is not ``ok``.

    The messages are "<expected>, got '<text>'", and "<bad>, got '<text>'" for a value that
    converts but is not ``ok`` (``expected`` when ``bad`` is not given).
    """

    def parse(text: str) -> N:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{expected}, got {text!r}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"{bad or expected}, got {text!r}")
        return value

    return parse


_positive_int = _checked(int, lambda v: v >= 1, "expected a positive integer")
_positive_float = _checked(
    float, lambda v: math.isfinite(v) and v > 0, "expected a positive number"
)
_job_id = _checked(
    lambda text: int(text.strip().removeprefix("#")),
    lambda v: v >= 1,
    "a job id is a number",
    bad="a job id is a positive number",
)
_confidence = _checked(
    float, lambda v: 0.0 <= v <= 1.0, "expected a number from 0 to 1"  # NaN refused too
)


def _working_points(text: str) -> int | None:
    """A working resolution: a count of points, 0 (or "none") for the stored resolution."""
    if text.strip().lower() in ("0", "none"):
        return None
    return _count_or_zero(text)


_count_or_zero = _checked(int, lambda v: v >= 0, "expected a number of points or 0")


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
        "service connection" + ("" if suppress else f" ({', '.join(COMMANDS)})")
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

    def command(name: str, *, job: bool = False, **kwargs: Any) -> argparse.ArgumentParser:
        """A client command with the connection options (and, with ``job``, the JOB it
        acts on)."""
        parser: argparse.ArgumentParser = sub.add_parser(name, **kwargs)
        add_connection_options(parser, suppress=True)
        if job:
            parser.add_argument("job", metavar="JOB", type=_job_id)
        return parser

    upload = command(
        "upload",
        help="upload a folder of shapes (point files, images) to a collection",
        description="Upload every point file (.txt .csv .json .npy) and image (.png .jpg "
        ".jpeg) in DIR whose name matches --pattern, sorted by name, in batches. The shape "
        "name is the file name without its extension.",
    )
    upload.add_argument("folder", metavar="DIR", type=Path)
    upload.add_argument("--collection", required=True, metavar="NAME",
                        help="the collection's name (or id); it must exist unless --create")
    upload.add_argument("--create", action="store_true",
                        help="create the collection (refused if one with this name exists)")
    upload.add_argument("--description", default="", help="with --create: its description")
    upload.add_argument("--pattern", default="*", metavar="GLOB", help="file names (default *)")
    upload.add_argument("--recursive", action="store_true", help="also look in subfolders")
    upload.add_argument("--mode", choices=IMAGE_MODES, default=DEFAULT_IMAGE_MODE,
                        help=f"how images become points (default {DEFAULT_IMAGE_MODE})")
    upload.add_argument("--target-points", type=_positive_int, metavar="N",
                        help="at most N points per image (default: the service's)")
    upload.add_argument(
        "--on-conflict", choices=ON_CONFLICT_POLICIES, default=DEFAULT_ON_CONFLICT,
        help="when the collection already holds a shape of a file's name: refuse (default: "
        "nothing of that batch is stored, so a folder uploaded twice is not doubled), replace "
        "it, or keep both",
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
    run.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD)
    for flag, largest in (("--similarity-threshold", "similarity distance D for a tree edge"),
                          ("--error-threshold", "registration error e to accept")):
        run.add_argument(flag, type=_positive_float, metavar="X",
                         help=f"largest {largest} (default: automatic)")
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
    run.add_argument("--max-rotation", type=float, metavar="DEG",
                     help="with --pose upright (or alone, which means upright): consider only "
                     "rotations within +-DEG degrees of the uploaded shapes (default 30)")
    run.add_argument(
        "--compare-direct", action=argparse.BooleanOptionalAction,
        default=DEFAULT_COMPARE_DIRECT,
        help="also register every subject directly from the model, for comparison (doubles "
        "the registrations; default: off, as on every surface)",
    )
    run.add_argument(
        "--working-points", type=_working_points, default=DEFAULT_WORKING_POINTS, metavar="N",
        help="decide the tree with every shape subsampled to at most N points, then register "
        "each edge once at the stored resolution (the result is at the stored resolution); "
        f"0 decides at the stored resolution (default: {DEFAULT_WORKING_POINTS})",
    )
    run.add_argument("--callback-url", metavar="URL",
                     help="POST a signed JSON notice (job id, state, result URL) to URL when "
                     "the job ends; the server must allow its host (setting "
                     "callback_allowed_hosts)")
    run.add_argument("--wait", action="store_true", help="follow the job until it ends")
    run.add_argument("-q", "--quiet", action="store_true", help="print only the job id")
    _watch_options(run)

    watch = command(
        "watch", job=True,
        help="follow a job's progress until it ends",
        description="Show the job's stage and done/total until it ends (a live bar on a "
        "terminal, one line per change otherwise). Exit 0 if it succeeded, 1 if it failed or "
        "was cancelled, 130 on Ctrl-C (the job keeps running unless --cancel-on-interrupt).",
    )
    _watch_options(watch)

    results = command(
        "results", job=True,
        help="print a job's result; download it and draw its pictures",
        description="Print the summary table and one line per subject (layer, parent, e, "
        "direct e, confidence, status: tree, leaf for a low-confidence leaf, or unattached). "
        "With --out, also write OUT/result.json (the full result document), tree.svg, "
        "tree.png, summary.png and subjects/<name>.png (the model warped onto each subject, "
        "beside direct CPD's). --sort, --min-confidence, --only-leaves and --no-leaves choose "
        "and order the subject lines and the subject pictures (the service does it); "
        "result.json, the tree and the summary always cover every subject.",
    )
    results.add_argument(
        "--out", type=Path, metavar="DIR", help="write the result and its pictures here"
    )
    results.add_argument("--subjects", type=_subjects_choice, default="all",
                         metavar="all|attached|N",
                         help="which subject pictures to draw: all (default), attached ones, "
                         "or the first N of the subject lines (0: none)")
    results.add_argument("--sort", type=_subject_sort, default=None, metavar="KEY",
                         help="order of the subjects: position (default, the job's shape "
                         "order), confidence, error, or descending with a leading - "
                         "(-confidence, -error); subjects without the value come last")
    results.add_argument("--min-confidence", type=_confidence, default=None, metavar="X",
                         help="only subjects whose confidence is at least X (0 to 1); leaves "
                         "out unattached ones")
    leaves = results.add_mutually_exclusive_group()
    leaves.add_argument("--only-leaves", dest="leaf", action="store_const", const=True,
                        default=None, help="only the low-confidence leaves")
    leaves.add_argument("--no-leaves", dest="leaf", action="store_const", const=False,
                        help="leave out the low-confidence leaves")
    results.add_argument("--format", choices=("png", "svg"), default="png",
                         help="format of the subject pictures (default png)")
    axis = results.add_mutually_exclusive_group()
    axis.add_argument("--y-up", dest="y_down", action="store_const", const=False, default=None,
                      help="draw every subject with y growing upwards (default: downwards for "
                      "shapes traced from images, upwards for shapes uploaded as coordinates, "
                      "as the service's own pictures)")
    axis.add_argument("--y-down", dest="y_down", action="store_const", const=True,
                      help="draw every subject with y growing downwards")
    results.add_argument("--csv", action="store_true", help="print the subjects as CSV (one "
                         "row per subject) instead of the tables")

    command("cancel", job=True, help="cancel a queued or running job")

    export = command(
        "export", job=True,
        help="download a whole job as one ZIP (JSON, CSV, similarity, pictures)",
        description="Write the job's ZIP: result.json (full), result.csv, similarity.json, "
        "job.json, tree.svg, tree.png, summary.png and, with --subject-pictures, one overlay "
        "per subject.",
    )
    export.add_argument(
        "--out", type=Path, metavar="FILE", help="where to write it (default job-JOB.zip)"
    )
    export.add_argument(
        "--subject-pictures", action="store_true", help="also draw every subject's overlay"
    )

    similarity = command(
        "similarity", job=True,
        help="print each shape's nearest shapes by the similarity D the job computed",
        description="For every shape of the job, the K shapes with the smallest D onto it "
        "(eq. 9; the direction the tree uses, member onto subject).",
    )
    similarity.add_argument(
        "--k", type=_positive_int, default=3, metavar="K", help="nearest shapes (default 3)"
    )

    group = command(
        "group",
        help="group a collection's shapes by the mould (type, block) that printed them",
        description="Queue a grouping job over every shape of the collection, follow it, and "
        "print the groups: each with its representative and members (shape id, name, "
        "confidence). With --no-wait, print the job id only.",
    )
    group.add_argument("collection", metavar="COLLECTION", help="its name or id")
    group.add_argument("--threshold", type=_positive_float, metavar="X",
                       help="cut of the average-linkage tree, in units of the shapes' RMS "
                       "radius (default: automatic, 2x the median nearest distance)")
    group.add_argument("--max-rotation", type=float, metavar="DEG",
                       help="the scans may be rotated by up to DEG degrees (default: a few)")
    group.add_argument("--wait", action=argparse.BooleanOptionalAction, default=True,
                       help="follow the job and print the groups (default: yes)")
    group.add_argument("--json", action="store_true", help="print the groups document")
    group.add_argument("--gallery", type=Path, metavar="PNG", help="also save the gallery")
    group.add_argument("--dendrogram", type=Path, metavar="PNG",
                       help="also save the dendrogram")
    _watch_options(group)


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

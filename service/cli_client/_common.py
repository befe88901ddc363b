"""What every client command shares: exit codes, errors, output, names or ids."""

from __future__ import annotations

import re
import sys
from collections.abc import Sequence
from enum import IntEnum
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from service.client import Collection, RegtreeClient, RegtreeError, Shape

COMMANDS = ("upload", "run", "watch", "results", "cancel", "export", "similarity", "group")



class Exit(IntEnum):
    """The client commands' exit codes."""

    OK = 0
    FAILED = 1
    USAGE = 2  # argparse's too
    CONNECTION = 3
    INTERRUPTED = 130  # 128 + SIGINT

DEFAULT_URL = "http://127.0.0.1:8000"


class CLIError(Exception):
    """An expected failure: printed as one ``regtree: error:`` line, exit ``code``."""

    def __init__(self, message: str, code: int = Exit.FAILED) -> None:
        super().__init__(message)
        self.code = code



def _check_url(url: str) -> None:
    if not re.match(r"^https?://[^/\s:]+", url):
        raise CLIError(
            f"--url must look like http://HOST:PORT (got {url!r}; default $REGTREE_URL)",
            Exit.USAGE,
        )


def _fail(message: str, code: int) -> int:
    sys.stdout.flush()
    print(f"regtree: error: {message}", file=sys.stderr, flush=True)
    return code


def describe_error(e: RegtreeError, *, notes: bool = True) -> str:
    """``<title>: <detail> (HTTP <status>)``, field errors after the first, every invalid
    file or shape of a refused upload after the first, and (with `notes`) the exception's
    notes."""
    if e.status is None:
        return str(e)
    text = str(e.title or "Error")
    if e.detail:
        text += f": {e.detail}"
    text += f" (HTTP {e.status})"
    for error in (e.errors or [])[1:]:
        where = ".".join(str(part) for part in error.get("loc") or [])
        text += f"; {where}: {error.get('msg')}" if where else f"; {error.get('msg')}"
    invalid = e.problem.get("invalid")
    if isinstance(invalid, list):
        for item in invalid[1:]:
            if isinstance(item, dict):
                where = item.get("file") or item.get("shape") or f"#{item.get('index')}"
                text += f"; {where}: {item.get('detail')}"
    if notes:
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
        raise CLIError(f"no {kind} {what}{where}{hint}", Exit.FAILED)
    ids = ", ".join(f"id {item.id} ({item.name!r})" for item in matches)
    raise CLIError(
        f"{value!r} is ambiguous: {len(matches)} {kind}s{where} match ({ids}); give the id",
        Exit.USAGE,
    )


def find_collection(rt: RegtreeClient, value: str) -> Collection:
    collection: Collection = _pick("collection", value, rt.list_collections())
    return collection


def find_shape(rt: RegtreeClient, collection: Collection, value: str) -> Shape:
    where = f" in collection {collection.name!r} (id {collection.id})"
    shape: Shape = _pick("shape", value, rt.list_shapes(collection.id), where=where)
    return shape


def _cell(text: str, width: int) -> str:
    text = text if len(text) <= width else text[: width - 1] + "…"
    return f"{text:<{width}}"



def _num(value: Any) -> str:
    return f"{value:11.4g}" if isinstance(value, int | float) else f"{'-':>11}"

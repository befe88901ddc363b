"""CSV/TXT uploads: one ``x y`` pair per line."""

from __future__ import annotations

import math
import re

import numpy as np

from service.ingest._base import (
    DEFAULT_LIMITS,
    FloatArray,
    IngestError,
    Limits,
    finalise,
    fmt_num,
    too_many,
)


def decode_text(data: bytes) -> str:
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        try:
            return data.decode("utf-16")
        except UnicodeDecodeError as e:
            raise IngestError("could not decode the file as UTF-16 text") from e
    if b"\x00" in data:
        raise IngestError("the file is not text (it contains NUL bytes)")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        # Numbers are ASCII; a legacy-encoded comment must not make the file unreadable.
        return data.decode("latin-1")


_SPACE_SPLIT = re.compile(r"\s+")
_NUMBER = re.compile(
    r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:nan|inf|infinity)", re.IGNORECASE
)


def _split_fields(line: str) -> list[str]:
    if ";" in line:
        fields = [f.strip() for f in line.split(";")]
        # ';' is the separator of locales whose decimal mark is ',' ("1,5;2,25").
        fields = [f.replace(",", ".") if f.count(",") == 1 and "." not in f else f for f in fields]
    elif "," in line:
        fields = [f.strip() for f in line.split(",")]
    else:
        fields = _SPACE_SPLIT.split(line.strip())
    while len(fields) > 2 and fields[-1] == "":  # "1,2," from spreadsheet exports
        fields.pop()
    return [f.strip().strip("\"'") for f in fields]


def _is_number(field: str) -> bool:
    return _NUMBER.fullmatch(field) is not None


def points_from_text(
    text: str,
    *,
    limits: Limits = DEFAULT_LIMITS,
) -> FloatArray:
    """Points from CSV/TXT text, one ``x y`` pair per line.

    Separators: whitespace (spaces or tabs), ``,`` or ``;`` (with ``;`` a decimal comma is
    accepted). Blank lines and ``#`` comments (whole-line or trailing) are skipped. The first
    non-comment line is skipped as a header if it has two fields and neither is a number
    (``x,y``, ``X;Y``, ``"x" "y"``). Any other line that is not exactly two numbers is an
    error naming the line (counted from 1).
    """
    rows: list[tuple[float, float]] = []
    first = True
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = _split_fields(line)
        if first:
            first = False
            if len(fields) == 2 and not any(_is_number(f) for f in fields):
                continue  # header
        shown = raw.strip()
        if len(shown) > 60:
            shown = shown[:57] + "..."
        if len(fields) != 2 or not all(_is_number(f) for f in fields):
            raise IngestError(f"line {lineno}: expected two numbers, got {shown!r}")
        x, y = float(fields[0]), float(fields[1])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise IngestError(f"line {lineno}: non-finite coordinate in {shown!r}")
        if abs(x) > limits.max_coordinate or abs(y) > limits.max_coordinate:
            raise IngestError(
                f"line {lineno}: coordinate beyond ±{fmt_num(limits.max_coordinate)} in "
                f"{shown!r}, the limit (setting max_coordinate)"
            )
        rows.append((x, y))
        if len(rows) > limits.max_points:
            raise too_many(limits)
    if not rows:
        raise IngestError("no points found: the file has only blank lines, comments or a header")
    return finalise(np.asarray(rows, dtype=np.float64).reshape(-1, 2), limits)

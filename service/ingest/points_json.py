"""JSON uploads: ``[[x, y], ...]`` or ``{"points": [[x, y], ...]}``."""

from __future__ import annotations

import json

import numpy as np

from service.ingest._base import (
    DEFAULT_LIMITS,
    FloatArray,
    IngestError,
    Limits,
    check_count,
    finalise,
    fmt_num,
)


def parse_json(data: bytes) -> object:
    """The parsed document, or an :class:`IngestError` saying where the JSON is broken."""
    try:
        return json.loads(data)
    except json.JSONDecodeError as e:
        raise IngestError(f"invalid JSON: {e.msg} at line {e.lineno} column {e.colno}") from e
    except UnicodeDecodeError as e:
        raise IngestError("invalid JSON: the file is not UTF-8 text") from e
    except RecursionError as e:
        raise IngestError("invalid JSON: nested too deeply") from e


def _json_type(v: object) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, str):
        return f"the string {json.dumps(v[:40])}"
    if isinstance(v, dict):
        return "an object"
    if isinstance(v, list | tuple):
        return "an array"
    if isinstance(v, int | float):
        return "a number"
    return type(v).__name__


def points_from_json(
    obj: object,
    *,
    limits: Limits = DEFAULT_LIMITS,
) -> FloatArray:
    """Points from parsed JSON: ``[[x, y], ...]`` or ``{"points": [[x, y], ...]}``.

    Coordinates must be JSON numbers (strings such as ``"3"`` and booleans are refused).
    """
    if isinstance(obj, dict):
        if "points" not in obj:
            raise IngestError(
                'expected a JSON array of [x, y] pairs or an object with a "points" array; '
                'the object has no "points" key'
            )
        obj = obj["points"]
        if not isinstance(obj, list):
            raise IngestError(f'"points" must be an array of [x, y] pairs; got {_json_type(obj)}')
    if not isinstance(obj, list | tuple):
        raise IngestError(f"expected a JSON array of [x, y] pairs; got {_json_type(obj)}")
    n = len(obj)
    if n > limits.max_points:
        check_count(n, limits)
    lengths = set()
    for i, p in enumerate(obj):
        if not isinstance(p, list | tuple):
            raise IngestError(f"point {i}: expected a pair [x, y]; got {_json_type(p)}")
        lengths.add(len(p))
    if lengths and lengths != {2}:
        if len(lengths) == 1:
            (k,) = lengths
            raise IngestError(f"expected points of shape (n, 2); got shape ({n}, {k})")
        i = next(i for i, p in enumerate(obj) if len(p) != 2)
        raise IngestError(f"point {i} has {len(obj[i])} coordinates; expected 2 (x, y)")
    out = np.empty((n, 2), dtype=np.float64)
    for i, p in enumerate(obj):
        for j, v in enumerate(p):
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise IngestError(f"point {i}: coordinates must be numbers; got {_json_type(v)}")
            try:
                out[i, j] = float(v)
            except OverflowError as e:  # an integer with hundreds of digits
                raise IngestError(
                    f"point {i} has a coordinate beyond ±{fmt_num(limits.max_coordinate)}, "
                    f"the limit (setting max_coordinate); points are counted from 0"
                ) from e
    return finalise(out, limits)

"""The running server's limits in its OpenAPI document.

Request models and routes are declared once, at import, but the limits they state are
settings (``REGTREE_MAX_POINTS_PER_SHAPE``...) that each app may have configured differently.
So wherever the schema states a limit, the source names the setting, and
:func:`resolve_limits` puts in the values of the app's settings when the app builds its
document (``service.main.create_app``):

* JSON Schema keywords: ``bounds(maxItems="max_points_per_shape")`` (``"-max_coordinate"``
  for the negation), spread into a schema or given as ``json_schema_extra``; it stands in
  the document as an ``x-regtree-limits`` extension until resolved;
* text: a placeholder ``{max_points_per_shape}`` in any string (a description, an example)
  is formatted in place; a format spec is allowed (``{max_coordinate:g}``). Only the names
  of :func:`limit_values` are placeholders: other braces (``/v1/jobs/{job_id}``) stay;
* upload examples: ``example("points")`` (or ``"batch"``, ``"csv"``, ``"text"``) stands for an
  example that the limits accept (enough points, coordinates in range, a batch that is not
  too large), so the document never shows an example the server would refuse.

The server enforces the same settings, so what the document states is what the server does.
"""

from __future__ import annotations

import math
import re
from typing import Any, Literal, Unpack

from pydantic import ConfigDict

from service.core.config import Settings

#: The page size of a list when the request gives none (at most ``max_page_size``).
DEFAULT_PAGE_SIZE = 50


def limit_values(settings: Settings) -> dict[str, int | float]:
    """The values placeholders may name: the limit settings, and what follows from them."""
    return {
        "max_body_bytes": settings.max_body_bytes,
        "min_points": settings.min_points,
        "max_points_per_shape": settings.max_points_per_shape,
        "max_coordinate": settings.max_coordinate,
        "max_image_pixels": settings.max_image_pixels,
        "max_batch_files": settings.max_batch_files,
        "max_shapes_per_collection": settings.max_shapes_per_collection,
        "max_page_size": settings.max_page_size,
        "default_page_size": default_page_size(settings),
    }


def default_page_size(settings: Settings) -> int:
    return min(DEFAULT_PAGE_SIZE, settings.max_page_size)


#: The names a placeholder or :func:`bounds` may use.
LIMIT_NAMES = frozenset(limit_values(Settings.model_construct()))
LIMITS_KEY = "x-regtree-limits"

_NAMES = "|".join(sorted(LIMIT_NAMES, key=len, reverse=True))
_PLACEHOLDER = re.compile(r"\{(" + _NAMES + r")(?::([^{}]*))?\}")


def bounds(**keywords: str) -> dict[str, Any]:
    """Schema keywords whose values are settings: ``bounds(maximum="max_coordinate",
    minimum="-max_coordinate")``."""
    unknown = [v for v in keywords.values() if v.removeprefix("-") not in LIMIT_NAMES]
    if unknown:
        raise ValueError(f"not limit settings: {unknown}; known: {sorted(LIMIT_NAMES)}")
    return {LIMITS_KEY: dict(keywords)}


EXAMPLE_KEY = "x-regtree-example"
ExampleKind = Literal["points", "batch", "csv", "text"]


def examples(*documents: dict[str, Any], **config: Unpack[ConfigDict]) -> ConfigDict:
    """A model's ``model_config``: ``config`` with ``documents`` as its schema's examples."""
    return ConfigDict(**config, json_schema_extra={"examples": list(documents)})


def example(kind: ExampleKind) -> dict[str, Any]:
    """An example upload that the app's limits accept, put in by :func:`resolve_limits`."""
    return {EXAMPLE_KEY: kind}


def example_values(settings: Settings) -> dict[str, Any]:
    """Example uploads within the limits: regular polygons with ``max(3, min_points)``
    vertices and coordinates well inside ``max_coordinate``; a batch of two shapes, or one
    when ``max_batch_files`` is 1."""
    n = max(3, settings.min_points)
    radius = 0.9 * min(1.0, settings.max_coordinate)

    def coordinate(v: float, r: float) -> float:
        return 0.0 if abs(v) < 1e-9 * r else float(f"{v:.4g}")

    def polygon(scale: float) -> list[list[float]]:
        angles = [2 * math.pi * i / n for i in range(n)]
        r = radius * scale
        return [[coordinate(r * math.cos(a), r), coordinate(r * math.sin(a), r)] for a in angles]

    points = polygon(1.0)
    batch = [{"name": f"shape-{k}", "points": polygon(1.0 - 0.4 * k)} for k in range(2)]
    rows = [f"{x:g},{y:g}" for x, y in points]
    return {
        "points": points,
        "batch": batch[: settings.max_batch_files],
        "csv": "x,y\n" + "\n".join(rows) + "\n",
        "text": "\n".join(row.replace(",", " ") for row in rows) + "\n",
    }


def resolve_text(text: str, values: dict[str, int | float]) -> str:
    """``text`` with every placeholder formatted."""
    return _PLACEHOLDER.sub(lambda m: format(values[m.group(1)], m.group(2) or ""), text)


def resolve_limits(node: Any, settings: Settings) -> Any:
    """A copy of ``node`` (an OpenAPI document or any part of it) with the values of the
    settings in place of its placeholders and ``bounds``."""
    return _resolve(node, limit_values(settings), example_values(settings))


def _resolve(node: Any, values: dict[str, int | float], examples: dict[str, Any]) -> Any:
    if isinstance(node, dict):
        if set(node) == {EXAMPLE_KEY}:
            return examples[node[EXAMPLE_KEY]]
        out = {
            key: _resolve(value, values, examples)
            for key, value in node.items()
            if key != LIMITS_KEY
        }
        for keyword, name in node.get(LIMITS_KEY, {}).items():
            value = values[name.removeprefix("-")]
            out[keyword] = -value if name.startswith("-") else value
        return out
    if isinstance(node, list):
        return [_resolve(item, values, examples) for item in node]
    if isinstance(node, str):
        return resolve_text(node, values)
    return node


def limits_description() -> str:
    """The limits section of the API description (with placeholders)."""
    return """
### Limits of this server

Set by the operator (`REGTREE_*` settings, named in brackets). A request past one is refused
with a problem document (413 for the body size, else 422) and stores nothing.

- Request body: at most {max_body_bytes} bytes [`max_body_bytes`].
- Points per shape: {min_points} to {max_points_per_shape} [`min_points`,
  `max_points_per_shape`]; each coordinate within ±{max_coordinate:g} [`max_coordinate`].
- Images: at most {max_image_pixels} pixels [`max_image_pixels`].
- One upload: at most {max_batch_files} files (multipart) or shapes (JSON batch)
  [`max_batch_files`].
- A collection: at most {max_shapes_per_collection} shapes [`max_shapes_per_collection`].
- Lists: at most {max_page_size} items a page, {default_page_size} by default
  [`max_page_size`].
- A transform request: at most {max_points_per_shape} points [`max_points_per_shape`].
"""

"""Reading the result document (``GET /v1/jobs/{id}/result``) defensively."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from registration import error_statistics
from service.contract.names import is_attached as is_attached
from service.contract.result import Summary

Doc = Mapping[str, Any]


def subjects(doc: Doc) -> list[Mapping[str, Any]]:
    items = doc.get("subjects")
    if not isinstance(items, Sequence):
        raise ValueError("the result document has no 'subjects' list")
    return [s for s in items if isinstance(s, Mapping)]


def is_leaf(subject: Mapping[str, Any]) -> bool:
    """A low-confidence leaf: the tree could not accept it, so it got its best registration
    once the tree stopped growing; never a parent."""
    return bool(subject.get("leaf", False))


def confidence(subject: Mapping[str, Any]) -> float | None:
    """The subject's confidence (0 to 1), or None (unattached, or an older result)."""
    value = subject.get("confidence")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if np.isfinite(value) else None


def root_id(doc: Doc) -> int:
    if "root_shape_id" not in doc:
        raise ValueError("the result document has no 'root_shape_id'")
    return int(doc["root_shape_id"])


def shape_names(doc: Doc) -> dict[int, str]:
    """Shape id -> name, from ``names``/``shape_ids`` and the subjects."""
    names: dict[int, str] = {}
    ids, labels = doc.get("shape_ids"), doc.get("names")
    if isinstance(ids, Sequence) and isinstance(labels, Sequence) and len(ids) == len(labels):
        names.update({int(i): str(n) for i, n in zip(ids, labels, strict=True)})
    for s in subjects(doc):
        if "shape_id" in s and s.get("name") is not None:
            names[int(s["shape_id"])] = str(s["name"])
    return names


def parent_of(subject: Mapping[str, Any]) -> int | None:
    parent = subject.get("parent_shape_id")
    if parent is not None:
        return int(parent)
    path = subject.get("path_shape_ids") or []
    return int(path[-2]) if len(path) >= 2 else None


def find_subject(doc: Doc, shape_id: int) -> Mapping[str, Any]:
    """The subject entry for ``shape_id`` in a (full) result document."""
    for s in subjects(doc):
        if int(s.get("shape_id", -1)) == shape_id:
            return s
    raise KeyError(f"shape {shape_id} is not a subject of this result")


def layer_statistics(doc: Doc) -> tuple[dict[int, dict[str, Any]], dict[int, dict[str, Any]]]:
    """Per tree layer: e statistics of the tree, and of direct CPD on the same subjects.

    Taken from ``summary.per_layer`` / ``summary.direct.per_layer`` when present, else computed
    from the subjects (``error``, ``direct_error`` or ``direct.error``). The direct dict is
    empty when the job did not compare with direct CPD.
    """
    raw = doc.get("summary")
    summary = Summary.model_validate(raw if isinstance(raw, Mapping) else {})
    if "per_layer" in summary.model_fields_set:
        tree = {int(k): v.model_dump() for k, v in summary.per_layer.items()}
        direct_summary = summary.direct
        direct = (
            {int(k): v.model_dump() for k, v in direct_summary.per_layer.items()}
            if direct_summary is not None and "per_layer" in direct_summary.model_fields_set
            else {}
        )
        return tree, direct
    tree_values: dict[int, list[float]] = {}
    direct_values: dict[int, list[float]] = {}
    any_direct = False
    for s in subjects(doc):
        if not is_attached(s) or s.get("layer") is None:
            continue
        layer = int(s["layer"])
        tree_values.setdefault(layer, [])
        direct_values.setdefault(layer, [])
        if s.get("error") is not None:
            tree_values[layer].append(float(s["error"]))
        d = s.get("direct_error")
        if d is None and isinstance(s.get("direct"), Mapping):
            d = s["direct"].get("error")
        if d is not None:
            any_direct = True
            direct_values[layer].append(float(d))
    tree = {k: error_statistics(v) for k, v in sorted(tree_values.items())}
    direct = (
        {k: error_statistics(v) for k, v in sorted(direct_values.items())} if any_direct else {}
    )
    return tree, direct

"""The library's result as the API's result document: shape ids beside list positions.

:func:`to_api_document` maps a ``CollectionResult.to_dict()`` onto the job's shape ids; its
output validates against :class:`service.contract.result.ResultDocument` (the light
document) and :class:`~service.contract.result.SubjectDetail` (each full subject).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from service.contract.names import is_attached, subject_status
from service.models import points_to_npy

__all__ = ["HEAVY_SUBJECT_KEYS", "json_safe", "similarity_npy", "to_api_document"]

#: What the light result document leaves out of each subject (``?full=true`` has them).
HEAVY_SUBJECT_KEYS = ("warped", "correspondence", "probability", "transform", "direct")


def _index_to_id(value: Any, shape_ids: list[int]) -> int | None:
    if value is None or isinstance(value, bool):
        return None
    try:
        index = int(value)
    except (TypeError, ValueError):
        return None
    return shape_ids[index] if 0 <= index < len(shape_ids) else None


def _with_shape_ids(raw: dict[str, Any], shape_ids: list[int], fallback: int) -> dict[str, Any]:
    subject = dict(raw)
    position = int(subject.get("index", fallback))
    subject["position"] = position
    subject["shape_id"] = shape_ids[position]
    subject["parent_shape_id"] = _index_to_id(subject.get("parent"), shape_ids)
    subject["status"] = subject_status(subject)
    path = subject.get("path")
    if isinstance(path, list):
        subject["path_shape_ids"] = [_index_to_id(p, shape_ids) for p in path]
    attempts = subject.get("attempts")
    if isinstance(attempts, list):
        subject["attempts"] = [
            {**a, "member_shape_id": _index_to_id(a.get("member"), shape_ids)}
            if isinstance(a, dict)
            else a
            for a in attempts
        ]
    quality = subject.get("quality")
    polish = quality.get("polish") if isinstance(quality, dict) else None
    consensus = polish.get("consensus") if isinstance(polish, dict) else None
    if (isinstance(quality, dict) and isinstance(polish, dict)  # the consensus's partner
            and isinstance(consensus, dict) and "partner" in consensus):
        subject["quality"] = {**quality, "polish": {**polish, "consensus": {
            **consensus, "partner_shape_id": _index_to_id(consensus["partner"], shape_ids)}}}
    transform = subject.get("transform")
    if isinstance(transform, dict) and isinstance(transform.get("path"), list):
        subject["transform"] = {
            **transform,
            "path_shape_ids": [_index_to_id(p, shape_ids) for p in transform["path"]],
        }
        base = transform.get("base")
        if isinstance(base, dict):  # the steps it shares with that subject's transform
            subject["transform"]["base"] = {
                **base, "shape_id": _index_to_id(base.get("index"), shape_ids)}
    return subject


def tree_nodes(root_shape_id: int | None, name: str, subjects: list[dict[str, Any]]
               ) -> list[dict[str, Any]]:
    """The tree by shape id: the root, then every attached subject in input order, each with
    its parent, layer, status and children (low-confidence leaves have none)."""
    root: dict[str, Any] = {
        "shape_id": root_shape_id,
        "name": name,
        "parent_shape_id": None,
        "layer": 1,
        "status": "root",
        "children_shape_ids": [],
    }
    nodes = [root] + [
        {
            "shape_id": s["shape_id"],
            "name": s.get("name", ""),
            "parent_shape_id": s.get("parent_shape_id"),
            "layer": s.get("layer"),
            "status": s["status"],
            "children_shape_ids": [],
        }
        for s in subjects
        if is_attached(s)
    ]
    by_id = {n["shape_id"]: n for n in nodes}
    for node in nodes[1:]:
        parent = by_id.get(node["parent_shape_id"])
        if parent is not None:
            parent["children_shape_ids"].append(node["shape_id"])
    return nodes


def to_api_document(
    job_id: int, doc: dict[str, Any], shape_ids: list[int]
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Map the library's positions onto shape ids.

    Returns the result document (subjects without heavy arrays) and the full subjects.
    Every subject keeps the library's keys (``index`` and ``parent`` are positions in the
    job's input) and gains ``shape_id``, ``position``, ``parent_shape_id``,
    ``path_shape_ids``, ``status``, in its transform ``path_shape_ids`` and, when its
    polish took a consensus, ``partner_shape_id`` beside the consensus's ``partner``; with
    ``compare_direct``, the direct registration of a subject is under ``direct`` (full) and
    ``direct_error`` (light). The document gains ``tree``: its nodes by shape id.
    """
    direct: dict[int, dict[str, Any]] = {}
    for k, raw in enumerate(doc.get("direct") or []):
        if isinstance(raw, dict):
            entry = _with_shape_ids(raw, shape_ids, k)
            direct[entry["shape_id"]] = entry
    subjects: list[dict[str, Any]] = []
    for k, raw in enumerate(doc.get("subjects", [])):
        subject = _with_shape_ids(raw, shape_ids, k)
        if subject["shape_id"] in direct:
            subject["direct"] = direct[subject["shape_id"]]
            subject["direct_error"] = direct[subject["shape_id"]].get("error")
        subjects.append(subject)
    light = [{k: v for k, v in s.items() if k not in HEAVY_SUBJECT_KEYS} for s in subjects]
    document = {k: v for k, v in doc.items() if k not in ("subjects", "direct")}
    root_shape_id = _index_to_id(doc.get("root"), shape_ids)
    names = doc.get("names") or []
    root = doc.get("root")
    root_name = str(names[root]) if isinstance(root, int) and 0 <= root < len(names) else ""
    document.update(
        job_id=job_id,
        root_shape_id=root_shape_id,
        shape_ids=list(shape_ids),
        subjects=light,
        tree=tree_nodes(root_shape_id, root_name, light),
    )
    return document, subjects


def json_safe(value: Any) -> Any:
    """Replace non-finite floats (not valid JSON) with None, recursively.

    A full result holds millions of floats (40 MB of JSON for 73 glyphs of ~1900 points):
    ``math.isfinite`` and a flat path for lists of floats and of points keep this to a
    fraction of a second (it was 5 s with ``np.isfinite`` on each scalar). A finite
    point is passed on as the input's own ``[x, y]`` list, not copied."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        first = value[0] if value else None
        numbers: Iterable[Any] | None = None
        if type(first) is float or type(first) is int:
            numbers = value
        elif (type(first) is list and first and type(first[0]) is float
              and set(map(type, value)) == {list}):  # points, rows of numbers
            numbers = itertools.chain.from_iterable(value)
        if numbers is not None:
            # every number finite: the list as it is, checked in C (73 glyphs' 580 000
            # points took 0.3 s checked point by point in Python, the job's last step)
            try:
                if all(map(math.isfinite, numbers)):
                    return value if type(value) is list else list(value)
            except (TypeError, OverflowError):  # not all numbers: the ways below
                pass
        if all(type(v) is float for v in value):
            return [v if math.isfinite(v) else None for v in value]
        if all(type(v) is list and len(v) == 2 and type(v[0]) is float and type(v[1]) is float
               for v in value):  # points: [x, y] pairs
            return [v if math.isfinite(v[0]) and math.isfinite(v[1]) else
                    [c if math.isfinite(c) else None for c in v] for v in value]
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        return json_safe(value.item())
    return value


def similarity_npy(similarity: np.ndarray | None, n: int) -> bytes | None:
    """The job's similarity D as ``.npy`` bytes to store, or None without an (n, n) one."""
    if similarity is None:
        return None
    array = np.asarray(similarity, dtype=np.float64)
    return points_to_npy(array) if array.shape == (n, n) else None

"""A ``grouping`` job (issue 11): the library's :func:`registration.group_instances` over the
collection's shapes, and its result as the API's grouping document, by shape id.

The document (:class:`service.contract.result.GroupingDocument`) is stored as the job's
result document, without result subjects: ``instances`` (one per shape, in the job's input
order: its group ``label``, ``confidence`` and the group's representative), ``labels`` (group
by shape id), ``groups`` (members and representative by shape id), the ``distances`` matrix
in ``shape_ids`` order and the average-linkage tree for a dendrogram.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.contract.names import GROUPING_METHOD

__all__ = ["grouping_document", "run_grouping"]

#: Distances are stored to this many decimals (units: RMS radius; noise is ~0.03).
DECIMALS = 5


def run_grouping(
    job_id: int,
    shapes: list[np.ndarray],
    names: list[str],
    shape_ids: list[int],
    params: dict[str, Any],
    *,
    executor: Any,
    progress: Any,
) -> dict[str, Any]:
    """Group the job's shapes and return the grouping document."""
    from registration import group_instances

    result = group_instances(
        shapes,
        threshold=params.get("group_threshold"),
        max_rotation=params.get("max_rotation"),
        executor=executor,
        progress=progress,
    )
    return grouping_document(job_id, result.to_dict(), names, shape_ids)


def grouping_document(
    job_id: int, raw: dict[str, Any], names: list[str], shape_ids: list[int]
) -> dict[str, Any]:
    """``GroupingResult.to_dict()`` with positions written as shape ids."""
    labels = [int(v) for v in raw["labels"]]
    groups = raw["groups"]
    distances = np.round(np.asarray(raw["distances"], dtype=np.float64), DECIMALS)
    rep_of = {int(g["label"]): int(g["representative"]) for g in groups}
    instances = [
        {
            "position": k,
            "shape_id": shape_ids[k],
            "name": names[k],
            "label": labels[k],
            "confidence": float(raw["confidence"][k]),
            "representative_shape_id": shape_ids[rep_of[labels[k]]],
            "distance_to_representative": float(distances[k, rep_of[labels[k]]]),
            "dropped_points": int(raw["dropped_points"][k]),
        }
        for k in range(len(shape_ids))
    ]
    return {
        "kind": GROUPING_METHOD,
        "method": GROUPING_METHOD,
        "job_id": job_id,
        "shape_ids": list(shape_ids),
        "names": list(names),
        "n_groups": len(groups),
        "threshold": float(raw["threshold"]),
        "threshold_source": raw["threshold_source"],
        "noise_level": float(raw["noise_level"]),
        "pairs_computed": int(raw["pairs_computed"]),
        "labels": {str(shape_ids[k]): labels[k] for k in range(len(shape_ids))},
        "instances": instances,
        "groups": [
            {
                "label": int(g["label"]),
                "size": len(g["members"]),
                "shape_ids": [shape_ids[m] for m in g["members"]],
                "representative_shape_id": shape_ids[int(g["representative"])],
                "spread": float(g["spread"]),
            }
            for g in groups
        ],
        "distances": distances.tolist(),
        "linkage": [[float(v) for v in row] for row in raw["linkage"]],
    }

"""Grouping impressions whose points come through the service's image ingestion."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from registration import group_instances
from registration.impressions import draw_strokes, recut_stroke_end, simulate_impressions
from service.ingest import points_from_image


def test_scans_through_image_ingestion_group_by_mould_with_a_recut_twin():
    mould = draw_strokes([[0.2, 0.25, 0.8, 0.25], [0.5, 0.25, 0.5, 0.85],
                          [0.25, 0.6, 0.75, 0.6]], size=160, width=0.08)
    other = draw_strokes([[0.15, 0.5, 0.85, 0.5], [0.5, 0.15, 0.5, 0.85]], size=160,
                         width=0.08)
    recut = recut_stroke_end(mould, change="extend", seed=2).mould
    rng = np.random.default_rng(7)
    shapes, truth = [], []
    for k, m in enumerate([mould, recut, other]):
        for img in simulate_impressions(m, 3, seed=rng):
            buf = io.BytesIO()
            Image.fromarray(img).save(buf, format="PNG")
            shapes.append(points_from_image(buf.getvalue(), mode="contour",
                                            target_points=1500))
            truth.append(k)
    res = group_instances(shapes)
    assert [sorted(g.members) for g in res.groups] == [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    assert res.to_dict()["labels"] == [int(v) for v in res.labels]

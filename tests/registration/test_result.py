"""error_statistics (registration/_result.py) against hand computations; the document's
collector pause."""

from __future__ import annotations

import gc
from typing import Any

import numpy as np
import pytest

from registration import CollectionResult, SubjectResult, error_statistics


def test_mean_and_linearly_interpolated_95th_percentile() -> None:
    # 1..20: mean 10.5; the 95th percentile sits at rank 0.95 * 19 = 18.05 (0-based),
    # between 19 and 20: 19 + 0.05 * (20 - 19) = 19.05
    stats = error_statistics([float(v) for v in range(20, 0, -1)])
    assert stats == {"count": 20, "mean": pytest.approx(10.5), "p95": pytest.approx(19.05)}


def test_small_lists() -> None:
    # two values: rank 0.95 -> 0.1 + 0.95 * (0.3 - 0.1) = 0.29
    stats = error_statistics([0.3, 0.1])
    assert stats["count"] == 2
    assert stats["mean"] == pytest.approx(0.2)
    assert stats["p95"] == pytest.approx(0.29)
    one = error_statistics([0.004])
    assert one == {"count": 1, "mean": pytest.approx(0.004), "p95": pytest.approx(0.004)}
    assert isinstance(one["mean"], float) and isinstance(one["p95"], float)


def test_empty_list_has_no_mean() -> None:
    assert error_statistics([]) == {"count": 0, "mean": None, "p95": None}


def _result(n_points: int = 300) -> CollectionResult:
    rng = np.random.default_rng(0)
    subjects = [
        SubjectResult(index=k, name=f"s{k}", parent=0, layer=2, path=[0, k], error=0.001 * k,
                      warped=rng.normal(size=(n_points, 2)),
                      correspondence=np.arange(n_points), probability=rng.random(n_points))
        for k in range(1, 6)
    ]
    return CollectionResult(method="direct", root=0, names=[f"s{k}" for k in range(6)],
                            subjects=subjects, thresholds={}, options={})


@pytest.mark.parametrize("enabled", [True, False])
def test_the_document_is_built_without_collections_and_the_collector_is_left_as_it_was(
        enabled: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """to_dict builds millions of containers on a full result; the collector is paused
    while the document is built (no collection runs, even with a threshold of 1) and then
    left as it was."""
    result = _result()
    collections: list[int] = []
    building = [False]
    document = CollectionResult._document

    def built(self: CollectionResult, *args: Any) -> dict[str, Any]:
        building[0] = True
        try:
            return document(self, *args)
        finally:
            building[0] = False

    monkeypatch.setattr(CollectionResult, "_document", built)

    def seen(phase: str, info: dict[str, int]) -> None:
        if phase == "start" and building[0]:
            collections.append(info["generation"])

    thresholds = gc.get_threshold()
    was = gc.isenabled()
    gc.callbacks.append(seen)
    try:
        gc.set_threshold(1, 1, 1)
        (gc.enable if enabled else gc.disable)()
        doc = result.to_dict()
        assert gc.isenabled() is enabled
    finally:
        gc.callbacks.remove(seen)
        gc.set_threshold(*thresholds)
        (gc.enable if was else gc.disable)()
    assert collections == []
    assert [s["warped"] for s in doc["subjects"]] == [s.warped.tolist() for s in result.subjects]


def test_the_collector_comes_back_when_the_document_fails() -> None:
    result = _result()
    result.subjects[0].warped = object()  # type: ignore[assignment]  # no tolist
    assert gc.isenabled()
    with pytest.raises(AttributeError):
        result.to_dict()
    assert gc.isenabled()

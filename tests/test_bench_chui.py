"""The Chui & Rangarajan families' ground truth (bench/bench_groundtruth.py `chui_cases`).

The benchmark's files differ by series: ``Y_clean`` has ``Y``'s rows (deformation, noise,
occlusion) or only its inlier rows (outliers, ``gt_index_into_X == -1``), and the
occlusion series lists the model's rows in another order at each level. Checked here on
small files written in those three layouts (the real ones are in ``../shared``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest


def _write(directory: Path, name: str, x: np.ndarray, y: np.ndarray, y_clean: np.ndarray,
           gt: np.ndarray) -> None:
    np.savez(directory / f"{name}.npz", X=x[None], Y=y[None], Y_clean=y_clean[None],
             gt_index_into_X=gt)


@pytest.fixture()
def series(tmp_path: Path, bg: Any, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Level files of three series for the kind 'fish', one trial: the model, and per
    level its true images (each a shift of the model by the level, so every row's truth
    is known)."""
    rng = np.random.default_rng(0)
    model = rng.normal(size=(12, 2))
    monkeypatch.setattr(bg, "CHUI", tmp_path)
    monkeypatch.setattr(bg, "CHUI_SERIES", {"noise": 2, "outlier": 2, "occlusion": 2})
    for lvl in (1, 2):
        image = model + lvl
        # noise: Y is the clean image plus noise, row for row
        _write(tmp_path, f"fish_noise_{lvl}", model, image + 0.01 * lvl, image,
               np.arange(12))
        # outliers: extra rows (gt -1) mixed in; Y_clean holds the inlier rows, in order
        extra = rng.uniform(-5, 5, size=(3 * lvl, 2))
        y = np.concatenate([image[:6], extra, image[6:]])
        gt = np.concatenate([np.arange(6), -np.ones(3 * lvl, int), np.arange(6, 12)])
        _write(tmp_path, f"fish_outlier_{lvl}", model, y, image, gt)
        # occlusion: the model's rows reordered; the last rows of that order cut away
        order = rng.permutation(12) if lvl > 1 else np.arange(12)
        x = model[order]
        keep = 12 - 4 * (lvl - 1)
        y = (x + lvl)[:keep]
        _write(tmp_path, f"fish_occlusion_{lvl}", x, y, y, np.arange(keep))
    return {"model": model, "order": order}


@pytest.mark.parametrize("name", ["noise", "outlier", "occlusion"])
def test_chui_series_truth(bg: Any, series: dict[str, Any], name: str) -> None:
    (case,) = bg.chui_cases("fish", [0], name)
    model = series["model"]
    assert case.kind == f"chui-{name}" and case.root == 0 and len(case.shapes) == 3
    np.testing.assert_array_equal(case.shapes[0], model)
    for lvl in (1, 2):
        truth = case.truth[lvl]
        has = np.isfinite(truth).all(axis=1)
        # every model row with an image has its own shift, whichever order Y lists it in
        np.testing.assert_allclose(truth[has], model[has] + lvl)
        expected = 12 if name != "occlusion" else 12 - 4 * (lvl - 1)
        assert has.sum() == expected
    if name == "occlusion":  # the rows cut away are the last of that level's order
        assert not np.isfinite(case.truth[2][series["order"][8:]]).any()
    if name == "outlier":  # the subject keeps its outliers; they are nobody's image
        assert len(case.shapes[2]) == 18


def test_chui_series_refuses_another_model(bg: Any, series: dict[str, Any],
                                           tmp_path: Path) -> None:
    d = np.load(tmp_path / "fish_noise_2.npz")
    np.savez(tmp_path / "fish_noise_2.npz", X=d["X"] + 1.0, Y=d["Y"], Y_clean=d["Y_clean"],
             gt_index_into_X=d["gt_index_into_X"])
    with pytest.raises(SystemExit, match="different model X"):
        bg.chui_cases("fish", [0], "noise")

"""group_instances: grouping impressions by the mould that printed them (issue 11)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from skimage.measure import find_contours

from registration import GroupingResult, group_instances
from registration.impressions import (
    draw_strokes,
    impression_set,
    recut_stroke_end,
    simulate_impressions,
)

# three "characters" of a few strokes each, and a variant of the first with one stroke
# end moved (another carver)
A = [[0.2, 0.2, 0.8, 0.2], [0.5, 0.2, 0.5, 0.85], [0.25, 0.55, 0.75, 0.55]]
B = [[0.2, 0.3, 0.8, 0.3], [0.3, 0.3, 0.3, 0.85], [0.3, 0.85, 0.8, 0.75]]
C = [[0.15, 0.5, 0.85, 0.5], [0.5, 0.15, 0.5, 0.85], [0.2, 0.2, 0.4, 0.35]]


def contour_points(img: np.ndarray, n: int = 800) -> np.ndarray:
    """Outline points of a grey scan (dark ink): every contour of the thresholded image."""
    found = find_contours(np.pad(img < 128, 1).astype(float), 0.5)
    pts = np.concatenate([c[:, ::-1] for c in found if len(c) >= 6])
    idx = np.linspace(0, len(pts) - 1, min(n, len(pts))).round().astype(int)
    return pts[idx]


def prints(moulds: list[np.ndarray], n: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    return impression_set(moulds, n, to_points=contour_points, seed=seed)


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    return all(len(set(b[a == v])) == 1 for v in set(a)) and \
        all(len(set(a[b == v])) == 1 for v in set(b))


@pytest.fixture(scope="module")
def three_moulds() -> tuple[list[np.ndarray], np.ndarray, GroupingResult]:
    moulds = [draw_strokes(s, size=160, width=0.08) for s in (A, B, C)]
    shapes, truth = prints(moulds, 4, seed=0)
    return shapes, truth, group_instances(shapes)


def test_impressions_of_different_moulds_fall_into_their_moulds(three_moulds):
    shapes, truth, res = three_moulds
    assert res.labels.shape == (len(shapes),)
    assert same_partition(res.labels, truth)
    assert res.n_groups == 3
    for g in res.groups:
        assert g.representative in g.members
        assert all(res.labels[m] == g.label for m in g.members)
        assert 0 <= g.spread <= 2 * res.threshold
    assert (res.confidence > 0.3).all()


def test_distances_are_symmetric_small_within_and_large_across(three_moulds):
    _, truth, res = three_moulds
    D = res.distances
    assert np.allclose(D, D.T, equal_nan=True)
    same = truth[:, None] == truth[None, :]
    off = ~np.eye(len(truth), dtype=bool)
    within = D[same & off]
    across = D[~same]
    assert np.nanmax(within) < np.nanmin(across)


def test_labels_follow_the_input_order(three_moulds):
    shapes, truth, _ = three_moulds
    perm = np.random.default_rng(3).permutation(len(shapes))
    res = group_instances([shapes[k] for k in perm])
    assert same_partition(res.labels, truth[perm])


def test_one_recut_stroke_end_makes_another_mould():
    mould = draw_strokes(A, size=160, width=0.08)
    recut = recut_stroke_end(mould, change="shorten", seed=1).mould
    shapes, truth = prints([mould, recut], 4, seed=1)
    res = group_instances(shapes)
    assert same_partition(res.labels, truth)


def test_an_outlier_stays_alone_with_no_confidence():
    moulds = [draw_strokes(s, size=160, width=0.08) for s in (A, B)]
    shapes, truth = prints(moulds, 3, seed=2)
    odd = draw_strokes(C, size=160, width=0.08)
    shapes.append(contour_points(simulate_impressions(odd, 1, seed=9)[0]))
    res = group_instances(shapes)
    assert same_partition(res.labels[:-1], truth)
    alone = res.groups[res.labels[-1]]
    assert alone.members == [len(shapes) - 1]
    assert res.confidence[-1] == 0.0
    assert (res.confidence[:-1] > 0).all()


def test_explicit_threshold_decides_the_cut(three_moulds):
    shapes, _, res = three_moulds
    huge = group_instances(shapes, threshold=10.0)
    assert huge.n_groups == 1 and huge.threshold_source == "given"
    tiny = group_instances(shapes, threshold=1e-6)
    assert tiny.n_groups == len(shapes)
    assert (tiny.confidence == 0).all()
    assert res.threshold_source == "automatic"


def test_result_is_json_serialisable_and_has_a_short_repr(three_moulds):
    shapes, _, res = three_moulds
    d = json.loads(json.dumps(res.to_dict()))
    assert d["labels"] == [int(v) for v in res.labels]
    assert len(d["distances"]) == len(shapes)
    assert len(d["linkage"]) == len(shapes) - 1
    assert {g["representative"] for g in d["groups"]} == {g.representative for g in res.groups}
    r = repr(res)
    assert "3 groups" in r and len(r) < 200


def test_a_single_instance_is_its_own_group():
    res = group_instances([np.random.default_rng(0).normal(size=(50, 2))])
    assert list(res.labels) == [0] and res.confidence[0] == 0.0


def test_ink_specks_are_ignored():
    mould = draw_strokes(A, size=160, width=0.08)
    shapes, _ = prints([mould], 3, seed=4)
    rng = np.random.default_rng(0)
    corners = np.array([[[2.0, 2.0]], [[2.0, 170.0]], [[170.0, 2.0]]])
    for k in range(len(shapes)):  # three specks of 4 points in the scan's corners
        specks = (corners + rng.normal(0, 0.5, size=(3, 4, 2))).reshape(-1, 2)
        shapes[k] = np.vstack([shapes[k], specks])
    res = group_instances(shapes)
    assert res.n_groups == 1
    assert all(d >= 12 for d in res.dropped_points)  # (and any the simulation printed)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"threshold": -1.0}, "threshold must be"),
    ({"neighbours": 0}, "neighbours must be"),
    ({"max_rotation": 400}, "max_rotation must be"),
])
def test_bad_options_are_value_errors(kwargs, match):
    shapes = [np.random.default_rng(k).normal(size=(30, 2)) for k in range(3)]
    with pytest.raises(ValueError, match=match):
        group_instances(shapes, **kwargs)


def test_bad_shapes_are_value_errors():
    with pytest.raises(ValueError, match="empty"):
        group_instances([])
    with pytest.raises(ValueError, match=r"shapes\[1\]"):
        group_instances([np.zeros((10, 2)) + np.arange(10)[:, None], np.zeros((10, 3))])


def test_compare_instances_says_where_a_recut_differs():
    from registration import compare_instances

    mould = draw_strokes(A, size=160, width=0.08)
    cut = recut_stroke_end(mould, change="shorten", seed=1)
    shapes, _ = prints([mould, cut.mould], 2, seed=3)
    same = compare_instances(shapes[0], shapes[1])
    other = compare_instances(shapes[0], shapes[2])
    assert same.distance < other.distance
    assert other.difference.shape == (len(other.grid), len(other.grid))
    assert other.instance.shape[1] == 2 and other.reference.shape[1] == 2
    from registration._outline_field import INK_WEIGHT

    assert other.difference.max() == pytest.approx(
        other.distance - abs(other.ink_offset) / INK_WEIGHT)
    with pytest.raises(ValueError, match="reference"):
        compare_instances(shapes[0], np.zeros((5, 3)))


def test_a_counter_is_outside_the_ink_whether_closed_or_not():
    """口 closed, and with one side stopping short of (or just touching) the next: the
    counter's field is outside in every case, so ink spread closing a gap between two
    strokes moves an instance little (it used to fill the counter)."""
    from registration import compare_instances
    from registration._mould_distance import prepare_impression
    from registration._outline_field import grid_centres, outline_field

    box = [[0.2, 0.2, 0.8, 0.2], [0.2, 0.8, 0.8, 0.8], [0.2, 0.2, 0.2, 0.8]]

    def outline(right_end: float, n: int) -> np.ndarray:
        mould = draw_strokes([*box, [0.8, 0.2, 0.8, right_end]], size=160, width=0.08)
        return contour_points(np.where(mould, 0, 255).astype(np.uint8), n)

    centre = int(np.argmin(np.abs(grid_centres())))
    for n in (300, 800, 3000):
        for end in (0.8, 0.725, 0.7):  # closed, a neck, a gap of 3 pixels
            field = outline_field(prepare_impression(outline(end, n), name="s").points).field
            assert field[centre, centre] < 0, (n, end)
            assert field.max() > 0
        assert compare_instances(outline(0.8, n), outline(0.7, n)).distance < 0.08


def test_a_lone_instance_joins_its_nearest_group_of_three_within_reach():
    from registration._grouping import ATTACH_MIN_SIZE, _attach_lone

    assert ATTACH_MIN_SIZE == 3
    # instances 0-3 a group, 4-5 a pair, 6 near the group (0.12 on average), 7 near the
    # pair only, 8 far from everything, 9 and 10 near each other (both alone at the cut)
    n = 11
    D = np.full((n, n), 1.0)
    D[np.ix_(range(4), range(4))] = 0.05
    D[np.ix_([4, 5], [4, 5])] = 0.05
    D[6, :4] = D[:4, 6] = [0.1, 0.1, 0.14, 0.14]
    D[7, [4, 5]] = D[[4, 5], 7] = 0.1
    D[9, 10] = D[10, 9] = 0.1
    np.fill_diagonal(D, 0.0)
    labels = np.array([0, 0, 0, 0, 1, 1, 2, 3, 4, 5, 6])
    out = _attach_lone(D, labels, reach=0.15)
    assert list(out) == [0, 0, 0, 0, 1, 1, 0, 3, 4, 5, 6]
    assert list(_attach_lone(D, labels, reach=0.11)) == list(labels)  # mean 0.12 > 0.11
    assert list(_attach_lone(D, np.arange(n), reach=0.5)) == list(range(n))  # no group


def test_a_damaged_print_joins_its_mould():
    """Three moulds x 4 prints and a fifth print of the first with its last stroke short
    by 0.4 of a stroke width (a printing accident: one print, not a mould): farther from
    its mould than the cut on average, it joins that mould's group all the same."""
    moulds = [draw_strokes(s, size=160, width=0.08) for s in (A, B, C)]
    shapes, truth = prints(moulds, 4, seed=0)
    damaged = [list(s) for s in A]
    damaged[2] = [0.25, 0.55, 0.72, 0.55]  # the third stroke 0.03 of the size shorter
    shapes.append(contour_points(simulate_impressions(
        draw_strokes(damaged, size=160, width=0.08), 1, seed=5)[0]))
    res = group_instances(shapes)
    assert res.distances[-1, :4].mean() > res.threshold
    assert same_partition(res.labels, np.r_[truth, truth[0]])

"""The ``one-type`` family (bench/bench_groundtruth.py): prints of one type, each subject
one small warp of the root's shape, drawn independently: a star, not a chain."""

from __future__ import annotations

import numpy as np


def test_one_type_is_a_star_of_small_warps(bg, latin_font) -> None:
    cases = bg.one_type_cases([], "a", {"font": latin_font}, [0, 1])
    assert [c.label for c in cases] == ["one-type a font seed 0", "one-type a font seed 1"]
    for case in cases:
        assert case.kind == "one-type" and case.root == 0
        assert len(case.shapes) == bg.ONE_TYPE_SUBJECTS + 1
        # every subject one step from the root, none of them far
        assert case.depth == [0] + [1] * bg.ONE_TYPE_SUBJECTS
        assert all(d < case.far_from for d in case.distance)
        root = case.shapes[0]
        np.testing.assert_array_equal(case.truth[0], root)
        radius = np.sqrt(np.mean(np.sum((root - root.mean(0)) ** 2, axis=1)))
        for shape, truth in zip(case.shapes[1:], case.truth[1:], strict=True):
            # a small warp: the true images lie a few hundredths of the size from the root
            moved = np.sqrt(np.mean(np.sum((truth - root) ** 2, axis=1))) / radius
            assert 0.005 < moved < 3 * bg.ONE_TYPE_STEP
            assert not np.allclose(shape, root)  # its own sample of the warped glyph
    # the two seeds draw different prints
    assert not np.allclose(cases[0].truth[1], cases[1].truth[1])


def test_one_type_dense_is_the_same_star_at_full_size(bg, latin_font) -> None:
    cases = bg.dense_one_type_cases("a", {"font": latin_font}, [0])
    assert [c.label for c in cases] == ["one-type-dense a font seed 0"]
    (case,) = cases
    assert case.kind == "one-type-dense" and case.root == 0
    assert case.depth == [0] + [1] * bg.ONE_TYPE_SUBJECTS
    # above the library's working resolution: decided on subsamples, registered again on
    # the stored points
    assert all(len(s) == bg.DENSE_POINTS for s in case.shapes)
    assert bg.DENSE_POINTS > 400

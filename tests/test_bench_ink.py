"""The ``ink-spread`` family's ground truth (bench/bench_groundtruth.py).

Extra ink moves a glyph's outline along its normal, so a root point's true image on a
heavier print is that print's edge pixel nearest it, at the ink's width; points whose
nearest pixel lies elsewhere (strokes merged) have none. The family is only as good as
that construction, checked here on one Latin glyph in whichever font the machine has.
"""

from __future__ import annotations

import numpy as np


def test_ink_spread_truth(bg, latin_font) -> None:
    cases = bg.ink_spread_cases([0], "a", {"font": latin_font}, n_points=150)
    assert len(cases) == 1
    case = cases[0]
    widths = bg.INK_WIDTHS
    assert len(case.shapes) == len(widths) == len(case.truth)
    assert case.kind == "ink-spread" and case.root == 0 and case.far_from == 4
    assert all(len(s) == 150 for s in case.shapes)
    # the lightest print is the root: every point its own true image
    np.testing.assert_array_equal(case.truth[0], case.shapes[0])
    for w, shape, truth in zip(widths[1:], case.shapes[1:], case.truth[1:], strict=True):
        has = np.isfinite(truth).all(axis=1)
        assert has.mean() > 0.8  # 'a' keeps its counters open at 6 px
        moved = np.linalg.norm(truth[has] - case.shapes[0][has], axis=1)
        assert np.all(np.abs(moved - w) <= bg.INK_TRUTH_TOLERANCE)
        # the subject is its own sample of the heavier print's pixels, not the root moved
        assert not np.allclose(shape, case.shapes[0])

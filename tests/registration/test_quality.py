"""Checks that see what e (eq. 10) cannot: folds, slides, turns, uncovered parts."""

import numpy as np

from registration import AffineTransform, cpd_nonrigid, registration_error
from registration._quality import measure_quality
from registration.synthetic import base_outline


def _spacing2(p: np.ndarray) -> float:
    d = np.sqrt(((p[:, None] - p[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    return float(np.mean(d.min(axis=1) ** 2))


def test_identity_registration_is_perfect_on_every_check():
    x = base_outline(120)
    q = measure_quality(x, x, x, AffineTransform(A=np.eye(2), t=np.zeros(2)), 0.0, _spacing2(x))
    assert abs(q.min_jacobian - 1.0) < 1e-9 and q.distortion < 1e-9 and q.anisotropy < 1e-9
    assert abs(q.cpd_rotation) < 1e-9 and q.coverage == 1.0
    assert q.confidence > 0.9


def test_a_turn_that_lies_on_the_subject_keeps_e_small_but_loses_confidence():
    # a circle turned by 90 degrees lies on itself (small e) with every correspondence a
    # quarter of the way round: only the map's checks can see that
    x = base_outline(200)
    h2 = _spacing2(x)
    y = x @ np.diag([1.05, 0.95])
    good = cpd_nonrigid(x, y)
    q_good = measure_quality(x, good.warped, y, good.transform, registration_error(good.warped, y),
                             h2)
    # a rotated copy of the model lying on itself: small e, turned correspondences
    turn = np.array([[0.0, -1.0], [1.0, 0.0]])
    turned = AffineTransform(A=turn, t=np.zeros(2))
    circle = np.c_[np.cos(np.linspace(0, 2 * np.pi, 120, endpoint=False)),
                   np.sin(np.linspace(0, 2 * np.pi, 120, endpoint=False))]
    q_turned = measure_quality(circle, turned.apply(circle), circle, turned,
                               registration_error(turned.apply(circle), circle), _spacing2(circle))
    assert q_turned.error < 1e-3 and abs(q_turned.cpd_rotation) > 80
    assert q_turned.confidence < q_good.confidence


def test_folded_map_has_zero_confidence():
    x = base_outline(80)
    fold = AffineTransform(A=np.diag([1.0, -1.0]), t=np.zeros(2))
    q = measure_quality(x, fold.apply(x), fold.apply(x), fold, 0.0, _spacing2(x))
    assert q.min_jacobian < 0 and q.confidence == 0.0


def test_part_of_the_subject_left_uncovered_lowers_coverage():
    x = base_outline(200)
    half = x[:100]
    ident = AffineTransform(A=np.eye(2), t=np.zeros(2))
    q = measure_quality(half, half, x, ident, registration_error(half, x), _spacing2(x))
    assert 0.4 < q.coverage < 0.65


def test_the_checks_do_not_depend_on_how_densely_the_shapes_are_sampled():
    """The same smooth registration sampled at 300 and at 2400 points gets about the same
    checks and confidence: e / h^2 and the coverage within 2h would otherwise grow with
    the density (h shrinks, the tracing noise does not) and score every dense registration
    low."""
    from registration._quality import QUALITY_POINTS

    def warp(p: np.ndarray) -> np.ndarray:
        return p @ np.array([[1.05, 0.08], [-0.04, 0.97]]).T + 0.04 * np.sin(2.0 * p[:, ::-1])

    conf = {}
    rng = np.random.default_rng(0)
    for n in (300, 2400):
        x = base_outline(n)
        y = warp(base_outline(n + 7))  # another sampling of the same deformed outline,
        y += rng.normal(scale=0.01, size=y.shape)  # traced with a little noise
        reg = cpd_nonrigid(x, y)
        q = measure_quality(x, np.asarray(reg.warped), y, reg.transform,
                            registration_error(reg.warped, y), _spacing2(y))
        conf[n] = q.confidence
        assert q.coverage > 0.9
    assert conf[300] > 0.8
    assert abs(conf[2400] - conf[300]) < 0.1
    assert QUALITY_POINTS < 2400  # the dense case is the subsampled one


def test_spacing_distortion_is_zero_under_a_similarity_and_small_under_a_smooth_warp():
    """V compares each point's nearest-neighbour spacing after and before: a similarity
    scales every spacing alike (V = 0 whatever the scale), a smooth warp changes
    neighbouring spacings alike (V small), points pulled onto a coarser set of samples
    squeeze some spacings to nothing and open others (V large)."""
    from registration._quality import nearest_spacing, spacing_distortion

    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0, 2 * np.pi, 300))
    model = np.c_[np.cos(t), 0.6 * np.sin(t)]
    spacing = nearest_spacing(model)
    angle = 0.4
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    assert spacing_distortion(3.7 * model @ rot.T + [5.0, -2.0], spacing) < 1e-20
    smooth = model + 0.08 * np.c_[np.sin(2 * model[:, 1]), np.cos(3 * model[:, 0])]
    v_smooth = spacing_distortion(smooth, spacing)
    u = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    samples = np.c_[np.cos(u), 0.6 * np.sin(u)]  # the model's points snapped onto these
    snapped = samples[np.argmin(((model[:, None] - samples[None]) ** 2).sum(-1), axis=1)]
    v_snapped = spacing_distortion(snapped, spacing)
    assert v_smooth < 0.05 and v_snapped > 100 * v_smooth
    # coincident points keep V finite (spacings floored at 1e-12)
    assert np.isfinite(v_snapped)
    twice = np.r_[model, model[:5]]
    assert np.isfinite(spacing_distortion(twice, nearest_spacing(twice)))


def test_closed_form_singular_values_match_lapack() -> None:
    from registration._quality import singular_values_2x2

    rng = np.random.default_rng(4)
    J = rng.normal(size=(2000, 2, 2))
    J[:5] = np.eye(2)  # equal singular values
    J[5:10] = [[1.0, 2.0], [2.0, 4.0]]  # singular
    J[10:15] = [[0.0, 1.0], [-1.0, 0.0]]  # a rotation
    J[15:20] = [[-1.0, 0.0], [0.0, 1.0]]  # a reflection (a fold)
    J[20:25] *= 1e-9
    want = np.linalg.svd(J, compute_uv=False)
    s1, s2 = singular_values_2x2(J)
    np.testing.assert_allclose(s1, want[:, 0], rtol=1e-14)
    np.testing.assert_allclose(s2, want[:, 1], rtol=0, atol=1e-14 * want[:, 0].max())
    assert np.all(s1 >= s2) and np.all(s2 >= 0)


def _two_row_stroke(n: int = 217) -> np.ndarray:
    """A rendered straight stroke's skeleton: a run of pixels along one row, then the
    next (as the skeleton of 一 lies), centred."""
    x = np.arange(float(n))
    rows = ((np.arange(n) // 40) % 2).astype(float)
    p = np.c_[x, rows]
    return (p - p.mean(axis=0)) / 60.0


def test_points_across_a_stroke_drawn_alone_are_none_and_an_outline_has_them_everywhere():
    from registration._quality import points_across

    stroke = _two_row_stroke()
    assert not points_across(stroke).any()  # the second row of pixels is the same stroke
    # gently bent, still alone
    bent = np.c_[stroke[:, 0], stroke[:, 1] + 0.15 * np.sin(stroke[:, 0])]
    assert not points_across(bent).any()
    assert points_across(base_outline(200)).all()
    # a cross: every point of each bar has the other bar across it, but its far ends
    bar = np.linspace(-1.0, 1.0, 101)
    cross = np.r_[np.c_[bar, np.zeros_like(bar)], np.c_[np.zeros_like(bar), bar]]
    assert points_across(cross).mean() > 0.9
    assert points_across(stroke[:2]).tolist() == [False, False]


def test_a_flip_across_a_stroke_drawn_alone_is_no_fold_but_on_an_outline_it_is():
    """Across a stroke with nothing across it CPD's field is only its kernel's extension:
    a map that flips the plane across the stroke moves no point out of order. The stretch
    along the stroke stands in for the determinant there (a registration from the pose
    as given refused as folded, or on the spread of its log determinants, let one turned
    end for end win); on an outline the same flip folds."""
    flip = AffineTransform(A=np.diag([1.0, -1.0]), t=np.zeros(2))
    stroke = _two_row_stroke()
    q = measure_quality(stroke, flip.apply(stroke), flip.apply(stroke), flip, 0.0,
                        _spacing2(stroke))
    assert abs(q.min_jacobian - 1.0) < 1e-9 and q.distortion < 1e-9 and q.anisotropy == 0.0
    assert q.confidence > 0.5
    squash = AffineTransform(A=np.diag([0.5, -1.0]), t=np.zeros(2))
    q = measure_quality(stroke, squash.apply(stroke), squash.apply(stroke), squash, 0.0,
                        _spacing2(stroke))
    assert abs(q.min_jacobian - 0.5) < 1e-9  # the stretch along the stroke
    x = base_outline(120)
    q = measure_quality(x, flip.apply(x), flip.apply(x), flip, 0.0, _spacing2(x))
    assert q.min_jacobian == -1.0 and q.confidence == 0.0
    # a shape mostly not a lone stroke keeps the determinant everywhere, also on its
    # stroke: an outline with a tail (a quarter of its points)
    t = np.linspace(0.0, 2.0 * np.pi, 150, endpoint=False)
    tail = np.c_[np.linspace(1.2, 3.0, 50), np.zeros(50)]
    lollipop = np.r_[np.c_[np.cos(t), np.sin(t)], tail]
    from registration._quality import LONE_STROKE_SHARE, points_across

    assert 0.1 < np.mean(~points_across(lollipop)) < LONE_STROKE_SHARE
    q = measure_quality(lollipop, flip.apply(lollipop), flip.apply(lollipop), flip, 0.0,
                        _spacing2(lollipop))
    assert q.min_jacobian == -1.0

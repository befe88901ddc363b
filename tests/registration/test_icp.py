import numpy as np
import pytest

from registration import affine_icp, bidirectional_distance, fit_affine
from registration.synthetic import base_outline

from .test_pose import rotation


def test_eq8_recovers_exact_affine_from_pairs():
    rng = np.random.default_rng(0)
    r = rng.normal(size=(40, 2))
    A = np.array([[1.2, -0.4], [0.3, 0.7]])
    t = np.array([5.0, -2.0])
    A_hat, t_hat = fit_affine(r, r @ A.T + t)
    np.testing.assert_allclose(A_hat, A, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-12)


def test_eq8_hand_computed_least_squares():
    # r: unit square corners; s: the corners with one moved -> A, t by hand
    r = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    s = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 1.0], [2.0, 2.0]])
    # a = r - (0.5, 0.5); sum a a^T = I; b = s - (1, 0.75);
    # sum b a^T = [[2, 0], [0.5, 1.5]] (computed by hand from the four pairs)
    A_hat, t_hat = fit_affine(r, s)
    np.testing.assert_allclose(A_hat, [[2.0, 0.0], [0.5, 1.5]])
    np.testing.assert_allclose(t_hat, np.array([1.0, 0.75]) - A_hat @ [0.5, 0.5])


def test_eq8_degenerate_pairs_raise():
    r = np.c_[np.arange(5.0), np.arange(5.0)]  # collinear
    with pytest.raises(ValueError, match="degenerate"):
        fit_affine(r, r)


def test_eq9_hand_computed():
    tx = np.array([[0.0, 0.0], [3.0, 0.0]])
    y = np.array([[0.0, 1.0], [1.0, 0.0], [3.0, 0.5]])
    # forward: 0->y1 (or y0): 1 ; 1->y2: 0.25 ; mean 0.625
    # backward: y0->0: 1, y1->0: 1, y2->1: 0.25 ; mean 0.75
    assert bidirectional_distance(tx, y) == pytest.approx(0.625 + 0.75)


@pytest.mark.parametrize("angle", [0.0, 60.0, 90.0, 180.0, 250.0])
def test_affine_icp_recovers_known_affine_map(angle):
    rng = np.random.default_rng(3)
    x = base_outline(240)
    A = rotation(angle) @ np.array([[1.3, 0.25], [0.0, 0.8]])
    t = np.array([4.0, -7.0])
    y = (x @ A.T + t)[rng.permutation(len(x))]
    res = affine_icp(x, y)
    truth = x @ A.T + t
    # point-to-point ICP on a densely sampled curve can stop a fraction of a point
    # spacing away along the curve (a fixed point of nearest-neighbour matching): bound the
    # map's error by the subject's spacing; measured: 1.39 spacings at every angle
    spacing = np.linalg.norm(np.diff(truth, axis=0), axis=1).mean()
    rms = np.sqrt(((res.apply(x) - truth) ** 2).sum(axis=1).mean())
    assert rms < 1.5 * spacing
    assert res.distance < 0.5 * spacing**2
    assert np.linalg.det(res.A) == pytest.approx(np.linalg.det(A), rel=0.05)


def test_affine_icp_exact_on_a_point_cloud_with_180_degree_rotation():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(150, 2)) * [2.0, 0.7] + rng.normal(size=(150, 2)) * 0.05
    A = rotation(180.0) @ np.array([[0.9, 0.1], [0.0, 1.1]])
    y = (x @ A.T + [1.0, 2.0])[rng.permutation(150)]
    res = affine_icp(x, y, coarse_points=150)
    np.testing.assert_allclose(res.A, A, atol=1e-8)
    assert res.distance < 1e-12


def test_affine_icp_never_returns_a_singular_map_on_collinear_points():
    x = np.c_[np.linspace(0, 1, 20), np.zeros(20)]
    y = np.c_[np.zeros(20), np.linspace(0, 1, 20)] + 0.01
    res = affine_icp(x, y)
    assert np.isfinite(res.A).all() and np.isfinite(res.distance)
    assert abs(np.linalg.det(res.A)) > 1e-8


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_rotations": 0}, "n_rotations"),
        ({"max_iter": 0}, "max_iter"),
        ({"tol": 0.0}, "tol must be positive"),
        ({"init": (np.zeros((2, 2)), np.zeros(2))}, "singular"),
        ({"init": (np.eye(3), np.zeros(2))}, "init must be"),
    ],
)
def test_affine_icp_rejects_bad_options(kwargs, message):
    x = base_outline(30)
    with pytest.raises(ValueError, match=message):
        affine_icp(x, x, **kwargs)


def test_upright_starts_keep_the_pose_of_a_near_symmetric_shape():
    # an ellipse-like outline deformed on one side: every orientation search may prefer a
    # flipped pose; the upright search stays within +-max_rotation of the given pose
    x = base_outline(200)
    y = x.copy()
    y[:, 1] += 0.25 * np.exp(-((x[:, 0] - 0.5) ** 2) / 0.05)  # a bump, no rotation
    res = affine_icp(x, y, max_rotation=30.0)
    angle = np.degrees(np.arctan2(res.A[1, 0], res.A[0, 0]))
    assert abs(angle) <= 30.0 + 10.0
    assert np.linalg.det(res.A) > 0


def test_max_rotation_is_validated():
    x = base_outline(30)
    with pytest.raises(ValueError, match=r"max_rotation must be in \[0, 180\]"):
        affine_icp(x, x, max_rotation=200.0)


@pytest.mark.parametrize("n, m", [(1000, 1000), (1000, 1500), (37, 2000)])
def test_dense_full_distance_matches_kd_trees(n, m, monkeypatch):
    """The similarity's D on the full sets (blocked float32 products) is eq. 9 computed
    with KD-trees, to float32 rounding."""
    import registration._icp._pairwise as icp

    rng = np.random.default_rng(n + m)
    t = np.linspace(0, 2 * np.pi, max(n, m), endpoint=False)
    x = np.c_[np.cos(t), 0.5 * np.sin(t)][rng.permutation(t.size)[:n]]
    y = np.c_[np.cos(t), 0.6 * np.sin(t)][rng.permutation(t.size)[:m]] + 0.01 * rng.normal(
        size=(m, 2))
    px, py = icp.prepare_shape(x), icp.prepare_shape(y)
    A, tt = np.array([[1.02, 0.05], [-0.03, 0.97]]), np.array([0.01, -0.02])
    dense = icp._full_distance(px, py, A, tt)
    assert dense == pytest.approx(bidirectional_distance(x @ A.T + tt, y), abs=1e-6)
    monkeypatch.setattr(icp, "_DENSE_FULL_MAX", 0)
    assert icp._full_distance(px, py, A, tt) == pytest.approx(dense, abs=1e-6)


def test_fit_rigid_recovers_a_rotation_and_a_mirror_of_the_asked_handedness():
    from registration._icp._pairwise import fit_rigid

    rng = np.random.default_rng(4)
    r = rng.normal(size=(50, 2))
    a = np.deg2rad(130.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    R, t = fit_rigid(r, r @ rot.T + [0.3, -1.0])
    assert np.allclose(R, rot) and np.allclose(t, [0.3, -1.0])
    mirrored = r @ (rot @ np.diag([1.0, -1.0])).T
    M, _ = fit_rigid(r, mirrored, mirror=True)
    assert np.allclose(M, rot @ np.diag([1.0, -1.0]))
    # asked for a rotation, the mirror image gets the nearest one, never a reflection
    P, _ = fit_rigid(r, mirrored)
    assert np.linalg.det(P) > 0


def test_rigid_turns_finds_the_turn_of_a_turned_outline():
    from registration._icp import rigid_turns
    from registration._pose import rotation_angle

    outline = base_outline(200)
    outline = outline - outline.mean(axis=0)
    turned = outline @ rotation(130.0).T + [0.2, -0.1]
    R, t, D = rigid_turns(outline, turned)
    assert R.shape == (4, 2, 2) and t.shape == (4, 2) and D.shape == (4,)
    assert np.allclose(np.linalg.det(R), 1.0)  # rotations: no scale, no reflection
    best = int(np.argmin(D))
    assert abs(rotation_angle(R[best]) - 130.0) < 1.0
    assert np.allclose(t[best], [0.2, -0.1], atol=1e-2)
    assert D[best] < 1e-6 < D[0]  # start 0, the pose as given, stays in its own basin


def test_rigid_turns_rejects_no_starts():
    from registration._icp import rigid_turns

    with pytest.raises(ValueError, match="n_starts must be at least 1"):
        rigid_turns(np.eye(2), np.eye(2), n_starts=0)

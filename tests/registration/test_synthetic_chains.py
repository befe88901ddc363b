"""`registration.synthetic.deformation_chains`: chained smooth warps of a dense real shape
with exact ground truth for any root. Uses a generated dense outline (no ../shared)."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from registration import synthetic
from registration.synthetic import (
    DeformationFamily,
    base_outline,
    correspondence_error,
    deformation_chains,
)

DENSE = base_outline(2000) * 80.0 + np.array([300.0, -120.0])  # "pixel" coordinates


@pytest.fixture(scope="module")
def family() -> DeformationFamily:
    return deformation_chains(DENSE, n_chains=4, chain_length=6, n_points=400, seed=3)


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(((a - b) ** 2).sum(axis=1).mean()))


def test_layout_and_shapes(family: DeformationFamily) -> None:
    n = 1 + 4 * 6
    assert len(family.shapes) == len(family.indices) == len(family.names) == n
    assert all(s.shape == (400, 2) for s in family.shapes)
    assert family.depth == [0] + [1, 2, 3, 4, 5, 6] * 4
    assert family.chain == [-1] + [c for c in range(4) for _ in range(6)]
    assert family.parent[:3] == [None, 0, 1] and family.parent[7] == 0
    assert family.names[0] == "shape0" and family.names[8] == "chain2-step2"
    for idx in family.indices:
        assert np.all(np.diff(idx) > 0) and idx[0] >= 0 and idx[-1] < len(DENSE)
    # every shape is sampled independently: no two shapes use the same subset
    assert not np.array_equal(family.indices[0], family.indices[1])
    # shape k is its warp of the dense points it samples; shape 0 is undeformed
    np.testing.assert_array_equal(family.shapes[0], DENSE[family.indices[0]])
    k = 11
    np.testing.assert_allclose(family.shapes[k], family.warp(k, DENSE[family.indices[k]]),
                               atol=1e-9)


def test_deterministic_for_a_seed() -> None:
    a = deformation_chains(DENSE, n_chains=2, chain_length=3, n_points=100, seed=5)
    b = deformation_chains(DENSE, n_chains=2, chain_length=3, n_points=100, seed=5)
    c = deformation_chains(DENSE, n_chains=2, chain_length=3, n_points=100, seed=6)
    for x, y in zip(a.shapes, b.shapes, strict=True):
        np.testing.assert_array_equal(x, y)
    for x, y in zip(a.root_images(2), b.root_images(2), strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a.shapes[3], c.shapes[3])


def test_root_zero_truth_is_shape_zero_itself(family: DeformationFamily) -> None:
    truth = family.root_images(0)
    assert len(truth) == len(family.shapes)
    assert all(t.shape == (400, 2) for t in truth)
    np.testing.assert_array_equal(truth[0], family.shapes[0])
    assert correspondence_error(family.shapes[0], truth[0], family.shapes[0]) == 0.0


def test_other_roots(family: DeformationFamily) -> None:
    for r in (3, 14, 24):
        truth = family.root_images(r)
        np.testing.assert_array_equal(truth[r], family.shapes[r])
        dense_r = DENSE[family.indices[r]]
        np.testing.assert_array_equal(truth[0], dense_r)
        np.testing.assert_allclose(truth[9], family.warp(9, dense_r), atol=1e-9)


def test_deformation_grows_along_chains() -> None:
    fam = deformation_chains(DENSE, n_chains=8, chain_length=6, n_points=200, seed=1)
    truth = fam.root_images(0)
    size = float(np.sqrt(((DENSE - DENSE.mean(axis=0)) ** 2).sum(axis=1).mean()))
    by_depth = np.zeros(7)
    for k in range(1, len(fam.shapes)):
        by_depth[fam.depth[k]] += _rms(truth[k], truth[0]) / size / 8
    # one step moves points by about `step` (0.12) of the RMS radius, plus a small rotation
    assert 0.08 < by_depth[1] < 0.2
    assert by_depth[1] < by_depth[2] < by_depth[4] < by_depth[6]
    assert np.mean(np.diff(by_depth[1:])) > 0


def test_amplitude_is_relative_to_size() -> None:
    """Normalised internally: a similarity-transformed input gives the transformed family."""
    a = deformation_chains(DENSE, n_chains=1, chain_length=3, n_points=150, seed=2)
    b = deformation_chains(DENSE * 0.01 - 7.0, n_chains=1, chain_length=3, n_points=150, seed=2)
    for x, y in zip(a.shapes, b.shapes, strict=True):
        np.testing.assert_allclose(x * 0.01 - 7.0, y, atol=1e-9)


def test_warps_are_smooth_and_orientation_preserving(family: DeformationFamily) -> None:
    """Nearby dense points stay nearby, and the finite-difference Jacobian stays positive."""
    gaps = np.linalg.norm(np.diff(DENSE, axis=0), axis=1)
    h = 1e-3 * float(DENSE.std())
    for k in (6, 12, 18, 24):  # the ends of the chains: the largest composed warps
        img = family.dense_images[k]
        ratio = np.linalg.norm(np.diff(img, axis=0), axis=1) / gaps
        assert ratio.min() > 0.2 and ratio.max() < 5.0
        p = DENSE[::20]
        ex, ey = np.array([h, 0.0]), np.array([0.0, h])
        dx = (family.warp(k, p + ex) - family.warp(k, p - ex)) / (2 * h)
        dy = (family.warp(k, p + ey) - family.warp(k, p - ey)) / (2 * h)
        det = dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]
        assert det.min() > 0.0


def test_each_step_jacobian_above_floor() -> None:
    fam = deformation_chains(DENSE, n_chains=2, chain_length=4, n_points=100, seed=9)
    for k in range(1, len(fam.shapes)):
        before = fam.dense_images[fam.parent[k] or 0]
        st = fam._steps[k][-1]
        u = (before - fam._center) / fam._scale
        assert st.jacobian_det(u).min() > synthetic.MIN_STEP_JACOBIAN


def test_fewer_dense_points_than_requested_uses_them_all() -> None:
    dense = base_outline(60)
    fam = deformation_chains(dense, n_chains=1, chain_length=2, n_points=400, seed=0)
    assert all(s.shape == (60, 2) for s in fam.shapes)
    assert all(np.array_equal(i, np.arange(60)) for i in fam.indices)


def test_even_sampling_takes_evenly_spaced_dense_points_from_a_random_start() -> None:
    """sampling="even": every n/k-th dense point (an ordered outline sampled evenly, as
    outlines are digitised), each shape from its own start; the truth still holds."""
    fam = deformation_chains(DENSE, n_chains=2, chain_length=3, n_points=100, seed=4,
                             sampling="even")
    starts = set()
    for idx, shape, img in zip(fam.indices, fam.shapes, fam.dense_images, strict=True):
        gaps = np.diff(np.r_[idx, idx[0] + len(DENSE)])
        assert len(idx) == 100 and set(gaps) <= {20}  # 2000 dense points / 100
        np.testing.assert_array_equal(shape, img[idx])
        starts.add(int(idx[0]))
    assert len(starts) > 1, "every shape sampled from the same start"
    truth = fam.root_images(0)
    np.testing.assert_allclose(truth[0], fam.shapes[0])
    random = deformation_chains(DENSE, n_chains=2, chain_length=3, n_points=100, seed=4)
    assert any(len(set(np.diff(i))) > 1 for i in random.indices)


def _gap_spread(shape: np.ndarray) -> float:
    """Coefficient of variation of the gaps between successive points of a closed outline."""
    gaps = np.linalg.norm(np.roll(shape, -1, axis=0) - shape, axis=1)
    return float(gaps.std() / gaps.mean())


def test_arclength_sampling_is_even_along_each_deformed_shape() -> None:
    """sampling="arclength": each shape's points evenly spaced along its own outline as it
    is (the warp leaves no trace in the spacing, unlike "even", which keeps the undeformed
    shape's index spacing), distinct and in order, from a phase of each shape's own; the
    truth still holds."""
    fam = deformation_chains(DENSE, n_chains=2, chain_length=3, n_points=100, seed=4,
                             sampling="arclength")
    even = deformation_chains(DENSE, n_chains=2, chain_length=3, n_points=100, seed=4,
                              sampling="even")
    dense_gap = float(np.linalg.norm(np.diff(DENSE, axis=0), axis=1).max())
    for idx, shape, img in zip(fam.indices, fam.shapes, fam.dense_images, strict=True):
        assert len(idx) == 100 and np.all(np.diff(idx) > 0)
        np.testing.assert_array_equal(shape, img[idx])
        gaps = np.linalg.norm(np.roll(shape, -1, axis=0) - shape, axis=1)
        # within about one deformed dense gap of the even step (the warps of this family
        # stretch a dense gap to at most 1.4x its undeformed length)
        assert np.all(np.abs(gaps - gaps.mean()) <= 2.5 * dense_gap), shape
    assert max(_gap_spread(s) for s in fam.shapes) < 0.05
    assert min(_gap_spread(s) for s in even.shapes[1:]) > 0.2
    assert len({int(i[0]) for i in fam.indices}) > 1, "every shape sampled from one phase"
    np.testing.assert_allclose(fam.root_images(0)[0], fam.shapes[0])
    # a dense outline with fewer points than asked keeps all of them
    small = deformation_chains(base_outline(60), n_chains=1, chain_length=1, n_points=400,
                               seed=0, sampling="arclength")
    assert all(np.array_equal(i, np.arange(60)) for i in small.indices)
    # nearly as many points as dense ones: two steps nearest one dense point still get two
    tight = deformation_chains(base_outline(110), n_chains=1, chain_length=2, n_points=100,
                               seed=1, sampling="arclength")
    assert all(len(i) == 100 and np.all(np.diff(i) > 0) and i[-1] < 110 for i in tight.indices)


@pytest.mark.parametrize(
    ("dense", "kwargs", "match"),
    [
        (np.zeros((10, 3)), {}, r"shape \(n, 2\)"),
        (np.r_[DENSE[:50], [[np.nan, 0.0]]], {}, "non-finite"),
        (np.ones((20, 2)), {}, "zero size"),
        (DENSE[:2], {}, "at least 3 points"),
        (DENSE, {"n_chains": 0}, "n_chains must be at least 1"),
        (DENSE, {"chain_length": 0}, "chain_length must be at least 1"),
        (DENSE, {"n_points": 2}, "n_points must be at least 3"),
        (DENSE, {"n_chains": 1.5}, "n_chains must be an integer"),
        (DENSE, {"step": -0.1}, "step must be a finite non-negative number"),
        (DENSE, {"step": float("nan")}, "step must be a finite non-negative number"),
        (DENSE, {"rotation_deg": float("inf")}, "rotation_deg must be"),
        (DENSE, {"shear": 1.0}, "shear must be below 1"),
        (DENSE, {"sampling": "grid"}, "sampling must be 'random', 'even' or 'arclength'"),
        (DENSE, {"step": 5.0}, "Jacobian determinant"),
    ],
)
def test_bad_inputs_raise(dense: np.ndarray, kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        deformation_chains(dense, **{"n_chains": 1, "chain_length": 1, "n_points": 50,
                                     **kwargs})  # type: ignore[arg-type]


def test_bad_root_and_shape_index(family: DeformationFamily) -> None:
    for bad in (-1, len(family.shapes), 1.0, True):
        with pytest.raises(ValueError, match="root must be an integer index"):
            family.root_images(bad)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="shape must be an integer index"):
            family.warp(bad, DENSE[:3])  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"shape \(n, 2\)"):
        family.warp(1, np.zeros((4, 3)))


@pytest.mark.parametrize("fn", [deformation_chains, DeformationFamily.root_images,
                                DeformationFamily.warp])
def test_numpydoc(fn: object) -> None:
    doc = inspect.getdoc(fn) or ""
    for section in ("Parameters\n----------", "Returns\n-------", "Raises\n------"):
        assert section in doc
    params = [p for p in inspect.signature(fn).parameters if p != "self"]  # type: ignore[arg-type]
    for p in params:
        assert p in doc, p

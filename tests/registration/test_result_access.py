"""The library's result: the root's identity transform, the inverse map, the similarity D,
and one key scheme for transform steps."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from registration import (
    AffineTransform,
    ChainTransform,
    build_dynamic_tree,
    cpd_nonrigid,
    register_direct,
)
from registration._inverse import invert_points
from registration._transform import _step_from_dict
from registration.synthetic import chained_family


@pytest.fixture(scope="module")
def tree():  # type: ignore[no-untyped-def]
    fam = chained_family(n_chains=2, chain_length=3, n_points=50, seed=3)
    return fam, build_dynamic_tree(fam.shapes, root=0)


def test_the_root_is_a_subject_with_the_identity(tree) -> None:  # type: ignore[no-untyped-def]
    fam, result = tree
    root = result.subject(0)
    assert root.attached and root.layer == 1 and root.path == [0] and root.error == 0.0
    t = result.transform_for(0)
    assert t.steps == () and t.path == (0,)
    assert np.allclose(t.apply(fam.shapes[0]), fam.shapes[0], rtol=0, atol=1e-12)
    assert t.source == result.subjects[0].transform.source  # the root's normalisation
    assert [s.index for s in result.subjects] == list(range(1, len(fam.shapes)))
    with pytest.raises(KeyError):
        result.subject(99)


def test_the_result_keeps_the_similarity_it_computed(tree) -> None:  # type: ignore[no-untyped-def]
    fam, result = tree
    D = result.similarity
    assert D is not None and D.shape == (len(fam.shapes),) * 2
    assert np.allclose(np.diag(D), 0.0)
    for s in result.subjects:
        if s.attached:
            assert D[s.parent, s.index] == s.similarity
    assert "similarity" not in result.to_dict()  # n x n: not in the document
    direct = register_direct(fam.shapes[:3], root=0)
    assert direct.similarity is not None and direct.similarity.shape == (3, 3)


def test_the_chain_inverse_maps_the_subject_back(tree) -> None:  # type: ignore[no-untyped-def]
    fam, result = tree
    model = fam.shapes[0]
    for s in result.subjects:
        t = s.transform
        onto = t.apply(model)
        back = t.apply_inverse(onto)
        assert np.abs(back - model).max() < 1e-8 * t.source.scale
        # any point of the subject's region, not only the model's images
        y = fam.shapes[s.index]
        z = t.apply_inverse(y)
        assert np.isfinite(z).all()
        assert np.abs(t.apply(z) - y).max() < 1e-8 * t.target.scale


def test_the_cpd_warp_inverse_accuracy() -> None:
    rng = np.random.default_rng(0)
    angle = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    model = np.c_[np.cos(angle), 0.6 * np.sin(angle)]
    subject = model + 0.08 * np.c_[np.sin(3 * angle), np.cos(2 * angle)]
    subject += rng.normal(scale=0.005, size=subject.shape)
    warp = cpd_nonrigid(model, subject).transform
    grid = np.stack(np.meshgrid(np.linspace(-1.2, 1.2, 15), np.linspace(-0.8, 0.8, 11)), -1)
    z, residual = invert_points(warp, grid.reshape(-1, 2))
    assert residual.max() < 1e-11
    assert np.abs(warp.apply(z) - grid.reshape(-1, 2)).max() < 1e-11


def test_a_point_without_preimage_is_nan() -> None:
    flat = AffineTransform(A=np.array([[1.0, 0.0], [0.0, 0.0]]), t=np.zeros(2))  # onto y = 0
    from registration import Normalization

    unit = Normalization(center=(0.0, 0.0), scale=1.0)
    chain = ChainTransform(source=unit, target=unit, steps=(flat,), path=(0, 1))
    out = chain.apply_inverse([[2.0, 0.0], [2.0, 1.0]])
    assert np.allclose(out[0], [2.0, 0.0]) or np.isfinite(out[0]).all()
    assert np.isnan(out[1]).all()
    with pytest.raises(ValueError, match="shape"):
        chain.apply_inverse([1.0, 2.0])
    with pytest.raises(ValueError, match="finite"):
        invert_points(flat, [[np.nan, 0.0]])


def test_every_step_has_one_key_scheme(tree) -> None:  # type: ignore[no-untyped-def]
    _, result = tree
    affine = AffineTransform(A=np.eye(2) * 2, t=np.array([1.0, 0.0]))
    steps = [affine.to_dict()] + [
        st for s in result.subjects for st in s.transform.to_dict()["steps"]
    ]
    kinds = {"affine": "affine", "nonrigid": "cpd_nonrigid"}
    for d in steps:
        assert {"type", "kind", "version"} <= set(d)
        assert kinds[d["type"]] == d["kind"]
    # steps stored before the scheme (affine without kind, nonrigid without type) still read
    old_affine = {"type": "affine", "A": [[1, 0], [0, 1]], "t": [0, 0]}
    assert isinstance(_step_from_dict(old_affine), AffineTransform)
    old_nonrigid = {k: v for k, v in steps[-1].items() if k != "type"}
    assert type(_step_from_dict(old_nonrigid)).__name__ == "NonrigidTransform"


def test_inverting_points_too_far_for_finite_distances_keeps_the_first_result():
    # a fuzzer's point at 1e233 stalls and is too far from every restart seed for a finite
    # distance: the KD-tree answers "no neighbour" (index n), which used to be indexed
    class Blows:
        def apply(self, p):
            p = np.asarray(p, dtype=np.float64)
            out = 1.1 * p
            out[np.abs(p).max(axis=1) > 1e100] = np.inf
            return out

    seeds = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the blown-up point is handled, not warned about
        z, residual = invert_points(Blows(), [[3.3e233, 4e16], [0.55, 1.1]], seeds=seeds)
    assert residual[0] == np.inf and residual[1] < 1e-9
    np.testing.assert_allclose(z[1], [0.5, 1.0])


def test_a_stalled_point_does_not_keep_the_others_from_converging() -> None:
    """A point the damped step cannot bring closer (no preimage) stops being iterated;
    the other points still converge."""

    class Fold:
        """(x, y) -> (x, y^2): no preimage below the x axis."""

        def apply(self, p):
            p = np.asarray(p, dtype=np.float64)
            return np.c_[p[:, 0], p[:, 1] ** 2]

    z, residual = invert_points(Fold(), [[0.5, -1.0], [0.3, 0.25]])
    assert residual[0] >= 1.0 - 1e-9  # the nearest it can get: y = 0
    assert residual[1] < 1e-11 and np.allclose(np.abs(z[1]), [0.3, 0.5])
    assert np.isfinite(z).all()


def test_a_map_with_its_own_jacobian_is_evaluated_once_per_newton_trial() -> None:
    """A CPD warp gives its Jacobian with its image: the Newton iterations take both from
    one evaluation of each trial point (plain ``apply`` only for the start), the trials
    of an iteration in at most two evaluations, and reach the same preimages as central
    differences of ``apply`` alone."""
    angle = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    model = np.c_[np.cos(angle), 0.6 * np.sin(angle)]
    subject = model + 0.08 * np.c_[np.sin(3 * angle), np.cos(2 * angle)]
    warp = cpd_nonrigid(model, subject).transform
    points = np.stack(np.meshgrid(np.linspace(-1.2, 1.2, 9), np.linspace(-0.8, 0.8, 7)),
                      -1).reshape(-1, 2)
    calls = {"apply": 0, "apply_with_jacobian": 0, "evaluations": 0}

    class Counting:
        def apply(self, p):
            calls["apply"] += len(p)
            return warp.apply(p)

        def apply_with_jacobian(self, p):
            calls["apply_with_jacobian"] += len(p)
            calls["evaluations"] += 1
            return warp.apply_with_jacobian(p)

    class ImageOnly:
        def apply(self, p):
            return warp.apply(p)

    z, residual = invert_points(Counting(), points)
    assert residual.max() < 1e-11
    assert calls["apply"] == len(points)  # the start, 2 y - f(y)
    # one evaluation of the starts, then per Newton iteration one of every active point's
    # step and one of the halved steps of those it did not improve, all together (up to
    # eleven trials a point): a few evaluations, each of at most a few trials a point
    assert calls["evaluations"] <= 1 + 2 * 8
    assert len(points) < calls["apply_with_jacobian"] < 16 * len(points)
    z_cd, residual_cd = invert_points(ImageOnly(), points)
    assert residual_cd.max() < 1e-11
    np.testing.assert_allclose(z, z_cd, atol=1e-10)

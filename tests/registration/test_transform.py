"""AffineTransform and jacobian_determinants (registration/_transform.py, _pointmap.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from registration import AffineTransform, ChainTransform, jacobian_determinants
from registration._points import normalise

RNG = np.random.default_rng(7)
POINTS = RNG.normal(size=(25, 2))


def _affine(A: list[list[float]], t: list[float]) -> AffineTransform:
    return AffineTransform(A=np.asarray(A, dtype=float), t=np.asarray(t, dtype=float))


def _inverse(f: AffineTransform) -> AffineTransform:
    inv = np.linalg.inv(f.A)
    return AffineTransform(A=inv, t=-inv @ f.t)


def test_apply_is_a_x_plus_t() -> None:
    f = _affine([[2.0, 1.0], [0.0, 3.0]], [1.0, -1.0])
    np.testing.assert_allclose(f.apply([[1.0, 1.0], [0.0, 0.0]]), [[4.0, 2.0], [1.0, -1.0]])


def test_compose_then_inverse_is_the_identity() -> None:
    f = _affine([[1.2, -0.4], [0.3, 0.9]], [0.5, -2.0])
    g = _affine([[0.0, -1.0], [1.0, 0.0]], [3.0, 0.25])
    np.testing.assert_allclose(_inverse(f).apply(f.apply(POINTS)), POINTS, atol=1e-12)
    # g after f is the affine map (A_g A_f, A_g t_f + t_g)
    composed = _affine((g.A @ f.A).tolist(), (g.A @ f.t + g.t).tolist())
    np.testing.assert_allclose(g.apply(f.apply(POINTS)), composed.apply(POINTS), atol=1e-12)
    # a chain applies its steps in order, and the inverse steps undo it
    identity = normalise(POINTS)[1]
    chain = ChainTransform(source=identity, target=identity, steps=(f, g), path=(0, 1, 2))
    back = ChainTransform(
        source=identity, target=identity, steps=(_inverse(g), _inverse(f)), path=(2, 1, 0)
    )
    np.testing.assert_allclose(back.apply(chain.apply(POINTS)), POINTS, atol=1e-9)


def test_serialised_round_trip_through_json() -> None:
    f = _affine([[1.2, -0.4], [0.3, 0.9]], [0.5, -2.0])
    d = json.loads(json.dumps(f.to_dict()))
    assert d["type"] == "affine"
    g = AffineTransform.from_dict(d)
    np.testing.assert_array_equal(g.A, f.A)
    np.testing.assert_array_equal(g.t, f.t)
    np.testing.assert_array_equal(g.apply(POINTS), f.apply(POINTS))


def test_jacobian_determinant_of_an_affine_map_is_det_a_everywhere() -> None:
    f = _affine([[1.5, 0.7], [-0.2, 0.8]], [4.0, -3.0])
    det = jacobian_determinants(f, POINTS)
    assert det.shape == (len(POINTS),)
    np.testing.assert_allclose(det, 1.5 * 0.8 - 0.7 * -0.2, rtol=1e-9)
    mirror = _affine([[-1.0, 0.0], [0.0, 1.0]], [0.0, 0.0])
    np.testing.assert_allclose(jacobian_determinants(mirror, POINTS), -1.0, rtol=1e-9)


def test_jacobian_determinant_of_a_nonlinear_map() -> None:
    class Square:
        """(x, y) -> (x^2, y): det = 2x, which folds the plane at x = 0."""

        def apply(self, p: np.ndarray) -> np.ndarray:
            p = np.asarray(p, dtype=float)
            return np.c_[p[:, 0] ** 2, p[:, 1]]

        def to_dict(self) -> dict[str, str]:
            return {}

    det = jacobian_determinants(Square(), POINTS)
    np.testing.assert_allclose(det, 2 * POINTS[:, 0], atol=1e-6)
    assert ((det <= 0) == (POINTS[:, 0] <= 0)).all()


def test_jacobian_determinants_refuse_bad_input() -> None:
    f = _affine([[1.0, 0.0], [0.0, 1.0]], [0.0, 0.0])
    with pytest.raises(ValueError, match="h must be positive"):
        jacobian_determinants(f, POINTS, h=0.0)
    with pytest.raises(ValueError, match="points"):
        jacobian_determinants(f, [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="points"):
        jacobian_determinants(f, [[0.0, np.nan]])


def test_exact_jacobians_match_central_differences() -> None:
    """The CPD field, an affine map and chains of them give their Jacobians exactly (one
    kernel pass instead of four); central differences of step 1e-4 agree to ~1e-7."""
    from registration import cpd_nonrigid
    from registration._pointmap import central_differences, jacobian_matrices
    from registration._points import Normalization

    t = np.linspace(0.0, 2.0 * np.pi, 120, endpoint=False)
    model = np.c_[3.0 * np.cos(t), 2.0 * np.sin(2.0 * t)] + [5.0, -1.0]
    subject = model * 1.1 + 0.3 * np.sin(model[:, ::-1]) + [0.5, 0.3]
    field = cpd_nonrigid(model, subject, max_iter=40).transform
    f = _affine([[1.2, 0.3], [-0.1, 0.9]], [1.0, 2.0])
    chain = ChainTransform(source=Normalization(center=(1.0, 2.0), scale=3.0),
                           target=Normalization(center=(0.0, 1.0), scale=0.5),
                           steps=(f, field), path=(0, 1))
    at = model + RNG.normal(scale=0.3, size=model.shape)
    for transform in (field, f, chain):
        exact = jacobian_matrices(transform, at)
        np.testing.assert_allclose(exact, central_differences(transform, at), atol=1e-6)
    out, _ = chain.apply_with_jacobian(at)
    np.testing.assert_allclose(out, chain.apply(at), atol=1e-12)
    # a displacement that is not the identity: the check would pass on any I otherwise
    assert np.abs(jacobian_matrices(field, at) - np.eye(2) * field.subject_scale
                  / field.model_scale).max() > 0.05


@pytest.fixture(scope="module")
def chained_result():
    from registration import CPDOptions, SerialExecutor, build_dynamic_tree
    from registration.synthetic import chained_family

    fam = chained_family(n_chains=2, chain_length=4, n_points=60, seed=3)
    res = build_dynamic_tree(fam.shapes, 0, cpd=CPDOptions(max_iter=40),
                             executor=SerialExecutor())
    return fam.shapes[0], res


def test_shared_steps_expand_to_the_whole_chains(chained_result) -> None:
    """to_dict(shared_steps=True): a subject's transform keeps the steps after those it
    shares with its parent's and names them in ``base``; expand_shared_steps gives back
    exactly to_dict()'s transform, which maps the root onto the warped model."""
    from registration import expand_shared_steps

    model, result = chained_result
    whole = result.to_dict()
    shared = result.to_dict(shared_steps=True)
    by_index = {s["index"]: s["transform"] for s in shared["subjects"]}
    based = [s for s in shared["subjects"] if s["transform"] and "base" in s["transform"]]
    assert based, "no subject below layer 2 in a chained family of depth 4"
    for s in based:
        assert s["transform"]["base"]["index"] == s["parent"]
        assert len(s["transform"]["steps"]) < len(result.subject(s["index"]).transform.steps)
    for w, s in zip(whole["subjects"], shared["subjects"], strict=True):
        if s["transform"] is None:
            assert w["transform"] is None
            continue
        expanded = expand_shared_steps(s["transform"], by_index.get)
        assert json.dumps(expanded) == json.dumps(w["transform"])
        np.testing.assert_allclose(ChainTransform.from_dict(expanded).apply(model),
                                   result.subject(s["index"]).warped, atol=1e-8)
    assert len(json.dumps(shared)) < len(json.dumps(whole))


def test_a_transform_with_a_base_is_not_read_as_a_whole_chain(chained_result) -> None:
    from registration import expand_shared_steps

    _, result = chained_result
    shared = result.to_dict(shared_steps=True)
    t = next(s["transform"] for s in shared["subjects"]
             if s["transform"] and "base" in s["transform"])
    by_index = {s["index"]: s["transform"] for s in shared["subjects"]}
    with pytest.raises(ValueError, match="expand_shared_steps"):
        ChainTransform.from_dict(t)
    with pytest.raises(ValueError, match="has no transform"):
        expand_shared_steps(t, lambda index: None)
    too_many = {**t, "base": {**t["base"], "steps": 10_000}}
    with pytest.raises(ValueError, match="refers to 10000 steps"):
        expand_shared_steps(too_many, by_index.get)
    loop = {**t, "base": {"index": 7, "steps": 1}}
    with pytest.raises(ValueError, match="loop"):
        expand_shared_steps(loop, lambda index: loop)
    with pytest.raises(ValueError, match="not a transform base"):
        expand_shared_steps({**t, "base": {"steps": 1}}, by_index.get)
    with pytest.raises(ValueError, match="base steps must be"):
        result.subjects[0].transform.to_dict(base=(0, 10_000))

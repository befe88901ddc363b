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

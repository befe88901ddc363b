"""Candidate pairs of a large collection: the descriptor's invariance, the k nearest, and a
tree that only computes (and chooses parents among) the allowed pairs."""

from __future__ import annotations

import numpy as np
import pytest

from registration import CPDOptions, SerialExecutor, build_dynamic_tree, normalise
from registration._candidates import candidate_pairs, shape_descriptor
from registration.synthetic import chained_family


def _outline(seed: int = 0, n: int = 200) -> np.ndarray:
    return chained_family(n_chains=1, chain_length=1, n_points=n, seed=seed).shapes[0]


@pytest.mark.parametrize(
    "A",
    [
        np.array([[0.0, -1.0], [1.0, 0.0]]),  # a quarter turn
        np.array([[-1.0, 0.0], [0.0, 1.0]]),  # a mirror
        np.array([[2.0, 0.7], [0.1, 0.5]]),  # an affine map with shear
    ],
    ids=["rotation", "mirror", "affine"],
)
def test_descriptor_is_invariant_to_affine_maps(A: np.ndarray) -> None:
    p = normalise(_outline())[0]
    q = normalise(p @ A.T + [3.0, -2.0])[0]
    np.testing.assert_allclose(shape_descriptor(q), shape_descriptor(p), atol=1e-9)


def test_descriptor_tells_different_shapes_apart() -> None:
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    star = np.c_[np.cos(t), np.sin(t)] * (1 + 0.3 * np.cos(5 * t))[:, None]
    a = shape_descriptor(normalise(_outline())[0])
    b = shape_descriptor(normalise(star)[0])
    same = shape_descriptor(normalise(_outline()[::-1])[0])  # point order does not matter
    assert np.linalg.norm(a - same) < 1e-9 < np.linalg.norm(a - b)


def test_candidate_pairs_join_each_shape_to_its_k_nearest_both_ways() -> None:
    fam = chained_family(n_chains=3, chain_length=6, n_points=80, seed=2)
    normed = [normalise(s)[0] for s in fam.shapes]
    pairs = candidate_pairs(normed, 3)
    assert pairs == sorted(set(pairs))
    assert all((j, i) in set(pairs) for i, j in pairs)
    out = {i: {j for a, j in pairs if a == i} for i in range(len(normed))}
    assert all(len(v) >= 3 for v in out.values())
    assert len(pairs) <= 2 * 3 * len(normed)
    # the nearest by descriptor, by brute force
    desc = np.stack([shape_descriptor(p) for p in normed])
    for i in range(len(normed)):
        d = np.linalg.norm(desc - desc[i], axis=1)
        d[i] = np.inf
        assert int(np.argmin(d)) in out[i]


def test_candidate_pairs_bad_k() -> None:
    with pytest.raises(ValueError, match="k must be at least 1"):
        candidate_pairs([np.zeros((3, 2))], 0)
    assert candidate_pairs([np.eye(2)], 3) == []


def test_tree_with_candidates_uses_only_allowed_pairs() -> None:
    fam = chained_family(n_chains=3, chain_length=4, n_points=50, seed=4)
    shapes = fam.shapes
    normed = [normalise(s)[0] for s in shapes]
    allowed = set(candidate_pairs(normed, 3)) | {(0, s) for s in range(1, len(shapes))}
    res = build_dynamic_tree(shapes, root=0, candidates=3, executor=SerialExecutor(),
                             cpd=CPDOptions(max_iter=30))
    computed = {(int(i), int(j)) for i, j in zip(*np.nonzero(np.isfinite(res.similarity)),
                                                  strict=True) if i != j}
    assert computed <= allowed
    for s in res.subjects:
        assert s.parent is not None
        assert (s.parent, s.index) in allowed

"""Generated shape families with known correspondences, for tests, demos and benchmarks.

A *chained-deformation family* starts from a closed, fish-like outline (the root) and
grows chains of shapes, each a small smooth deformation of the previous one. Neighbours
in a chain are similar, while the ends of a chain differ from the root by a large
deformation: exactly the situation the dynamic tree of Du et al. 2016 is built for. Each
shape's points are shuffled and posed by a random similarity transform, and the ground
truth (which point of a shape is the image of each root point) is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ._points import normalise

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

__all__ = ["ShapeFamily", "base_outline", "chained_family", "correspondence_error"]


@dataclass(frozen=True)
class ShapeFamily:
    """A generated family of shapes with ground-truth correspondences.

    Attributes
    ----------
    shapes : list of ndarray, shape (n, 2)
        The shapes in "user" coordinates (posed, shuffled). ``shapes[0]`` is the root.
    gt_index : list of ndarray of int, shape (n,)
        ``shapes[k][gt_index[k][i]]`` is the image of root point ``shapes[0][gt_index[0][i]]``.
    generation_parent : list of int or None
        The shape each one was deformed from (None for the root).
    depth : list of int
        Number of deformation steps from the root.
    names : list of str
    """

    shapes: list[FloatArray]
    gt_index: list[IntArray]
    generation_parent: list[int | None]
    depth: list[int]
    names: list[str]

    def to_npz_dict(self) -> dict[str, FloatArray]:
        return dict(zip(self.names, self.shapes, strict=True))


def base_outline(n_points: int = 200) -> FloatArray:
    """A closed, asymmetric fish-like outline (body, fins, forked tail), ordered, no repeats."""
    t = np.linspace(0.0, 2.0 * np.pi, n_points, endpoint=False)
    x = np.cos(t) + 0.15 * np.cos(2 * t)
    y = 0.42 * np.sin(t) * (1.0 + 0.35 * np.cos(t)) + 0.08 * np.sin(3 * t)
    # a dorsal fin on top and a smaller ventral fin below break the mirror symmetry,
    # so that correspondences are unambiguous (as on real fish)
    y += 0.30 * np.exp(-(((t - 1.35) / 0.22) ** 2)) - 0.12 * np.exp(-(((t - 4.3) / 0.15) ** 2))
    # a forked tail on the left: pull the points near t = pi outwards
    tail = np.exp(-(((t - np.pi) / 0.35) ** 2))
    x -= 0.45 * tail
    y += 0.55 * tail * np.sin(4.0 * (t - np.pi))
    return np.c_[x, y]


def _smooth_warp(p: FloatArray, rng: np.random.Generator, strength: float) -> FloatArray:
    """A smooth random deformation: a bend, a taper and two Gaussian bumps."""
    x, y = p[:, 0], p[:, 1]
    bend = strength * rng.uniform(-1.0, 1.0)
    taper = 0.5 * strength * rng.uniform(-1.0, 1.0)
    out = np.c_[x, y + bend * (x**2 - 0.5)]
    out[:, 1] *= 1.0 + taper * x
    for _ in range(2):
        c = rng.uniform(-1.0, 1.0, size=2) * [1.0, 0.4]
        v = rng.normal(size=2)
        v *= strength * 0.35 / max(float(np.linalg.norm(v)), 1e-9)
        w = np.exp(-((p - c) ** 2).sum(axis=1) / (2 * 0.35**2))
        out += w[:, None] * v
    return out


def chained_family(
    *,
    n_chains: int = 3,
    chain_length: int = 5,
    n_points: int = 200,
    step: float = 0.35,
    pose: bool = True,
    noise: float = 0.0,
    seed: int = 0,
) -> ShapeFamily:
    """Generate a root outline and `n_chains` chains of progressively deformed copies.

    Parameters
    ----------
    n_chains : int
        Number of chains leaving the root.
    chain_length : int
        Shapes per chain; shape ``k`` of a chain is ``k`` deformation steps from the root.
    n_points : int
        Points per shape.
    step : float
        Strength of each deformation step (about the displacement, relative to the
        shape's half-length, that one step produces).
    pose : bool
        Give every shape a random rotation (up to 30 degrees), scale and translation, as
        real collections are not aligned.
    noise : float
        Standard deviation of Gaussian jitter added to each point, relative to size.
    seed : int

    Returns
    -------
    ShapeFamily
    """
    if n_chains < 1 or chain_length < 1:
        raise ValueError("n_chains and chain_length must be at least 1")
    if n_points < 10:
        raise ValueError(f"n_points must be at least 10; got {n_points}")
    rng = np.random.default_rng(seed)
    root = base_outline(n_points)
    clean: list[FloatArray] = [root]
    parents: list[int | None] = [None]
    depth = [0]
    names = ["root"]
    for c in range(n_chains):
        prev_idx = 0
        for k in range(1, chain_length + 1):
            clean.append(_smooth_warp(clean[prev_idx], rng, step))
            parents.append(prev_idx)
            depth.append(k)
            names.append(f"chain{c + 1}-step{k}")
            prev_idx = len(clean) - 1
    shapes: list[FloatArray] = []
    gt: list[IntArray] = []
    for p in clean:
        q = p + noise * rng.normal(size=p.shape) if noise > 0 else p.copy()
        if pose:
            a = np.deg2rad(rng.uniform(-30.0, 30.0))
            rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            q = (q @ rot.T) * rng.uniform(50.0, 150.0) + rng.uniform(-500.0, 500.0, size=2)
        perm = rng.permutation(n_points)
        shapes.append(q[perm])
        gt.append(np.argsort(perm).astype(np.intp))  # shapes[k][gt[k][i]] == q[i]
    return ShapeFamily(shapes=shapes, gt_index=gt, generation_parent=parents, depth=depth,
                       names=names)


def correspondence_error(
    warped_model: FloatArray, subject: FloatArray, gt_model: IntArray, gt_subject: IntArray
) -> float:
    """Root-mean-square ground-truth correspondence error on the subject's normalised scale.

    ``warped_model[gt_model[i]]`` should land on ``subject[gt_subject[i]]``; both arrays are
    in the subject's user coordinates, and the error is divided by the subject's RMS
    radius so it is comparable across shapes.
    """
    _, norm = normalise(subject)
    diff = warped_model[gt_model] - subject[gt_subject]
    return float(np.sqrt((diff**2).sum(axis=1).mean()) / norm.scale)

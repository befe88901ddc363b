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

__all__ = ["ShapeFamily", "base_outline", "chained_family", "correspondence_error"]


@dataclass(frozen=True)
class ShapeFamily:
    """A generated family of shapes with ground-truth correspondences.

    Attributes
    ----------
    shapes : list of ndarray, shape (n_k, 2)
        The shapes in "user" coordinates (posed, shuffled). ``shapes[0]`` is the root.
    root_images : list of ndarray, shape (n_0, 2)
        ``root_images[k][i]`` is where root point ``shapes[0][i]`` lies on shape ``k``
        (in shape k's coordinates): the ground truth for a registration of the root onto
        shape ``k``. With ``resample=True`` it is generally not one of shape k's points.
    outline_order : list of ndarray of int
        ``shapes[k][outline_order[k]]`` walks along shape k's outline.
    generation_parent : list of int or None
        The shape each one was deformed from (None for the root).
    depth : list of int
        Number of deformation steps from the root.
    names : list of str
    """

    shapes: list[FloatArray]
    root_images: list[FloatArray]
    outline_order: list[NDArray[np.intp]]
    generation_parent: list[int | None]
    depth: list[int]
    names: list[str]

    def to_npz_dict(self) -> dict[str, FloatArray]:
        return dict(zip(self.names, self.shapes, strict=True))


def _outline_at(t: FloatArray) -> FloatArray:
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


def base_outline(n_points: int = 200) -> FloatArray:
    """A closed, asymmetric fish-like outline (body, fins, forked tail), ordered, no repeats."""
    return _outline_at(np.linspace(0.0, 2.0 * np.pi, n_points, endpoint=False))


@dataclass(frozen=True)
class _Warp:
    """A smooth deformation: a bend, a taper and two Gaussian bumps."""

    bend: float
    taper: float
    centres: FloatArray
    vectors: FloatArray

    @classmethod
    def random(cls, rng: np.random.Generator, strength: float, trend: _Warp) -> _Warp:
        """A step that continues `trend` (a chain's direction) with random magnitudes,
        so that deformations accumulate along a chain instead of cancelling."""
        mag = rng.uniform(0.5, 1.0, size=4)
        jitter = rng.normal(scale=0.15, size=(2, 2))
        return cls(
            bend=strength * mag[0] * trend.bend,
            taper=0.5 * strength * mag[1] * trend.taper,
            centres=trend.centres + jitter * [1.0, 0.4],
            vectors=trend.vectors * (strength * 0.35 * mag[2:, None]),
        )

    @classmethod
    def trend(cls, rng: np.random.Generator) -> _Warp:
        """A chain's direction: signs of bend and taper, bump centres and directions."""
        vectors = rng.normal(size=(2, 2))
        vectors /= np.maximum(np.linalg.norm(vectors, axis=1), 1e-9)[:, None]
        return cls(
            bend=float(rng.choice([-1.0, 1.0])),
            taper=float(rng.choice([-1.0, 1.0])),
            centres=rng.uniform(-1.0, 1.0, size=(2, 2)) * [1.0, 0.4],
            vectors=vectors,
        )

    def apply(self, p: FloatArray) -> FloatArray:
        x, y = p[:, 0], p[:, 1]
        out = np.c_[x, y + self.bend * (x**2 - 0.5)]
        out[:, 1] *= 1.0 + self.taper * x
        for c, v in zip(self.centres, self.vectors, strict=True):
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
    resample: bool = True,
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
        shape's half-length, that one step produces). The steps of a chain continue in
        one direction (same sense of bending, tapering and bulging, random magnitudes),
        so the deformation from the root grows along the chain.
    pose : bool
        Give every shape a random rotation (up to 30 degrees), scale and translation, as
        real collections are not aligned.
    noise : float
        Standard deviation of Gaussian jitter added to each point, relative to size.
    resample : bool
        Sample every shape's outline at its own positions (a random phase along the
        outline), as independently digitised shapes are; with False every shape's points
        are the images of the root's points (exact point-to-point correspondence).
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
    t_root = np.linspace(0.0, 2.0 * np.pi, n_points, endpoint=False)
    chains: list[list[_Warp]] = [[]]
    parents: list[int | None] = [None]
    depth = [0]
    names = ["root"]
    for c in range(n_chains):
        prev_idx = 0
        trend = _Warp.trend(rng)
        for k in range(1, chain_length + 1):
            chains.append([*chains[prev_idx], _Warp.random(rng, step, trend)])
            parents.append(prev_idx)
            depth.append(k)
            names.append(f"chain{c + 1}-step{k}")
            prev_idx = len(chains) - 1
    shapes: list[FloatArray] = []
    truths: list[FloatArray] = []
    perms: list[NDArray[np.intp]] = []
    for k, warps in enumerate(chains):
        t = t_root
        if resample and k > 0:
            t = t_root + rng.uniform(0.0, 2.0 * np.pi / n_points)
        clean, truth = _outline_at(t), _outline_at(t_root)
        for warp in warps:
            clean, truth = warp.apply(clean), warp.apply(truth)
        if noise > 0:
            clean = clean + noise * rng.normal(size=clean.shape)
        if pose:
            a = np.deg2rad(rng.uniform(-30.0, 30.0))
            rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            scale = rng.uniform(50.0, 150.0)
            shift = rng.uniform(-500.0, 500.0, size=2)
            clean = (clean @ rot.T) * scale + shift
            truth = (truth @ rot.T) * scale + shift
        perm = rng.permutation(n_points)
        shapes.append(clean[perm])
        truths.append(truth)
        perms.append(perm)
    # root row r is outline parameter t_root[perms[0][r]]: index the truths the same way
    root_images = [tr[perms[0]] for tr in truths]
    outline_order = [np.argsort(p).astype(np.intp) for p in perms]
    return ShapeFamily(shapes=shapes, root_images=root_images, outline_order=outline_order,
                       generation_parent=parents,
                       depth=depth, names=names)


def correspondence_error(warped_model: FloatArray, truth: FloatArray, subject: FloatArray) -> float:
    """Root-mean-square ground-truth correspondence error on the subject's normalised scale.

    ``warped_model[i]`` should land on ``truth[i]``; both are in the subject's user
    coordinates, and the error is divided by the subject's RMS radius (`subject` is only
    used for that scale) so it is comparable across shapes.
    """
    _, norm = normalise(subject)
    diff = np.asarray(warped_model) - np.asarray(truth)
    return float(np.sqrt((diff**2).sum(axis=1).mean()) / norm.scale)

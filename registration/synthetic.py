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
from numpy.typing import ArrayLike, NDArray

from ._points import as_points, normalise

FloatArray = NDArray[np.float64]

__all__ = [
    "DeformationFamily",
    "ShapeFamily",
    "base_outline",
    "chained_family",
    "correspondence_error",
    "deformation_chains",
]


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


# ----------------------------------------------------------------------------- real shapes

#: Smallest Jacobian determinant a warp step may have on the shape's points.
MIN_STEP_JACOBIAN = 0.2
#: Gaussian width of the RBF displacement bumps, relative to the shape's RMS radius.
RBF_WIDTH = 0.5
_MAX_STEP_ATTEMPTS = 200
#: How :func:`deformation_chains` may sample each shape's points off its dense points.
SAMPLINGS = ("random", "even", "arclength")


@dataclass(frozen=True)
class _RBFStep:
    """One warp step in normalised coordinates: ``x -> pivot + A (x + d(x) - pivot)``,
    with ``d`` a sum of Gaussian bumps (width `sigma`) at `centres` with `vectors`."""

    centres: FloatArray
    vectors: FloatArray
    sigma: float
    A: FloatArray
    pivot: FloatArray

    def _weights(self, p: FloatArray) -> FloatArray:
        d2 = ((p[:, None, :] - self.centres[None, :, :]) ** 2).sum(axis=2)
        return np.exp(-d2 / (2.0 * self.sigma**2))

    def displacement(self, p: FloatArray) -> FloatArray:
        return self._weights(p) @ self.vectors

    def apply(self, p: FloatArray) -> FloatArray:
        moved = p + self.displacement(p)
        return self.pivot + (moved - self.pivot) @ self.A.T

    def jacobian_det(self, p: FloatArray) -> FloatArray:
        w = self._weights(p)  # (n, m)
        rel = p[:, None, :] - self.centres[None, :, :]  # (n, m, 2)
        # grad d[a] / d x[b] = sum_j v_j[a] * w_j * (-(x - c_j)[b] / sigma^2)
        grad = -np.einsum("nm,ma,nmb->nab", w, self.vectors, rel) / self.sigma**2
        jac = np.eye(2)[None, :, :] + grad
        return np.linalg.det(jac) * float(np.linalg.det(self.A))


def _random_step(
    rng: np.random.Generator,
    p: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    step: float,
    rotation_deg: float,
    shear: float,
) -> _RBFStep:
    """A random step for the (normalised) current shape `p`, its Jacobian checked on `p`."""
    for _ in range(_MAX_STEP_ATTEMPTS):
        m = int(rng.integers(6, 11))
        centres = rng.uniform(lo, hi, size=(m, 2))
        vectors = rng.normal(size=(m, 2))
        a = np.deg2rad(rng.uniform(-rotation_deg, rotation_deg))
        s = rng.uniform(-shear, shear)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        A = rot @ np.array([[1.0, s], [0.0, 1.0]])
        trial = _RBFStep(centres=centres, vectors=vectors, sigma=RBF_WIDTH, A=A,
                         pivot=p.mean(axis=0))
        rms = float(np.sqrt((trial.displacement(p) ** 2).sum(axis=1).mean()))
        if rms <= 1e-12:
            continue
        cand = _RBFStep(centres=centres, vectors=vectors * (step / rms), sigma=RBF_WIDTH,
                        A=A, pivot=trial.pivot)
        if float(cand.jacobian_det(p).min()) > MIN_STEP_JACOBIAN:
            return cand
    raise ValueError(
        f"could not draw a warp step with Jacobian determinant > {MIN_STEP_JACOBIAN} on the "
        f"shape in {_MAX_STEP_ATTEMPTS} attempts: step={step}, rotation_deg={rotation_deg}, "
        f"shear={shear} are too large"
    )


def _check_index(name: str, value: object, n: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not 0 <= value < n:
        raise ValueError(f"{name} must be an integer index into shapes (0..{n - 1}); got {value!r}")


@dataclass(frozen=True)
class DeformationFamily:
    """Chains of smooth random deformations of one dense shape, with exact ground truth.

    Made by :func:`deformation_chains`. Shape ``k`` is the composed warp ``warp_k`` of
    the dense shape, sampled at its own random subset ``indices[k]`` of the dense points:
    ``shapes[k] == warp_k(dense[indices[k]])``. Every coordinate is in the user's
    coordinate system (that of the dense points given).

    Attributes
    ----------
    shapes : list of ndarray, shape (n_k, 2)
        ``shapes[0]`` is the undeformed shape (warp_0 is the identity).
    indices : list of ndarray of int, shape (n_k,)
        Which dense points each shape samples (sorted, without repeats).
    depth : list of int
        Warp steps from the undeformed shape (0 for shape 0, ``s`` for step ``s``).
    chain : list of int
        Chain of each shape (0-based), -1 for shape 0.
    parent : list of int or None
        The shape each was deformed from (None for shape 0).
    names : list of str
        ``"shape0"`` and ``"chain<c>-step<s>"`` (1-based c and s).
    dense : ndarray, shape (n, 2)
        The undeformed dense points, as given.
    dense_images : list of ndarray, shape (n, 2)
        ``warp_k(dense)`` for every shape ``k``.
    """

    shapes: list[FloatArray]
    indices: list[NDArray[np.intp]]
    depth: list[int]
    chain: list[int]
    parent: list[int | None]
    names: list[str]
    dense: FloatArray
    dense_images: list[FloatArray]
    _center: FloatArray
    _scale: float
    _steps: list[tuple[_RBFStep, ...]]

    def root_images(self, root: int) -> list[FloatArray]:
        """Ground truth for registering shape `root` onto every shape of the family.

        Parameters
        ----------
        root : int
            Index of the model shape.

        Returns
        -------
        list of ndarray, shape (n_root, 2)
            Entry ``k`` holds, for each point ``i`` of ``shapes[root]``, its true image on
            shape ``k``: ``warp_k(dense[indices[root][i]])``. Entry ``root`` equals
            ``shapes[root]``.

        Raises
        ------
        ValueError
            If `root` is not an index into `shapes`.
        """
        _check_index("root", root, len(self.shapes))
        idx = self.indices[int(root)]
        return [img[idx] for img in self.dense_images]

    def warp(self, shape: int, points: ArrayLike) -> FloatArray:
        """Apply shape `shape`'s composed warp to arbitrary points.

        Parameters
        ----------
        shape : int
            Index of a shape of the family.
        points : array_like, shape (m, 2)
            Points in the user's coordinates (those of the undeformed shape).

        Returns
        -------
        ndarray, shape (m, 2)
            ``warp_shape(points)`` in the user's coordinates.

        Raises
        ------
        ValueError
            If `shape` is not an index into `shapes` or `points` is not a finite
            (m, 2) array.
        """
        _check_index("shape", shape, len(self.shapes))
        p = as_points(points, name="points", min_points=1)
        u = (p - self._center) / self._scale
        for st in self._steps[int(shape)]:
            u = st.apply(u)
        return u * self._scale + self._center


def _arclength_indices(outline: FloatArray, n_points: int, phase: float) -> NDArray[np.intp]:
    """Indices of the dense points of the closed `outline` (in order along it) nearest to
    `n_points` even steps of its length, the first `phase` (in [0, 1)) of a step in;
    sorted and distinct (a dense point nearest two steps is taken once, the next free one
    along the outline for the other)."""
    n = len(outline)
    seg = np.linalg.norm(np.roll(outline, -1, axis=0) - outline, axis=1)
    cum = np.r_[0.0, np.cumsum(seg)]  # cum[k]: length from point 0 to point k (cum[n]: all)
    total = float(cum[-1])
    targets = (phase + np.arange(n_points)) * (total / n_points)
    k = np.clip(np.searchsorted(cum, targets), 1, n)
    nearer_before = (targets - cum[k - 1]) <= (cum[k] - targets)
    idx = np.where(nearer_before, k - 1, k) % n
    taken: set[int] = set()
    for j, i in enumerate(idx):  # in order along the outline: a repeat moves on by one
        while int(i) in taken:
            i = (i + 1) % n
        taken.add(int(i))
        idx[j] = i
    return np.sort(idx).astype(np.intp)


def deformation_chains(
    dense_points: ArrayLike,
    *,
    n_chains: int = 4,
    chain_length: int = 6,
    n_points: int = 400,
    step: float = 0.12,
    rotation_deg: float = 3.0,
    shear: float = 0.03,
    seed: int = 0,
    sampling: str = "random",
) -> DeformationFamily:
    """Chains of composed random smooth warps of a real shape, each shape sampled anew.

    Shape 0 is the undeformed shape. Each of `n_chains` chains has `chain_length` shapes;
    shape ``s`` of a chain is ``step_s o ... o step_1`` applied to the dense points, where
    every step is a random Gaussian-RBF displacement field (6-10 centres uniform over the
    shape's bounding box, width 0.5 x the RMS radius, scaled so that its RMS displacement
    over the current shape is `step` x the RMS radius) followed by a random rotation
    (uniform in +-`rotation_deg`) and shear (uniform in +-`shear`) about the current
    shape's centroid. A step is redrawn until its Jacobian determinant exceeds 0.2 at
    every dense point, so every warp is a diffeomorphism on the shape. Every shape,
    shape 0 included, samples its own `n_points` dense points (a random subset, or evenly
    from a random start: see `sampling`; sorted indices, no repeats; all points when there
    are fewer), so no two shapes share points (but by chance).
    Nothing is posed or shuffled otherwise.

    Parameters
    ----------
    dense_points : array_like, shape (n, 2)
        A densely sampled real shape (edge pixels, a skeleton, a contour) in any
        coordinates; the shapes are returned in these coordinates.
    n_chains : int
        Number of chains leaving shape 0, at least 1.
    chain_length : int
        Shapes per chain (warp steps), at least 1.
    n_points : int
        Points sampled for each shape, at least 3.
    step : float
        RMS displacement of one RBF step, relative to the shape's RMS radius (size
        about the centroid); non-negative.
    rotation_deg : float
        Largest rotation of one step, in degrees; non-negative.
    shear : float
        Largest shear of one step; in [0, 1).
    seed : int
        Seed of the random generator: equal arguments give equal families.
    sampling : {"random", "even", "arclength"}
        How each shape picks its `n_points` dense points: a random subset (for unordered
        points such as edge pixels); every ``n / n_points``-th point from a random start
        ("even": evenly along an outline whose dense points are in order along it, in the
        undeformed shape's spacing, which the warps stretch, so the sampling density
        follows the deformation); or, from a random start, the dense point nearest each of
        `n_points` even steps of the shape's own closed outline length ("arclength":
        evenly along each deformed shape as it is, as an outline digitised anew on every
        shape; the sampling then says nothing of the warp).

    Returns
    -------
    DeformationFamily
        ``1 + n_chains * chain_length`` shapes; ground truth for any root from
        :meth:`DeformationFamily.root_images`.

    Raises
    ------
    ValueError
        If `dense_points` is not a finite (n, 2) array of at least 3 points or has zero
        size, if a count or amplitude is out of range, or if no step with a positive
        enough Jacobian can be drawn (amplitudes far too large).
    """
    p, norm = normalise(dense_points, name="dense_points")
    for label, value in (("n_chains", n_chains), ("chain_length", chain_length),
                         ("n_points", n_points), ("seed", seed)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"{label} must be an integer; got {value!r}")
    if n_chains < 1:
        raise ValueError(f"n_chains must be at least 1; got {n_chains}")
    if chain_length < 1:
        raise ValueError(f"chain_length must be at least 1; got {chain_length}")
    if n_points < 3:
        raise ValueError(f"n_points must be at least 3; got {n_points}")
    for label, amount in (("step", step), ("rotation_deg", rotation_deg), ("shear", shear)):
        if isinstance(amount, bool) or not isinstance(amount, int | float | np.number):
            raise ValueError(f"{label} must be a number; got {amount!r}")
        if not (np.isfinite(amount) and amount >= 0):
            raise ValueError(f"{label} must be a finite non-negative number; got {amount!r}")
    if shear >= 1:
        raise ValueError(f"shear must be below 1; got {shear}")
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be 'random', 'even' or 'arclength'; got {sampling!r}")
    rng = np.random.default_rng(seed)
    lo, hi = p.min(axis=0), p.max(axis=0)
    steps: list[tuple[_RBFStep, ...]] = [()]
    images: list[FloatArray] = [p]
    depth, chain, names = [0], [-1], ["shape0"]
    parent: list[int | None] = [None]
    for c in range(n_chains):
        prev = 0
        for s in range(1, chain_length + 1):
            st = _random_step(rng, images[prev], lo, hi, float(step), float(rotation_deg),
                              float(shear))
            steps.append((*steps[prev], st))
            images.append(st.apply(images[prev]))
            depth.append(s)
            chain.append(c)
            names.append(f"chain{c + 1}-step{s}")
            parent.append(prev)
            prev = len(images) - 1
    n_dense = p.shape[0]
    center, scale = np.asarray(norm.center), norm.scale
    dense_images = [img * scale + center for img in images]
    dense_images[0] = as_points(dense_points, name="dense_points").copy()
    indices: list[NDArray[np.intp]] = []
    shapes: list[FloatArray] = []
    for img in dense_images:
        if n_dense <= n_points:
            idx = np.arange(n_dense, dtype=np.intp)
        elif sampling == "even":
            start = int(rng.integers(n_dense))
            idx = np.sort((start + (np.arange(n_points) * n_dense) // n_points) % n_dense)
            idx = idx.astype(np.intp)
        elif sampling == "arclength":
            idx = _arclength_indices(img, n_points, float(rng.random()))
        else:
            idx = np.sort(rng.choice(n_dense, size=n_points, replace=False)).astype(np.intp)
        indices.append(idx)
        shapes.append(img[idx])
    return DeformationFamily(
        shapes=shapes, indices=indices, depth=depth, chain=chain, parent=parent, names=names,
        dense=dense_images[0], dense_images=dense_images, _center=center, _scale=scale,
        _steps=steps,
    )

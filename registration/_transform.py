"""Transforms that map the root model onto a subject, composable along a tree path."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._points import Normalization, as_points

FloatArray = NDArray[np.float64]

__all__ = ["AffineTransform", "ChainTransform", "PointTransform", "jacobian_determinants"]


class PointTransform(Protocol):
    """Anything that maps (n, 2) points to (n, 2) points and serialises to JSON."""

    def apply(self, points: ArrayLike) -> FloatArray: ...

    def to_dict(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class AffineTransform:
    """``x -> A x + t``."""

    A: FloatArray
    t: FloatArray

    def apply(self, points: ArrayLike) -> FloatArray:
        p = np.asarray(points, dtype=np.float64)
        return p @ self.A.T + self.t

    def apply_with_jacobian(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """The mapped points and the Jacobian matrices there (all ``A``): (K, 2, 2)."""
        p = self.apply(points)
        return p, np.broadcast_to(np.asarray(self.A, dtype=np.float64), (len(p), 2, 2)).copy()

    def to_dict(self) -> dict[str, Any]:
        return {
            "type": "affine",
            "kind": "affine",
            "version": 1,
            "A": self.A.tolist(),
            "t": self.t.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AffineTransform:
        return cls(A=np.asarray(d["A"], dtype=np.float64), t=np.asarray(d["t"], dtype=np.float64))


#: A step's ``kind`` (what wrote it) -> its ``type`` (what it is): every serialised step
#: carries ``type``, ``kind`` and ``version``.
STEP_TYPES = {"affine": "affine", "cpd_nonrigid": "nonrigid"}


def _step_from_dict(d: dict[str, Any]) -> PointTransform:
    kind = d.get("type") or STEP_TYPES.get(str(d.get("kind")))
    if kind == "affine":
        return AffineTransform.from_dict(d)
    if kind == "nonrigid":
        from ._cpd import NonrigidTransform

        return NonrigidTransform.from_dict(d)
    raise ValueError(f"unknown transform step type {kind!r}")


def _step_to_dict(step: PointTransform) -> dict[str, Any]:
    d = dict(step.to_dict())
    d.setdefault("type", STEP_TYPES.get(str(d.get("kind")), "nonrigid"))
    return d


@dataclass(frozen=True)
class ChainTransform:
    """The map from the root model onto a subject along its tree path.

    ``apply`` takes points in the root model's user coordinates, normalises them with the
    root's normalisation, applies every step (in size-normalised coordinates: for each
    tree edge an affine pre-alignment then a CPD non-rigid warp), and returns them in the
    subject's user coordinates.

    Attributes
    ----------
    source : Normalization
        The root model's normalisation.
    target : Normalization
        The subject's normalisation.
    steps : tuple of PointTransform
    path : tuple of int
        Shape indices from the root to the subject.
    """

    source: Normalization
    target: Normalization
    steps: tuple[PointTransform, ...]
    path: tuple[int, ...]

    def __repr__(self) -> str:
        from ._repr import chain_repr

        return chain_repr(self)

    def apply_normalised(self, points: ArrayLike) -> FloatArray:
        """Apply the steps to points already in normalised coordinates."""
        p = np.asarray(points, dtype=np.float64)
        for step in self.steps:
            p = step.apply(p)
        return p

    def apply(self, points: ArrayLike) -> FloatArray:
        """Map points from the root model's user coordinates onto the subject's."""
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must have shape (n, 2); got {p.shape}")
        if not np.isfinite(p).all():
            raise ValueError("points must be finite")
        return self.target.invert(self.apply_normalised(self.source.apply(p)))

    def apply_inverse(self, points: ArrayLike, *, tol: float = 1e-6) -> FloatArray:
        """Map points from the subject's user coordinates back onto the root model's.

        Each step is inverted numerically (:func:`registration._inverse.invert_points`:
        Newton iterations; an affine step exactly). A point whose preimage was not found to
        ``tol`` times the subject's size (forward-mapping the answer must land that close to
        the point; typically it lands within 1e-12) is NaN: e.g. far outside the region the
        warp was fitted on, or where it folds.
        """
        from ._inverse import invert_points

        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must have shape (n, 2); got {p.shape}")
        if not np.isfinite(p).all():
            raise ValueError("points must be finite")
        z = self.target.apply(p)
        for step in reversed(self.steps):
            z, _ = invert_points(step, z)
        out = self.source.invert(z)
        with np.errstate(invalid="ignore", over="ignore"):
            miss = np.linalg.norm(self.apply(out) - p, axis=1)
        out[~(miss <= tol * self.target.scale)] = np.nan
        return out

    def apply_with_jacobian(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """:meth:`apply` and the map's Jacobian matrices at `points` (K, 2, 2): exact
        (chain rule over the steps) when every step gives its own, else central
        differences."""
        p = np.asarray(points, dtype=np.float64)
        both = composed_with_jacobian(self.steps, self.source.apply(p))
        if both is None:
            return self.apply(p), _central_differences(self, p)
        z, jac = both
        return self.target.invert(z), jac * (self.target.scale / self.source.scale)

    @classmethod
    def identity(cls, normalization: Normalization, node: int) -> ChainTransform:
        """The root model's own transform: no steps, from and to its normalisation."""
        return cls(source=normalization, target=normalization, steps=(), path=(node,))

    def extended(
        self, steps: tuple[PointTransform, ...], target: Normalization, node: int
    ) -> ChainTransform:
        return ChainTransform(
            source=self.source, target=target, steps=self.steps + steps, path=(*self.path, node)
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source.to_dict(),
            "target": self.target.to_dict(),
            "path": list(self.path),
            "steps": [_step_to_dict(s) for s in self.steps],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ChainTransform:
        try:
            return cls(
                source=Normalization.from_dict(d["source"]),
                target=Normalization.from_dict(d["target"]),
                steps=tuple(_step_from_dict(s) for s in d["steps"]),
                path=tuple(int(k) for k in d["path"]),
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"not a serialised ChainTransform: {exc}") from None


def jacobian_determinants(
    transform: PointTransform, points: ArrayLike, *, h: float = 1e-4
) -> FloatArray:
    """Determinant of the Jacobian of `transform` at each point (central differences).

    A non-positive value means the map folds (or collapses) the plane there.

    Parameters
    ----------
    transform : object with ``apply(points) -> points``
        Any of the library's transforms (affine, CPD non-rigid, chain).
    points : array_like, shape (n, 2)
        Where to evaluate, in the transform's input coordinates.
    h : float
        Step of the central differences.

    Returns
    -------
    ndarray, shape (n,)

    Raises
    ------
    ValueError
        If `points` is not a finite (n, 2) array or `h` is not positive.
    """
    if not h > 0:
        raise ValueError(f"h must be positive; got {h}")
    J = jacobian_matrices(transform, as_points(points, name="points", min_points=1), h=h)
    return J[:, 0, 0] * J[:, 1, 1] - J[:, 1, 0] * J[:, 0, 1]


def composed_with_jacobian(steps: tuple[PointTransform, ...], points: ArrayLike
                           ) -> tuple[FloatArray, FloatArray] | None:
    """`steps` applied one after the other, and the Jacobians of the whole map (chain
    rule), when every step gives its own (``apply_with_jacobian``); else None."""
    if not all(hasattr(s, "apply_with_jacobian") for s in steps):
        return None
    p = np.asarray(points, dtype=np.float64)
    jac = np.broadcast_to(np.eye(2), (len(p), 2, 2)).copy()
    for step in steps:
        p, j = step.apply_with_jacobian(p)  # type: ignore[attr-defined]
        jac = j @ jac
    return p, jac


def jacobian_matrices(transform: PointTransform, points: FloatArray, *, h: float = 1e-4
                      ) -> FloatArray:
    """Jacobian matrices, shape (n, 2, 2), of `transform` at (n, 2) `points`:
    ``J[k, a, b] = d out_a / d x_b`` (no input checks: internal). Exact when the transform
    gives its own (``apply_with_jacobian``: the library's affine, CPD and composed maps),
    else by central differences of step `h`."""
    exact = getattr(transform, "apply_with_jacobian", None)
    if exact is not None:
        out: FloatArray = exact(points)[1]
        return out
    return _central_differences(transform, points, h)


def _central_differences(transform: PointTransform, points: FloatArray, h: float = 1e-4
                         ) -> FloatArray:
    ex = np.array([h, 0.0])
    ey = np.array([0.0, h])
    out = transform.apply(np.concatenate([points + ex, points - ex, points + ey, points - ey]))
    n = points.shape[0]
    dx = (out[:n] - out[n : 2 * n]) / (2 * h)  # d out / dx
    dy = (out[2 * n : 3 * n] - out[3 * n :]) / (2 * h)  # d out / dy
    return np.stack([dx, dy], axis=2)

"""Transforms that map the root model onto a subject, composable along a tree path."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._cpd import NonrigidTransform
from ._inverse import invert_points
from ._pointmap import PointTransform, central_differences, composed_with_jacobian
from ._points import Normalization

FloatArray = NDArray[np.float64]

__all__ = ["AffineTransform", "ChainTransform", "expand_shared_steps"]


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

    def __repr__(self) -> str:  # short: the steps' arrays are not printed, runs counted
        runs: list[list[Any]] = []
        for step in self.steps:
            name = type(step).__name__
            if runs and runs[-1][0] == name:
                runs[-1][1] += 1
            else:
                runs.append([name, 1])
        kinds = ", ".join(name if k == 1 else f"{k} x {name}" for name, k in runs)
        return f"ChainTransform(path={self.path}, steps=[{kinds or 'identity'}])"

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
            return self.apply(p), central_differences(self, p)
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

    def to_dict(self, *, base: tuple[int, int] | None = None) -> dict[str, Any]:
        """The chain as JSON-ready data.

        ``base=(index, k)``: the first ``k`` steps are written as a reference to those of
        subject ``index``'s chain (``"base": {"index": index, "steps": k}``) and only the
        steps after them in ``steps``; :func:`expand_shared_steps` puts them back. A tree
        subject's chain starts with its parent's, so a deep subject's document would
        otherwise repeat every step of every ancestor (three quarters of a full result's
        bytes on the 73 永 glyphs).
        """
        k = 0 if base is None else base[1]
        if not 0 <= k <= len(self.steps):
            raise ValueError(f"base steps must be between 0 and {len(self.steps)}; got {k}")
        d: dict[str, Any] = {
            "source": self.source.to_dict(),
            "target": self.target.to_dict(),
            "path": list(self.path),
            "steps": [_step_to_dict(s) for s in self.steps[k:]],
        }
        if base is not None and k > 0:
            d["base"] = {"index": int(base[0]), "steps": k}
        return d

    def shared_steps(self, other: ChainTransform) -> int:
        """How many leading steps this chain shares with `other` (the same step objects: a
        child's chain is built by extending its parent's)."""
        k = 0
        for a, b in zip(self.steps, other.steps, strict=False):
            if a is not b:
                break
            k += 1
        return k

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ChainTransform:
        """A chain from :meth:`to_dict`'s data, which must hold every step (see
        :func:`expand_shared_steps` for data written with a ``base``)."""
        if "base" in d:
            raise ValueError("this transform refers to another subject's steps (\"base\"): "
                             "expand it with expand_shared_steps first")
        try:
            return cls(
                source=Normalization.from_dict(d["source"]),
                target=Normalization.from_dict(d["target"]),
                steps=tuple(_step_from_dict(s) for s in d["steps"]),
                path=tuple(int(k) for k in d["path"]),
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"not a serialised ChainTransform: {exc}") from None


def expand_shared_steps(
    transform: Mapping[str, Any], base_of: Callable[[int], Mapping[str, Any] | None]
) -> dict[str, Any]:
    """A transform document with every step put back.

    :meth:`CollectionResult.to_dict(shared_steps=True) <CollectionResult.to_dict>` writes
    each subject's transform as the steps after those it shares with its parent's, and a
    ``base`` (``{"index": parent, "steps": k}``): the first ``k`` steps are the parent's.
    This puts them back in front, through as many bases as there are.

    Parameters
    ----------
    transform : mapping
        A :meth:`ChainTransform.to_dict` document, with or without a ``base``.
    base_of : callable
        ``base_of(index)``: the transform document of subject ``index`` (itself with or
        without a base), or None when there is none.

    Returns
    -------
    dict
        `transform` without ``base`` and with every step (for
        :meth:`ChainTransform.from_dict`); its step documents are the inputs', not copies.

    Raises
    ------
    ValueError
        When a base is missing, has fewer steps than referred to, or the bases loop.
    """
    chain: list[Mapping[str, Any]] = [transform]
    seen: set[int] = set()
    while "base" in chain[-1]:
        base = chain[-1]["base"]
        try:
            index, k = int(base["index"]), int(base["steps"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"not a transform base: {base!r}") from None
        if index in seen:
            raise ValueError(f"the transforms' bases loop through subject {index}")
        seen.add(index)
        found = base_of(index)
        if found is None:
            raise ValueError(f"the transform's base, subject {index}, has no transform")
        chain.append(found)
    steps: list[Any] = list(chain[-1]["steps"])
    for link in reversed(chain[:-1]):
        k = int(link["base"]["steps"])
        if k > len(steps):
            raise ValueError(f"the transform refers to {k} steps of subject "
                             f"{link['base']['index']}, which has {len(steps)}")
        steps = steps[:k] + list(link["steps"])
    out = {key: value for key, value in transform.items() if key != "base"}
    out["steps"] = steps
    return out

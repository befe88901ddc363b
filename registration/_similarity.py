"""Similarity of the shapes of a collection: D of eq. 9 for the pairs that matter."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._candidates import candidate_pairs, shape_descriptor
from ._executor import Executor, owned_executor
from ._icp import PairPose, pairwise_affine_icp, prepare_shape
from ._points import normalise
from ._pose import PoseSpec

FloatArray = NDArray[np.float64]
ProgressCallback = Callable[[str, int, int], None]

__all__ = [
    "ProgressCallback",
    "Similarity",
    "candidate_pairs",
    "shape_descriptor",
    "similarity_matrix",
]

_PAIRS_PER_TASK = 64
_TILE = 8
# D only has to be compared with a threshold: a looser tolerance than affine_icp's default
_SIMILARITY_TOL = 1e-3


@dataclass
class Similarity:
    """Directed affine-ICP distances between shapes of a collection.

    ``D[i, j]`` is ``D(X_i, Y=X_j)`` of eq. 9: shape ``i`` is the model moved by the
    affine map onto shape ``j``, on size-normalised shapes. It is not symmetric. Pairs not
    computed hold NaN; the diagonal is 0.

    Attributes
    ----------
    D : ndarray, shape (n, n)
    A : ndarray, shape (n, n, 2, 2)
        Linear part of the affine map of each computed pair (the map that gives D).
    t : ndarray, shape (n, n, 2)
    D_given, A_given, t_given : ndarray
        The same for the local optimum reached from the shapes as given (identity start);
        equal to D, A, t where the pose as given is also the best.
    computed : int
        Number of ICP runs done so far.
    pose : PoseSpec
        Which poses the ICP starts covered.
    """

    D: FloatArray
    A: FloatArray
    t: FloatArray
    D_given: FloatArray
    A_given: FloatArray
    t_given: FloatArray
    computed: int = 0
    pose: PoseSpec = field(default_factory=PoseSpec)
    _shapes: list[FloatArray] = field(default_factory=list, repr=False)

    @classmethod
    def empty(
        cls, normalised_shapes: Sequence[FloatArray], *, pose: PoseSpec | None = None
    ) -> Similarity:
        n = len(normalised_shapes)
        D = np.full((n, n), np.nan)
        np.fill_diagonal(D, 0.0)
        A = np.zeros((n, n, 2, 2))
        A[:] = np.eye(2)
        return cls(D=D, A=A, t=np.zeros((n, n, 2)), D_given=D.copy(), A_given=A.copy(),
                   t_given=np.zeros((n, n, 2)), pose=pose if pose is not None else PoseSpec(),
                   _shapes=list(normalised_shapes))

    def shape(self, index: int) -> FloatArray:
        """Shape `index` as the ICP saw it: centred on its centroid, unit RMS radius."""
        return self._shapes[index]

    @property
    def max_rotation(self) -> float | None:
        return self.pose.max_rotation

    def ensure(
        self,
        pairs: Iterable[tuple[int, int]],
        *,
        executor: Executor | None = None,
        progress: ProgressCallback | None = None,
        stage: str = "similarity",
    ) -> None:
        """Compute D for the given (model, subject) pairs that are not yet known."""
        todo = sorted(
            {(i, j) for i, j in pairs if i != j and np.isnan(self.D[i, j])},
            # tiles of _TILE x _TILE shapes, both directions of a pair side by side: a task
            # of consecutive pairs then needs few shapes (each task prepares its own)
            key=lambda p: (min(p) // _TILE, max(p) // _TILE, min(p), max(p), p),
        )
        if not todo:
            return
        tasks = []
        k = 0
        while k < len(todo):
            end = min(k + _PAIRS_PER_TASK, len(todo))
            if end < len(todo) and {todo[end - 1][0], todo[end - 1][1]} == set(todo[end]):
                end += 1  # keep (i, j) and (j, i) in the same task
            chunk = todo[k:end]
            tasks.append(
                _PairTask(pairs=chunk, shapes={idx: self._shapes[idx] for p in chunk for idx in p},
                          pose=self.pose)
            )
            k = end
        with owned_executor(executor, len(todo)) as ex:
            done = 0
            if progress is not None:
                progress(stage, 0, len(todo))
            for _, rows in ex.map_unordered(_icp_task, tasks):
                for r in rows:
                    i, j = r.i, r.j
                    self.D[i, j], self.A[i, j], self.t[i, j] = r.D, r.A, r.t
                    self.D_given[i, j], self.A_given[i, j], self.t_given[i, j] = (
                        r.D_given, r.A_given, r.t_given)
                done += len(rows)
                self.computed += len(rows)
                if progress is not None:
                    progress(stage, done, len(todo))

    def to_dict(self) -> dict[str, object]:
        return {
            "D": [[None if np.isnan(v) else float(v) for v in row] for row in self.D],
            "computed": self.computed,
        }


@dataclass(frozen=True)
class _PairTask:
    pairs: list[tuple[int, int]]
    shapes: dict[int, FloatArray]
    pose: PoseSpec


def _icp_task(task: _PairTask) -> list[PairPose]:
    """Affine ICP for a chunk of pairs, vectorised across the chunk."""
    prepared = {k: prepare_shape(v) for k, v in task.shapes.items()}
    return pairwise_affine_icp(prepared, task.pairs, tol=_SIMILARITY_TOL, pose=task.pose)


def similarity_matrix(
    shapes: Sequence[ArrayLike],
    *,
    candidates: int | None = None,
    pairs: Iterable[tuple[int, int]] | None = None,
    pose: str | None = None,
    max_rotation: float | None = None,
    executor: Executor | None = None,
    progress: ProgressCallback | None = None,
) -> Similarity:
    """Affine-ICP distance D (eq. 9) between the shapes of a collection.

    Parameters
    ----------
    shapes : sequence of array_like, shape (n_i, 2)
        Shapes in any coordinates; each is size-normalised first.
    candidates : int, optional
        Only compute pairs joining each shape to its `candidates` nearest shapes by a
        cheap descriptor (both directions). Default: all ordered pairs.
    pairs : iterable of (int, int), optional
        Explicit (model, subject) pairs to compute; overrides `candidates`.
    pose : {"rotation", "as_given", "upright", "affine"}, optional
        Which poses the ICP starts cover (see :func:`affine_icp`); default any rotation
        without reflection. The pose as given is always computed too (``D_given``).
    max_rotation : float, optional
        Half-width in degrees of the "upright" mode; given alone, it selects it.
    executor : Executor, optional
        Where ICP runs; default: serial for small collections, else a local process pool.
    progress : callable(stage, done, total), optional
        Called as pairs complete; an exception it raises stops the computation and
        propagates.

    Returns
    -------
    Similarity
    """
    spec = PoseSpec.resolve(pose, max_rotation)
    normed = [normalise(s, name=f"shapes[{k}]")[0] for k, s in enumerate(shapes)]
    n = len(normed)
    if n < 2:
        raise ValueError(f"need at least 2 shapes; got {n}")
    if pairs is not None:
        todo = list(pairs)
        for i, j in todo:
            if not (0 <= i < n and 0 <= j < n):
                raise ValueError(f"pair ({i}, {j}) is out of range for {n} shapes")
    elif candidates is not None:
        if candidates < 1:
            raise ValueError(f"candidates must be at least 1; got {candidates}")
        todo = candidate_pairs(normed, candidates)
    else:
        todo = [(i, j) for i in range(n) for j in range(n) if i != j]
    sim = Similarity.empty(normed, pose=spec)
    sim.ensure(todo, executor=executor, progress=progress)
    return sim

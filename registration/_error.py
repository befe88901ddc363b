"""The bidirectional registration error e of Du et al. 2016, eq. 10."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from ._cpd._switch import compiled as _compiled
from ._points import as_points

#: Up to this many pairs e's nearest neighbours come from the compiled pass over every
#: pair (both directions at once; 400 x 400 points in about 0.1 ms against the k-d
#: trees' 0.7), beyond from k-d trees.
DENSE_MAX_PAIRS = 1 << 22

#: One half of e (eq. 10), the mean squared distance from each point of one shape to the
#: nearest of the other, more than this many times the other half (and above the
#: subject's squared spacing h^2): that shape has points the other has no counterpart
#: for (`unmatched_side`). e counts every point both ways, so it then falls most where
#: the model is pulled over the subject's extra points, or squeezed into the part of it
#: the subject has. Registrations of whole shapes are near even: over the default
#: bench's families (2838 registrations of the tree without its polish) the ratio of the
#: two halves has its 1st-99th percentiles within 0.56-2.26 on every family but random
#: subsets of 80-120 points of an outline (0.27-1.58: their gaps leave model points off
#: the samples), and with that floor lies above 2 on 3 registrations one way and on 53
#: the other (52 of them those subsets). On the Chui & Rangarajan outlier series 22 of
#: the 24 subjects with outliers lie above 2 one way, on the occlusion series 11 of the
#: 30 occluded ones the other (bench/RESULTS.md 7.58). The tree acts on the second: it
#: compares poses by the subject's half when the model has the unmatched points
#: (`_tree._tasks._pose_term`). On the first it acts only when the subject's points
#: without counterpart are scattered (`scattered_extra`): the ratio alone also catches
#: real MPEG-7 outlines whose chain had not yet reached a leg or a wing (ratios 2.2-4.9
#: there, 2.2-22 on the outliers), which the polish fits (7.58, 7.59).
UNMATCHED_RATIO = 2.0

#: The subject's points without counterpart (`scattered_extra`) are those farther than
#: this many of its spacings h from the registered model.
EXTRA_SPACINGS = 2.0
#: Those points are scattered (outliers, specks) rather than a piece of outline the model
#: has not reached (a leg, a wing, an extra stroke) when the median, over each of them,
#: of the ratio of the smaller to the larger principal variance of it and its
#: :data:`SCATTER_NEIGHBOURS` nearest points of the subject is above this. A piece of
#: outline is near a line at the scale of five of its samples whatever its shape, so its
#: ratios sit near 0; points strewn at random give a median of 0.26 (uniform points in
#: the plane). Measured on the Chui & Rangarajan outlier series: 0.23-0.37 (fish),
#: 0.17-0.45 (Chinese character). The nearest among the off points alone (the first
#: version, and until session 59 the lower of the two readings counted) misreads a sparse
#: random sample of an outline (80-120 points), which leaves single points off the model
#: along its gaps whose nearest such points lie across the shape (0.21-0.27), and reads
#: the outlier series' Chinese character at 0.06-0.25, where few points are left off a
#: registration (3-33 off plain CPD's, of 52-157 outliers, at levels 2-4). The subject's
#: points misread one kind of outline: the tips of thin fins the registration has not
#: reached, whose nearest subject points lie on both sides of the fin (an MPEG-7 fish at
#: 0.26, bench/RESULTS.md 7.59 and 7.62).
SCATTER_MIN = 0.15
SCATTER_NEIGHBOURS = 4

#: The least share of the model's points inside a piece of it without counterpart on
#: the subject (:func:`part_of_model`) for the subject to be part of the model. On the
#: Chui & Rangarajan occlusion series 0.051-0.26; the far subjects of 永 chains whose
#: other readings look like a part 0.010-0.018, two random subsets of outlines 0 (bench/
#: RESULTS.md 7.60). e's pull to squeeze the model onto the part grows with the piece;
#: on a generated outline cut 5%, refusing the polish cost more than the squeeze (the
#: correspondence error 0.033 -> 0.038 and 0.070 -> 0.088 of the radius).
PART_MIN_INSIDE = 0.03

__all__ = ["EXTRA_SPACINGS", "PART_MIN_INSIDE", "SCATTER_MIN", "SCATTER_NEIGHBOURS",
           "UNMATCHED_RATIO", "directed_errors", "part_of_model", "registration_error",
           "scattered_extra", "unmatched_side"]


def registration_error(q: ArrayLike, y: ArrayLike) -> float:
    """Bidirectional nearest-neighbour mean squared distance (eq. 10).

    .. math::

        e = \\Big(\\sum_{i=1}^N \\lVert q_i - y_{r(i)} \\rVert^2
              + \\sum_{j=1}^M \\lVert q_{s(j)} - y_j \\rVert^2\\Big) / (N + M)

    where :math:`r(i)` is the subject point nearest to :math:`q_i` and :math:`s(j)` the
    warped-model point nearest to :math:`y_j`.

    Parameters
    ----------
    q : array_like, shape (N, 2)
        The model after registration (warped model points).
    y : array_like, shape (M, 2)
        The subject.

    Returns
    -------
    float
        e, in squared units of the input coordinates (the tree reports it on
        size-normalised shapes).

    Raises
    ------
    ValueError
        If either input is not a finite (n, 2) array with at least one point.
    """
    forward, backward = _nearest_squared(q, y)
    return float(forward.sum() + backward.sum()) / (forward.shape[0] + backward.shape[0])


def _nearest_squared(q: ArrayLike, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Each point of `q`'s squared distance to the nearest point of `y`, and each point of
    `y`'s to the nearest of `q` (the two halves of e)."""
    qa = as_points(q, name="q", min_points=1)
    ya = as_points(y, name="y", min_points=1)
    compiled = _compiled()
    if compiled is not None and len(qa) * len(ya) <= DENSE_MAX_PAIRS:
        fwd, bwd = np.empty(len(qa)), np.empty(len(ya))
        compiled.nearest(np.ascontiguousarray(qa[:, 0]), np.ascontiguousarray(qa[:, 1]),
                         np.ascontiguousarray(ya[:, 0]), np.ascontiguousarray(ya[:, 1]),
                         len(qa), len(ya), None, fwd, None, bwd)
        return fwd, bwd
    forward, _ = cKDTree(ya).query(qa)
    backward, _ = cKDTree(qa).query(ya)
    return forward * forward, backward * backward


def directed_errors(q: ArrayLike, y: ArrayLike) -> tuple[float, float]:
    """The two halves of e (eq. 10) as means: the mean squared distance from each point of
    the registered model `q` to the nearest point of the subject `y`, and from each point
    of `y` to the nearest of `q`."""
    forward, backward = _nearest_squared(q, y)
    return float(forward.mean()), float(backward.mean())


def unmatched_side(q: ArrayLike, y: ArrayLike, spacing2: float) -> str | None:
    """Which of the registered model `q` and the subject `y` has points the other has no
    counterpart for (:data:`UNMATCHED_RATIO`): ``"subject"`` (outliers, a speck, an extra
    stroke on the subject), ``"model"`` (the subject is part of the model: occluded, cut
    off), or None. `spacing2`: the subject's mean squared point spacing h^2."""
    return _side(*directed_errors(q, y), spacing2)


def _side(to_subject: float, to_model: float, spacing2: float) -> str | None:
    """:func:`unmatched_side` from the two halves of e (means)."""
    if max(to_subject, to_model) <= spacing2:
        return None
    if to_model > UNMATCHED_RATIO * to_subject:
        return "subject"
    if to_subject > UNMATCHED_RATIO * to_model:
        return "model"
    return None


def part_of_model(q: ArrayLike, y: ArrayLike, spacing2: float) -> bool:
    """Whether the subject `y` is part of the registered model `q` (occluded, cut off):

    - the model has the unmatched points (:func:`unmatched_side` ``"model"``);
    - the subject lies on the model: the share of the model's points farther than
      :data:`EXTRA_SPACINGS` spacings from the subject is more than
      :data:`UNMATCHED_RATIO` times the share of the subject's points that far from the
      model (a registration that is off somewhere leaves both shapes off the other
      about alike);
    - those model points form a piece: at least :data:`PART_MIN_INSIDE` of the model's
      points lie inside one, they and their :data:`SCATTER_NEIGHBOURS` nearest model
      points all that far from the subject (the gaps of a sparse random sample of an
      outline leave mostly single model points off it, with no inside; a gap long
      enough to hold a piece of the outline counts).

    Measured on the root's registrations of the subjects of the default bench that read
    ``"model"`` (bench/RESULTS.md 7.60): the Chui & Rangarajan occlusion series, ratio 6.6
    or more (the model's share 0.13-0.35, the subject's 0-0.02), inside 0.051-0.26; an
    outline cut 15% each side of a direction, ratio 2.9; far subjects of 永 chains,
    ratio 1.2-1.7, or above 2 with inside 0.010-0.018; random subsets of 80-120 points of
    an outline, ratio 5, inside 0 on the two probed (7 of the bench's 15 such runs have a
    subject with a gap that holds a piece). `spacing2`: the subject's mean squared point
    spacing h^2."""
    qa = np.asarray(q, dtype=np.float64)
    forward, backward = _nearest_squared(qa, y)
    if _side(float(forward.mean()), float(backward.mean()), spacing2) != "model":
        return False
    far = EXTRA_SPACINGS ** 2 * spacing2
    model_off = forward > far
    if not model_off.mean() > UNMATCHED_RATIO * float(np.mean(backward > far)):
        return False
    if model_off.sum() < SCATTER_NEIGHBOURS + 1:
        return False
    inside = int(model_off[_neighbourhoods(qa[model_off], qa)].all(axis=1).sum())
    return inside >= PART_MIN_INSIDE * len(qa)


def scattered_extra(q: ArrayLike, y: ArrayLike, spacing2: float) -> float | None:
    """How scattered the subject `y`'s points without counterpart on the registered model
    `q` are, when the subject has such points (:func:`unmatched_side` ``"subject"``): the
    median over the points farther than :data:`EXTRA_SPACINGS` spacings from `q` of the
    ratio of the smaller to the larger principal variance of each and its
    :data:`SCATTER_NEIGHBOURS` nearest points of `y` (0: on a line; 1: spread evenly;
    above :data:`SCATTER_MIN`: scattered, as outliers are). None when the subject has no
    such points, or too few of them to tell (fewer than ``SCATTER_NEIGHBOURS + 1``).
    `spacing2`: the subject's mean squared point spacing h^2."""
    forward, backward = _nearest_squared(q, y)  # one pass for the halves and the points
    if _side(float(forward.mean()), float(backward.mean()), spacing2) != "subject":
        return None
    ya = np.asarray(y, dtype=np.float64)
    extra = ya[backward > EXTRA_SPACINGS ** 2 * spacing2]
    if len(extra) < SCATTER_NEIGHBOURS + 1:
        return None
    return _anisotropy(extra, ya)


def _anisotropy(points: np.ndarray, among: np.ndarray) -> float:
    """The median over `points` of the ratio of the smaller to the larger principal
    variance of each point's :data:`SCATTER_NEIGHBOURS` + 1 nearest in `among` (the point
    itself included when it is one of `among`)."""
    idx = _neighbourhoods(points, among)
    local = among[idx] - among[idx].mean(axis=1, keepdims=True)  # (n, k, 2)
    cov = np.einsum("nki,nkj->nij", local, local)
    low, high = np.linalg.eigvalsh(cov).T
    return float(np.median(low / np.maximum(high, np.finfo(float).tiny)))


def _neighbourhoods(points: np.ndarray, among: np.ndarray) -> np.ndarray:
    """The indices into `among` of each of `points`' :data:`SCATTER_NEIGHBOURS` + 1
    nearest (the point itself included when it is one of `among`), shape (n, k): the
    neighbourhoods :func:`scattered_extra` and :func:`part_of_model` read."""
    _, idx = cKDTree(among).query(points, k=SCATTER_NEIGHBOURS + 1)
    return np.asarray(idx)

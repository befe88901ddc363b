"""Halfway to the registration back: the step the dynamic tree's symmetric edges
(`_tasks._symmetric_link`) and the polish's symmetric finish (`_polish._symmetric`, and
again at the stored resolution) share, and the fold-checked field through points
(:func:`fitted_step`) it and the polish's other steps (`_polish._step_onto`) are fitted with.

CPD is not symmetric: the model's points are the mixture's centroids, pulled onto the
subject's points, so a registration slides the model along the subject's outline wherever
the two samplings let the centroids settle at a lower e; the other way round the subject's
points are the centroids and the slides fall elsewhere. Moving the forward registration
halfway to where the subject, registered back onto the model, puts the model's points
cancels part of each slide (bench/RESULTS.md 7.16 for the finish, 7.29 for the edges)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from .._cpd import interpolating_field
from .._inverse import invert_points
from .._pointmap import PointTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: A model point's preimage under the backward registration counts as found to this
#: accuracy (normalised coordinates: the shapes' RMS radius is 1).
INVERSE_TOL = 1e-6
#: At least this share of the model's points (of the control points, when the fields are
#: fitted through those) must have a preimage for the step to be taken; the others move
#: with the step's field through their neighbours. Across real glyph designs the backward
#: field cannot reach the tips of strokes the subject lacks or has shorter (the model's
#: point has no preimage near the subject's outline): on the 73 永 edge glyphs 0.8 % of the
#: root's points in the median inversion and at most 4.5 % (144 inversions), where asking
#: for every point rejected the symmetric finish for 39 of 72 subjects (65 of 72 at the
#: stored resolution). Nine in ten keeps a backward registration that has lost more of the
#: model from leading the step.
MIN_REACHED = 0.9
#: Ridge added to the kernel matrices of the fields fitted through points (kernel 1 at
#: distance 0).
RIDGE = 1e-3


class Halfway(NamedTuple):
    """The step halfway (:func:`halfway_back`), the points it moves the registration to,
    and how many of the points it was to be fitted through had no inverse (moved by the
    step's field through the others)."""

    step: PointTransform
    moved: FloatArray
    without_inverse: int


class NoHalfway(NamedTuple):
    """Why :func:`halfway_back` has no step, and how many of the points it was to be fitted
    through had no inverse."""

    reason: str
    without_inverse: int


def fitted_step(points: FloatArray, targets: FloatArray, beta: float,
                through: IntArray | None = None) -> tuple[PointTransform, FloatArray] | None:
    """CPD's field of kernel width `beta` (ridge :data:`RIDGE`) fitted through `points`
    (the `through` ones alone, when given) onto `targets` (one per point fitted), and where
    it puts every one of `points`; None when it folds at any of them."""
    fit = points if through is None else points[through]
    step = interpolating_field(fit, targets, beta, RIDGE)
    moved, jac = step.apply_with_jacobian(points)
    if not float(np.linalg.det(jac).min()) > 0:
        return None
    return step, np.asarray(moved, dtype=np.float64)


def halfway_back(model: FloatArray, y: FloatArray, warped: FloatArray, beta: float,
                 backward: Callable[[FloatArray], PointTransform], step_beta: float,
                 control: IntArray | None = None) -> Halfway | NoHalfway:
    """The registration `warped` (the `model`'s points registered onto the subject `y`)
    moved halfway to where the subject registered back onto the model puts the model's
    points: the step, the points it moves `warped` to and how many had no inverse, or why
    there is no step.

    `backward(start)` registers the subject back onto the model, CPD started from `start`
    (the subject's points in the model's frame) and returns its transform; the start is
    the inverse of `warped` (CPD's field through `warped` back onto the model, kernel width
    `beta`, applied to the subject). The backward transform is inverted
    (:func:`~registration._inverse.invert_points`, to :data:`INVERSE_TOL`, seeded at
    `warped`) at the model's points the fields are fitted through (the `control` points;
    None: every point). The step is CPD's field of kernel width `step_beta` through the
    points with a preimage onto halfway; the points without one (a stroke's tip the
    subject lacks: nothing of the subject is registered onto it) move by that field with
    their neighbours. At least :data:`MIN_REACHED` of the points must have one, and the
    step must not fold at any of `warped`."""
    at = np.arange(len(model)) if control is None else np.asarray(control, dtype=np.intp)
    back = interpolating_field(warped[at], model[at], beta, RIDGE)
    transform = backward(back.apply(y))
    z, residual = invert_points(transform, model[at], seeds=warped[at])
    reached = np.isfinite(z).all(axis=1) & (residual <= INVERSE_TOL)
    without = int(np.count_nonzero(~reached))
    if not reached.mean() >= MIN_REACHED:
        return NoHalfway(f"the backward registration has no inverse at more than "
                         f"{1 - MIN_REACHED:.0%} of the model's points", without)
    through = at[reached]
    found = fitted_step(warped, 0.5 * (warped[through] + z[reached]), step_beta, through)
    if found is None:
        return NoHalfway("the step halfway folds", without)
    return Halfway(*found, without)

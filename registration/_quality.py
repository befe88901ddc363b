"""What a registration's e (eq. 10) cannot see: checks on the correspondences, and a
calibrated confidence.

e measures how closely the warped model lies on the subject; a registration that
mirrors, rotates or slides the model along the subject's curves can still lie on it. The
checks below look at the map itself:

- ``min_jacobian``: the smallest Jacobian determinant of the CPD warp over the model
  (<= 0: the warp folds the model). On a model drawn as a lone stroke (a straight or
  gently bent stroke's skeleton: most of its points have no model point across them,
  :func:`points_across`), the warp's stretch along the stroke stands in for the
  determinant at those points, in this check and in ``distortion``, and ``anisotropy``
  is 0 there: across such a stroke the field is the kernel's extension of the stroke's
  displacements, where no point is to fold or shear (:func:`fold_values`);
- ``distortion``: the spread (standard deviation) of the log Jacobian determinant of the
  CPD warp over the model. A smooth deformation changes area evenly; a slide along a
  curve compresses the model on one side and stretches it on the other;
- ``anisotropy``: the 90th percentile of log(s1 / s2), the singular values of the CPD
  warp's Jacobian: shearing a stroke along itself;
- ``cpd_rotation``: the rotation (degrees) of the best similarity fit from the
  pre-aligned model to the warped model: CPD turning the whole model is a wrong pose
  repaired by sliding;
- ``coverage``: the fraction of subject points within two point spacings of the warped
  model: a registration that piles the model on part of the subject leaves the rest
  uncovered;
- ``error_ratio``: e over the subject's squared point spacing h^2 (scale-free).

The checks are taken at a fixed density: shapes of more than :data:`QUALITY_POINTS` points
are measured on farthest-point subsamples of that many (the model's picked once, so the
prealigned and warped models keep their correspondence). e / h^2 and the coverage within
2h depend on how densely the shapes are sampled (h shrinks as points are added while a
registration's geometric misfit does not), and the confidence model was fitted on shapes
of 100-400 points: measured on 73 永 glyphs at their stored 1167-2244 points, correct
registrations scored near 0.05 and a tree built there left 71 of 72 subjects as leaves.

``confidence`` is a logistic function of these, fitted on registrations with known
ground truth (``bench/calibrate_thresholds.py``): the estimated probability that the RMS
correspondence error is below ``GOOD_ERROR`` (0.15) of the subject's RMS radius: right up
to a local slip along a stroke, where a mirrored, turned or slid registration is off by
0.3 to 1.5. Every feature is
scale-free (ratios, angles, logs of ratios), so the fit carries over to other collections.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ._error import registration_error
from ._pointmap import PointTransform, jacobian_matrices
from ._points import farthest_point_indices, mean_spacing2, nearest_distances

FloatArray = NDArray[np.float64]

__all__ = ["GOOD_ERROR", "RegistrationQuality", "measure_quality", "nearest_spacing",
           "spacing_distortion"]

#: A registration counts as good when its RMS ground-truth correspondence error is below
#: this fraction of the subject's RMS radius (what the confidence estimates).
GOOD_ERROR = 0.15
#: Most points per shape the checks are measured on (the largest shapes the confidence
#: model was fitted on: the 400-point 永 chains of bench/calibrate_thresholds.py).
QUALITY_POINTS = 400

# Logistic model of P(good | features): intercept, then one weight per entry of
# `RegistrationQuality.features()`. Fitted by bench/calibrate_thresholds.py (see there
# for the data and the held-out figures); the values below are its output.
_MIN_ERROR_RATIO = 0.01
_FEATURES = ("log_error_ratio", "distortion", "anisotropy", "cpd_rotation", "coverage")
# 2026-12-06: 3140 registrations that do not fold (of 1144 pairs: the Chui fish and
# Chinese series; 永 edge and skeleton chains, and the same turned by 90 degrees; 書水心東龍
# in two Noto fonts chained at a seed bench_groundtruth.py does not run, upright and turned
# at random; generated families), from every start the tree offers (the pose as given, the
# similarity's turn, rigid ICP's turn, the mirror under "affine"), registered one way as
# direct CPD does and as the dynamic tree's edges are (held start, made symmetric).
# AUC 0.85 overall, 0.72-0.97 with each set held out; the model before (fitted on 742
# one-way registrations without rigid ICP's turn or the rendered glyphs) scored 0.69 and
# 0.76 on the rendered glyphs upright and turned, this one held out 0.77 and 0.80. Of the
# registrations it scores below 0.2, 5.1% were good; in [0.8, 0.95), 89% (the model
# before: 0.6% and 85%); above 0.95, 100%. bench/RESULTS.md 7.47.
_INTERCEPT = 0.7102
_WEIGHTS = (-0.5312, 0.0761, -0.5295, -0.2659, 0.9936)
_MEAN = (0.4827, 0.2864, 0.7462, 5.6071, 0.8674)
_SCALE = (1.1899, 0.1404, 0.4350, 7.0318, 0.1494)


@dataclass(frozen=True)
class RegistrationQuality:
    """Checks of one registration (member -> subject) beyond e; see the module doc."""

    error: float
    spacing2: float
    min_jacobian: float
    distortion: float
    anisotropy: float
    cpd_rotation: float
    coverage: float

    @property
    def error_ratio(self) -> float:
        return self.error / max(self.spacing2, 1e-300)

    def features(self) -> FloatArray:
        """The confidence model's inputs, in the order of ``_FEATURES``."""
        return np.array([
            # below e = 0.01 h^2 the model lies on the subject as closely as its sampling
            # allows: no further evidence, so the feature stops there
            math.log(max(self.error_ratio, _MIN_ERROR_RATIO)),
            self.distortion,
            self.anisotropy,
            abs(self.cpd_rotation),
            self.coverage,
        ])

    @property
    def confidence(self) -> float:
        """Estimated probability that the correspondences are right (0 when folded)."""
        if not self.min_jacobian > 0:
            return 0.0
        z = (self.features() - np.asarray(_MEAN)) / np.asarray(_SCALE)
        logit = _INTERCEPT + float(np.dot(_WEIGHTS, z))
        return float(1.0 / (1.0 + math.exp(-min(max(logit, -50.0), 50.0))))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["error_ratio"] = self.error_ratio
        d["confidence"] = self.confidence
        return d


def _similarity_rotation(src: FloatArray, dst: FloatArray) -> float:
    """Rotation in degrees of the least-squares similarity map src -> dst (Procrustes)."""
    a = src - src.mean(axis=0)
    b = dst - dst.mean(axis=0)
    num = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    den = float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    return math.degrees(math.atan2(num, den))


def measure_quality(
    prealigned: FloatArray,
    warped: FloatArray,
    subject: FloatArray,
    warp: PointTransform,
    error: float,
    spacing2: float,
) -> RegistrationQuality:
    """Checks of a registration whose CPD step `warp` moved `prealigned` to `warped`.

    Parameters
    ----------
    prealigned : ndarray, shape (N, 2)
        The model after the affine pre-alignment (CPD's input), normalised coordinates.
    warped : ndarray, shape (N, 2)
        The model after CPD.
    subject : ndarray, shape (M, 2)
    warp : PointTransform
        CPD's non-rigid transform (applies to `prealigned`).
    error : float
        e of eq. 10 between `warped` and `subject`.
    spacing2 : float
        The subject's mean squared nearest-neighbour spacing h^2.

    Both are measured again on the subsamples when a shape has more than
    :data:`QUALITY_POINTS` points (see the module doc), and the result reports those.

    Returns
    -------
    RegistrationQuality
    """
    if len(prealigned) > QUALITY_POINTS or len(subject) > QUALITY_POINTS:
        pick = farthest_point_indices(prealigned, QUALITY_POINTS)
        prealigned, warped = prealigned[pick], warped[pick]
        subject = subject[farthest_point_indices(subject, QUALITY_POINTS)]
        error = registration_error(warped, subject)
        spacing2 = mean_spacing2(subject)
    J = jacobian_matrices(warp, prealigned)
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    s1, s2 = singular_values_2x2(J)
    aniso = np.log(np.maximum(s1, 1e-12) / np.maximum(s2, 1e-12))
    det, across = fold_values(prealigned, J, det)
    # along a stroke with nothing across it there is no second direction to compare
    aniso = np.where(across, aniso, 0.0)
    min_jac = float(det.min())
    logdet = np.log(np.maximum(det, 1e-6))
    h = math.sqrt(max(spacing2, 1e-300))
    dist, _ = cKDTree(warped).query(subject)
    return RegistrationQuality(
        error=float(error),
        spacing2=float(spacing2),
        min_jacobian=min_jac,
        distortion=float(np.std(logdet)),
        anisotropy=float(np.percentile(aniso, 90)),
        cpd_rotation=_similarity_rotation(prealigned, warped),
        coverage=float(np.mean(dist <= 2.0 * h)),
    )


#: Neighbours (the point included) whose spread gives a model point's tangent.
TANGENT_NEIGHBOURS = 7
#: Model points nearer than this many point spacings (h) across a point are the same
#: stroke (a rendered skeleton's second row of pixels), not across it. At 3 the two sides
#: of the Chui fish's thin fins (98 points) counted as one stroke too: 4.6% of its
#: points (at most 28% of one shape) had nothing across, against 1.5% (9%) at 1.5; the
#: straight strokes' skeletons were the same at both.
ACROSS_MIN_SPACINGS = 1.5
#: About this many of a shape's points are looked among for points across each point.
ACROSS_CANDIDATES = 128
#: The stretch along the stroke stands in for the determinant only on a model at least
#: this share of whose points have nothing across (:func:`fold_values`): a stroke drawn
#: alone (the skeletons of 一, 丨, I and -: 70-100%). A few such points on a shape of
#: several strokes or a closed outline (stroke tips, fin tips: at most 1.2% of a 永
#: skeleton's points, 9% of a Chui fish's) lie within the kernel's reach of points
#: across, which constrain the field there: with them too, one 永 skeleton run went
#: from 0.39 to 0.41 of plain CPD's correspondence error (bench/RESULTS.md 7.44).
LONE_STROKE_SHARE = 0.5


def _tangents_and_spacing(points: FloatArray) -> tuple[FloatArray, float]:
    """Each point's unit tangent (the principal direction of its ``TANGENT_NEIGHBOURS``
    nearest points, itself included) and the RMS distance of a point to its nearest
    other point (h, ``sqrt(mean_spacing2)``), from one neighbour query."""
    n = len(points)
    k = min(TANGENT_NEIGHBOURS, n)
    dist, idx = cKDTree(points).query(points, k)
    dist = np.asarray(dist, dtype=np.float64).reshape(n, k)
    nb = points[np.asarray(idx).reshape(n, k)]
    c = nb - nb.mean(axis=1, keepdims=True)
    sxx = np.einsum("nk,nk->n", c[..., 0], c[..., 0])
    syy = np.einsum("nk,nk->n", c[..., 1], c[..., 1])
    sxy = np.einsum("nk,nk->n", c[..., 0], c[..., 1])
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # the 2 x 2 scatter's principal axis
    h = float(np.sqrt(np.mean(dist[:, 1] ** 2))) if k > 1 else 0.0
    return np.c_[np.cos(angle), np.sin(angle)], h


def outline_tangents(points: FloatArray) -> FloatArray:
    """Each point's unit tangent: the principal direction of its ``TANGENT_NEIGHBOURS``
    nearest points, itself included (its sign arbitrary)."""
    return _tangents_and_spacing(points)[0]


def points_across(points: FloatArray) -> NDArray[np.bool_]:
    """Whether each point has other points of the set across it: within 45 degrees of
    its normal (either side, any distance) and more than ``ACROSS_MIN_SPACINGS`` point
    spacings (h) away; looked for among every ``len(points) // ACROSS_CANDIDATES``-th
    point. False along a straight or gently bent stroke drawn alone (its other points
    lie along it); True on an outline (the other side of the shape) and on a glyph's
    strokes that other strokes cross or face.

    Along such a stroke CPD's field across it is only its kernel's extension of the
    stroke's displacements: it may flip the plane there at no cost on the points. On
    the skeleton of 一 (Noto Sans, chained as the bench's glyphs) 48 registrations from
    the pose as given "folded" so, on 41% of their points, none of them reversing a
    point's order along the stroke; each let a registration turned end for end win, and
    the log determinants' spread refused the right ones on confidence
    (bench/RESULTS.md 7.44). On the kinds of shape the confidence was fitted on almost
    every point has points across (0.1% of the points of 永 skeletons have none, none of
    the Chui Chinese, 1.5% of the Chui fish: its fin tips), so none of them is a lone
    stroke (``LONE_STROKE_SHARE``) and its checks, and the fit, are as before.
    """
    n = len(points)
    if n < 3:
        return np.zeros(n, dtype=bool)
    return _across(points, *_tangents_and_spacing(points))


def _across(points: FloatArray, t: FloatArray, h: float) -> NDArray[np.bool_]:
    n = len(points)
    others = points[::max(1, n // ACROSS_CANDIDATES)]
    near2 = (ACROSS_MIN_SPACINGS * h) ** 2
    across = np.zeros(n, dtype=bool)
    for lo in range(0, n, 512):  # blocks of rows: at most 512 x 2 ACROSS_CANDIDATES pairs
        dx = others[None, :, 0] - points[lo:lo + 512, 0, None]
        dy = others[None, :, 1] - points[lo:lo + 512, 1, None]
        tx, ty = t[lo:lo + 512, 0, None], t[lo:lo + 512, 1, None]
        along2 = (dx * tx + dy * ty) ** 2
        normal2 = (dx * ty - dy * tx) ** 2
        across[lo:lo + 512] = np.any((normal2 > near2) & (along2 <= normal2), axis=1)
    return across


def fold_values(points: FloatArray, J: FloatArray, det: FloatArray | None = None
                ) -> tuple[FloatArray, NDArray[np.bool_]]:
    """What says, at each of the model's `points`, whether a warp with Jacobians `J`
    (shape (N, 2, 2); `det` their determinants, computed when omitted) folds the model
    there, and at which points the determinant is what says so: the determinant
    where points lie across a point (:func:`points_across`); elsewhere, along a stroke
    with nothing across it, the stretch ``|J t|`` along the stroke (t the point's
    tangent), the determinant of the map restricted to the stroke, positive unless the
    warp collapses it. Only on a model drawn as a lone stroke (``LONE_STROKE_SHARE``);
    on any other the determinant everywhere. A fold is a value <= 0."""
    if det is None:
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    if len(points) < 3:
        return det, np.ones(len(points), dtype=bool)
    t, h = _tangents_and_spacing(points)
    across = _across(points, t, h)
    if not np.mean(~across) >= LONE_STROKE_SHARE:
        return det, np.ones(len(points), dtype=bool)
    stretch = np.hypot(J[:, 0, 0] * t[:, 0] + J[:, 0, 1] * t[:, 1],
                       J[:, 1, 0] * t[:, 0] + J[:, 1, 1] * t[:, 1])
    return np.where(across, det, stretch), across


def singular_values_2x2(J: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The larger and the smaller singular value of each 2 x 2 matrix of `J` (shape (N, 2,
    2)), in closed form: for ``[[a, b], [c, d]]``, with ``p = |(a + d, c - b)|`` and ``q =
    |(a - d, b + c)|``, they are ``(p + q) / 2`` and ``|p - q| / 2``. Within a few ulp of
    LAPACK's (``np.linalg.svd``), which took a quarter of the quality checks' time, a
    call per matrix."""
    a, b, c, d = J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1]
    p = np.hypot(a + d, c - b)
    q = np.hypot(a - d, b + c)
    return 0.5 * (p + q), 0.5 * np.abs(p - q)


def nearest_spacing(points: FloatArray) -> FloatArray:
    """Each point's distance to the nearest other point of the same set (floored at 1e-12:
    coincident points count as a spacing of 1e-12, so their log ratios stay finite)."""
    return np.maximum(nearest_distances(points), 1e-12)


def spacing_distortion(warped: FloatArray, model_spacing: FloatArray) -> float:
    """V: the variance, over the model's points, of ``log(d_warped / d_model)``, each point's
    distance to its nearest neighbour in the warped model over that in the model.

    A registration maps the model's own sampling along with its shape: a smooth map
    stretches neighbouring spacings alike, so their log ratios vary slowly and V stays
    small whatever the overall stretch (its mean drops out). A registration that slides
    the model along the subject's curves, or pulls its points onto the subject's own
    samples, squeezes some spacings and opens others: V grows while e (eq. 10), which sees
    only how closely the model lies on the subject, can fall. Unlike ``distortion`` (the
    Jacobian of one CPD step), V is taken on the whole map from the model, so
    registrations reached along different paths compare. The tree does not use it: as a
    penalty on e in the polish it helped on smooth deformations with ground truth and
    refused the fits that differences between real font designs need (bench/RESULTS.md
    7.8; ``bench/bench_polish_scores.py`` measures it).

    Parameters
    ----------
    warped : ndarray, shape (N, 2)
        The model as the registration places it.
    model_spacing : ndarray, shape (N,)
        :func:`nearest_spacing` of the model (any coordinates: a common scale drops out).
    """
    r = np.log(nearest_spacing(warped) / model_spacing)
    return float(np.var(r))

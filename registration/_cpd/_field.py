"""The fitted CPD displacement field, :class:`NonrigidTransform`, and its Gaussian kernel."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._repr import number_text, points_text
from ._fgt import bounding_box, gauss_transform, grid_nodes
from ._switch import compiled as _compiled

FloatArray = NDArray[np.float64]

#: Elements of one kernel or E-step block (M x block columns). Each block makes several
#: passes over its elements (product, clamp, cast, exp, two sums), so it pays to keep them
#: near the cache: 1 << 18 against 1 << 22 took 0.73x / 0.63x / 0.58x the time of the
#: float32 dense E-step at 500 x 1900 / 1900^2 / 4000^2 points, and 0.8-0.9x of the final
#: posterior pass (bench/RESULTS.md section 7.3); smaller blocks lose to the loop's overhead.
_BLOCK_ELEMS = 1 << 18
#: Chebyshev nodes per axis added to the field's Gauss transform beyond its 1e-10 rule
#: (:func:`._fgt.cheb_rank`): about 1e-13 per kernel value; measured on 永 glyphs at beta 1
#: and 2, every sum within 4e-16 of ``sum_j |q_j|`` of the dense product.
FIELD_FGT_EXTRA = 8
#: The field's kernel product goes through the Chebyshev Gauss transform when its cost,
#: ``FIELD_FGT_NODE_COST * (K + M) * r_x * r_y + FIELD_FGT_FIXED``, is below the dense
#: product's ``K * M`` (in kernel entries). Fitted on 永 glyphs at beta 1 and 2, 100-2000
#: points a side, 2 and 6 weight columns, against the dense kernel of one product and an
#: exp (:func:`_gauss_kernel`; bench/RESULTS.md 7.9): the estimate within 0.6-1.7x of the
#: measured ratio of the two, on the same side of 1 in every case: 400 x 400 points
#: 0.41-0.44 ms dense, 0.61-1.02 ms by the grid; 800 x 800 1.7-1.9 ms dense, 0.95-1.5 ms
#: by the grid; 2000 x 2000 8-11 ms dense, 2.1-3.5 ms by the grid.
FIELD_FGT_NODE_COST = 0.33
FIELD_FGT_FIXED = 82_500


def _readonly(a: ArrayLike, dtype: Any = np.float64) -> NDArray[Any]:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def _exponent_rows(t: FloatArray, sigma2: float) -> FloatArray:
    """The centroids' factor of the Gaussian exponent as one product: ``exponent[m, n] =
    (t_m . x_n) / s2 - |t_m|^2 / (2 s2) - |x_n|^2 / (2 s2) = rows @ cols`` (with
    :func:`_exponent_cols`)."""
    rows = np.empty((len(t), 4))
    rows[:, :2] = t
    rows[:, 2] = -0.5 / sigma2 * np.einsum("ij,ij->i", t, t)
    rows[:, 3] = 1.0
    return rows


def _exponent_cols(x: FloatArray, xsq: FloatArray, sigma2: float) -> FloatArray:
    """The subject points' factor (``xsq``: their squared norms), see
    :func:`_exponent_rows`."""
    cols = np.empty((4, len(x)))
    cols[:2] = x.T / sigma2
    cols[2] = 1.0
    cols[3] = -0.5 / sigma2 * xsq
    return cols


def _gauss_kernel(a: FloatArray, b: FloatArray, beta: float) -> FloatArray:
    """``exp(-|a_i - b_j|^2 / (2 beta^2))``.

    The exponents come from one product, ``(a_i . b_j - |a_i|^2 / 2 - |b_j|^2 / 2) /
    beta^2`` (the dense E-step's factors, :func:`_exponent_rows` and
    :func:`_exponent_cols`, at ``sigma^2 = beta^2``), clamped at 0 against rounding, then
    one exp: 0.2-0.6x the time of the coordinate differences' six passes at 400-1200
    points a side (their temporaries the size of the kernel), the kernel within 3e-14
    relative of theirs at beta 0.25-2 on unit shapes (the rounding of the expansion grows
    with ``|a|^2 / beta^2``). Rows or columns
    of points whose squared norm is not finite (infinite, NaN or beyond 1e154) are taken
    from the differences, as before: 0 at infinity, NaN for NaN."""
    s2 = beta * beta
    with np.errstate(invalid="ignore", over="ignore"):  # such rows are redone below
        rows = _exponent_rows(a, s2)
        cols = _exponent_cols(b, np.einsum("ij,ij->i", b, b), s2)
        k = rows @ cols
    np.minimum(k, 0.0, out=k)
    np.exp(k, out=k)
    bad_a = ~np.isfinite(rows[:, 2])
    if bad_a.any():
        k[bad_a] = _gauss_kernel_by_differences(a[bad_a], b, beta)
    bad_b = ~np.isfinite(cols[3])
    if bad_b.any():
        k[:, bad_b] = _gauss_kernel_by_differences(a, b[bad_b], beta)
    return k


def _gauss_kernel_by_differences(a: FloatArray, b: FloatArray, beta: float) -> FloatArray:
    """:func:`_gauss_kernel` from the coordinate differences (any points)."""
    k = np.subtract.outer(a[:, 0], b[:, 0])
    np.square(k, out=k)
    d1 = np.subtract.outer(a[:, 1], b[:, 1])
    np.square(d1, out=d1)
    k += d1
    k *= -0.5 / (beta * beta)
    np.exp(k, out=k)
    return k


def kernel_product(z: FloatArray, cp: FloatArray, q: FloatArray, beta: float) -> FloatArray:
    """``G(z, cp) @ q`` (``G[i, j] = exp(-|z_i - cp_j|^2 / (2 beta^2))``), shape (K, k).

    Dense in blocks of :data:`_BLOCK_ELEMS`, or through the Chebyshev Gauss transform
    (:func:`._fgt.gauss_transform` with :data:`FIELD_FGT_EXTRA` more nodes) when its estimated
    cost is lower: a CPD field's kernel is wide (beta 1-2 on shapes of RMS radius 1), so
    its grid has a few hundred nodes however many points there are.
    """
    k, m = len(z), len(cp)
    out = np.zeros((k, q.shape[1]))
    if k == 0 or m == 0:
        return out
    lo, hi = bounding_box(z, cp)
    # a point at infinity or NaN makes the count so: the dense product keeps such points
    nodes = grid_nodes(np.maximum(hi - lo, 1e-12 * beta), beta, FIELD_FGT_EXTRA)
    if FIELD_FGT_NODE_COST * (k + m) * nodes + FIELD_FGT_FIXED < k * m:
        return gauss_transform(cp, q, z, beta, extra=FIELD_FGT_EXTRA)
    compiled = _compiled()
    if compiled is not None and np.isfinite(lo).all() and np.isfinite(hi).all():
        # one pass over the pairs (see _estep._EStep._dense_compiled); points at infinity
        # or NaN take numpy's route below
        compiled.product(np.ascontiguousarray(z, dtype=np.float64),
                         np.ascontiguousarray(cp.T, dtype=np.float64),
                         np.ascontiguousarray(q.T, dtype=np.float64), 0.5 / (beta * beta),
                         out)
        return out
    step = max(1, _BLOCK_ELEMS // m)
    for a in range(0, k, step):
        out[a:a + step] = _gauss_kernel(z[a:a + step], cp, beta) @ q
    return out


@dataclass(frozen=True, eq=False)
class NonrigidTransform:
    """A fitted CPD Gaussian-RBF displacement field that can warp any 2D points.

    For caller-coordinate points ``p`` the warp is::

        z = (p - model_shift) / model_scale
        out = (z + G(z, control_points) @ coefficients) * subject_scale + subject_shift

    with ``G(a, b)[i, j] = exp(-|a_i - b_j|^2 / (2 beta^2))``.  ``control_points`` are the
    normalised model points the field was fitted on (``Y`` of the CPD paper) and
    ``coefficients`` the weights ``W``. For many points the product ``G W`` goes through
    a Chebyshev Gauss transform, each kernel value within about 1e-13 of the exact one
    (:func:`kernel_product`).

    Attributes
    ----------
    control_points : ndarray, shape (M, 2)
        Normalised model points (kernel centres).
    coefficients : ndarray, shape (M, 2)
        Kernel weights ``W``.
    beta : float
        Kernel width, in normalised units.
    model_shift, subject_shift : ndarray, shape (2,)
        Translations of the model and subject normalisations.
    model_scale, subject_scale : float
        Scales of the model and subject normalisations.
    """

    control_points: FloatArray
    coefficients: FloatArray
    beta: float
    model_shift: FloatArray
    model_scale: float
    subject_shift: FloatArray
    subject_scale: float

    def __post_init__(self) -> None:
        cp = _readonly(self.control_points)
        co = _readonly(self.coefficients)
        if cp.ndim != 2 or cp.shape[1] != 2 or co.shape != cp.shape:
            raise ValueError(
                "control_points and coefficients must both have shape (M, 2); "
                f"got {cp.shape} and {co.shape}"
            )
        for name, v in (("beta", self.beta), ("model_scale", self.model_scale),
                        ("subject_scale", self.subject_scale)):
            if not (math.isfinite(float(v)) and float(v) > 0):
                raise ValueError(f"{name} must be a positive finite number; got {v!r}")
        object.__setattr__(self, "control_points", cp)
        object.__setattr__(self, "coefficients", co)
        object.__setattr__(self, "model_shift", _readonly(self.model_shift).reshape(2))
        object.__setattr__(self, "subject_shift", _readonly(self.subject_shift).reshape(2))
        object.__setattr__(self, "beta", float(self.beta))
        object.__setattr__(self, "model_scale", float(self.model_scale))
        object.__setattr__(self, "subject_scale", float(self.subject_scale))

    def apply(self, points: ArrayLike) -> FloatArray:
        """Warp points given in the model's (caller's) coordinates.

        Parameters
        ----------
        points : array_like, shape (K, 2)
            Points to warp; ``K`` may be 0.

        Returns
        -------
        ndarray, shape (K, 2)
            Warped points in the subject's (caller's) coordinates.
        """
        return self._warp(points, jacobian=False)[0]

    __call__ = apply

    def apply_with_jacobian(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """The warped points and the warp's Jacobian matrices there, shape (K, 2, 2)
        (``J[k, a, b] = d out_a / d p_b``), from one kernel product
        (:func:`kernel_product`, as for :meth:`apply`)::

            J = s (I + (G (W (x) C) - (G W) z^T) / beta^2),  s = subject_scale / model_scale

        (the derivative of ``exp(-|z - c|^2 / (2 beta^2))`` is the kernel times
        ``(c - z) / beta^2``)."""
        out, jac = self._warp(points, jacobian=True)
        assert jac is not None
        return out, jac

    def _warp(self, points: ArrayLike, jacobian: bool) -> tuple[FloatArray, FloatArray | None]:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must have shape (k, 2); got {p.shape}")
        z = (p - self.model_shift) / self.model_scale
        out = z.copy()
        cp, w = self.control_points, self.coefficients
        # [W | W_a C_b]: the kernel product gives the displacement and, for the Jacobian,
        # sum_k g_k W_ka C_kb in one pass
        rhs = np.concatenate([w, (w[:, :, None] * cp[:, None, :]).reshape(-1, 4)], axis=1) \
            if jacobian else w
        prod = kernel_product(z, cp, rhs, self.beta)
        out += prod[:, :2]
        jac = None
        if jacobian:
            jac = (prod[:, 2:].reshape(-1, 2, 2) - prod[:, :2, None] * z[:, None, :]) \
                / self.beta**2
        out *= self.subject_scale
        out += self.subject_shift
        if jac is not None:
            jac[:, 0, 0] += 1.0
            jac[:, 1, 1] += 1.0
            jac *= self.subject_scale / self.model_scale
        return out, jac

    def __repr__(self) -> str:  # short: the arrays are not printed
        return (
            f"NonrigidTransform(control_points={points_text(self.control_points)}, "
            f"beta={number_text(self.beta)}, model_scale={number_text(self.model_scale)}, "
            f"subject_scale={number_text(self.subject_scale)})"
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable representation (nested lists of floats).

        Returns
        -------
        dict
            Keys ``kind``, ``version``, ``beta``, ``control_points``, ``coefficients``,
            ``model_shift``, ``model_scale``, ``subject_shift``, ``subject_scale``.
        """
        return {
            "kind": "cpd_nonrigid",
            "version": 1,
            "beta": self.beta,
            "control_points": self.control_points.tolist(),
            "coefficients": self.coefficients.tolist(),
            "model_shift": self.model_shift.tolist(),
            "model_scale": self.model_scale,
            "subject_shift": self.subject_shift.tolist(),
            "subject_scale": self.subject_scale,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> NonrigidTransform:
        """Rebuild a transform from :meth:`to_dict` output.

        Parameters
        ----------
        data : dict
            As returned by :meth:`to_dict` (possibly after a JSON round trip).

        Returns
        -------
        NonrigidTransform
        """
        if data.get("kind") != "cpd_nonrigid" or data.get("version") != 1:
            raise ValueError(
                "not a serialised NonrigidTransform (expected kind 'cpd_nonrigid', version 1); "
                f"got kind={data.get('kind')!r}, version={data.get('version')!r}"
            )
        cp = np.asarray(data["control_points"], dtype=np.float64).reshape(-1, 2)
        co = np.asarray(data["coefficients"], dtype=np.float64).reshape(-1, 2)
        return cls(
            control_points=cp,
            coefficients=co,
            beta=float(data["beta"]),
            model_shift=np.asarray(data["model_shift"], dtype=np.float64),
            model_scale=float(data["model_scale"]),
            subject_shift=np.asarray(data["subject_shift"], dtype=np.float64),
            subject_scale=float(data["subject_scale"]),
        )


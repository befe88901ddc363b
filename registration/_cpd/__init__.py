"""Coherent Point Drift, non-rigid (Myronenko & Song 2010), in numpy/scipy.

This package implements the Gaussian-RBF non-rigid CPD of the reference MATLAB code
(``cpd_GRBF.m`` called from ``cpd_register.m``) with the same defaults and stopping rule,
plus four optional accelerations, each exact to within a stated tolerance of the dense
float64 computation:

* a vectorised, chunked E-step: the exponents ``-|x - t|^2 / (2 sigma^2)`` of one block of
  subject points come out of a single BLAS product of augmented 4-column matrices (no
  ``M x N x D`` temporary), the exponential is taken in place, and ``P1``, ``Pt1`` and ``P X``
  come out of one more product, without ever normalising ``P`` explicitly;
* a low-rank kernel ``G ~= U U^T`` (pivoted Cholesky without forming ``G``, rank chosen
  by a trace tolerance) with the Woodbury M-step of the paper's fast variant;
* a grid E-step while sigma is wide: a Chebyshev-grid fast Gauss transform
  (:mod:`._fgt`), linear in the points;
* a truncated E-step once sigma is small: only pairs closer than a radius derived from a
  rigorous bound on the dropped mass are evaluated (pairs from a cell list,
  :mod:`._neighbours`, kept as a CSR kernel while the centroids move little), giving a sparse ``P``;
  its passes over the pair list are compiled (:mod:`._ckernel`, optional: numpy's when it
  is not built), as are the dense E-step, the final correspondences, the field's dense
  kernel product and the pivoted Cholesky factor (one pass over the pairs through a
  vectorised exp instead of numpy's product, clamp, exp and products).

The cheapest allowed E-step is chosen on every iteration from estimated costs
(``_estep.run_estep``).

Conventions: ``model`` is ``Y`` in the CPD paper (M x 2, the GMM centroids, the set that
moves) and ``subject`` is ``X`` (N x 2, the data).  The kernel is
``G[i, j] = exp(-|y_i - y_j|^2 / (2 beta^2))`` and the transform is ``T = Y + G W``.

Modules, by seam: :mod:`._nonrigid` (:func:`cpd_nonrigid`, its EM loop and
:class:`CPDResult`), :mod:`._options` (:class:`CPDOptions` and the validation of every
option), :mod:`._estep` (the E-step engine), :mod:`._mstep` (dense and low-rank M-step),
:mod:`._field` (:class:`NonrigidTransform`) and :mod:`._pycpd` (the pycpd backend).
"""

from ._field import NonrigidTransform
from ._nonrigid import CPDResult, cpd_nonrigid, interpolating_field
from ._options import DTYPES, MIXTURES, CPDOptions, Range
from ._switch import compiled_kernel, compiled_simd

__all__ = ["DTYPES", "MIXTURES", "CPDOptions", "CPDResult", "NonrigidTransform", "Range",
           "compiled_kernel", "compiled_simd", "cpd_nonrigid", "interpolating_field"]

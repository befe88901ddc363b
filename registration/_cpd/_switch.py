"""CPD's compiled passes (:mod:`._ckernel`) and the one switch that every pass reads.

``CKERNEL`` is the compiled module in use, or None: numpy then runs the same sums (also
with ``REGTREE_NO_CKERNEL=1`` in the environment, read at import). Every pass (the E-step's,
the Chebyshev grids', the field's products, the low-rank factor and M-step, the nearest
neighbours of e and of the similarity's ICP) reads it at each call, through
:func:`compiled`, so that setting it (as the tests do) switches them all at once. A leaf
module: the passes import it, it imports none of them.
"""

from __future__ import annotations

import os
from typing import Any

#: The compiled module as built, whether in use or not (None: not built; setup.py builds it
#: when a C compiler is there).
BUILT: Any
try:
    from . import _ckernel as BUILT
except ImportError:  # pragma: no cover - depends on the install
    BUILT = None
#: The compiled passes in use: None runs the same computation with numpy.
CKERNEL: Any = None if os.environ.get("REGTREE_NO_CKERNEL") == "1" else BUILT


def compiled() -> Any:
    """The compiled passes in use (:data:`CKERNEL`), or None for numpy's, looked up at
    each call."""
    return CKERNEL


def compiled_kernel() -> bool:
    """Whether CPD runs its compiled passes (the E-step, dense and truncated, with the
    truncated one's neighbour list searched and pruned, the Chebyshev grids' interpolation
    weights, the final correspondences, the field's dense kernel product, the low-rank
    factor and the low-rank M-step; also the nearest neighbours of e, eq. 10, and of the
    similarity's affine ICP, and the farthest-point subsamples of the coarse stage).

    ``registration._cpd._ckernel`` is built at install when a C compiler is present; without
    it (or with ``REGTREE_NO_CKERNEL=1`` set before the import) numpy runs the same sums,
    equal to rounding (1e-11 relative in float64; float32 runs within their 1e-5), in
    about twice the truncated step's time at thousands of points and 2-3x the dense
    E-step's.

    Returns
    -------
    bool
        True when the compiled passes are in use.
    """
    return CKERNEL is not None


def compiled_simd() -> str | None:
    """The instruction set CPD's compiled passes run with on this machine.

    :mod:`._ckernel` is built in several clones and the CPU picks one at import: with GCC
    12 or later ``"x86-64-v4"`` (AVX-512 with FMA), ``"x86-64-v3"`` (AVX2 with FMA) or
    ``"baseline"``; older GCC and clang builds name their clone's feature (``"avx512f"``,
    ``"avx2"``, ``"fma"``), without FMA. The dense pass takes about twice as long a pair
    without FMA (bench/RESULTS.md 7.20): benchmarks and the service's workers report this
    beside their times, so that figures from different machines can be compared.

    Returns
    -------
    str or None
        The clone's name, or None when numpy runs the passes (see :func:`compiled_kernel`).
    """
    return None if CKERNEL is None else str(CKERNEL.simd())

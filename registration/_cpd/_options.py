"""CPD's options and their one validation.

:class:`CPDOptions` is what the tree methods run CPD with and what the service's
``CPDParams`` accepts; :func:`~registration.cpd_nonrigid` validates the same options through
it.  Every rule is stated once, in :data:`CPDOptions.RANGES` and :data:`DTYPES`, and
:meth:`CPDOptions.check` is the one place that enforces it (a ``ValueError`` naming the
option, the rule and the value).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np

#: Precisions of CPD's E-step.
DTYPES = ("float64", "float32")
#: CPD's mixture weights by name (:attr:`CPDOptions.mixture_weights`): every centroid
#: alike, or each weighted by the outline length it stands for.
MIXTURES = ("uniform", "sampling")
BACKENDS = ("native", "pycpd")


@dataclass(frozen=True)
class Range:
    """The allowed values of a numeric option: ``low (<|<=) value (<|<=) high``.

    ``None`` is an open end; ``integer`` asks for an integral value.
    """

    low: float | None = None
    low_closed: bool = True
    high: float | None = None
    high_closed: bool = True
    integer: bool = False

    def __contains__(self, value: float) -> bool:
        if self.low is not None and not (value >= self.low if self.low_closed
                                         else value > self.low):
            return False
        return self.high is None or (value <= self.high if self.high_closed
                                     else value < self.high)

    def rule(self, name: str) -> str:
        """The rule in words, as the error message states it: ``"be > 0"``, ``"satisfy
        0 <= w < 1"``, ``"be an integer >= 1"``."""
        lo = "" if self.low is None else f"{self.low:g} {'<=' if self.low_closed else '<'} "
        hi = "" if self.high is None else f" {'<=' if self.high_closed else '<'} {self.high:g}"
        if lo and hi:
            return f"satisfy {lo}{name}{hi}"
        bound = (f"{'>=' if self.low_closed else '>'} {self.low:g}" if self.low is not None
                 else hi.strip())
        return f"be {'an integer ' if self.integer else ''}{bound}"


def _real(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number; got {value!r}")
    f = float(value)
    if not math.isfinite(f):
        raise ValueError(f"{name} must be finite; got {value!r}")
    return f


@dataclass(frozen=True)
class CPDOptions:
    """Options of the CPD non-rigid registration (:func:`~registration.cpd_nonrigid`), as
    the tree methods run it on every edge.

    The algorithm's defaults follow the reference MATLAB implementation of Myronenko & Song
    (2010); the E-step runs in float32 unless ``dtype="float64"`` (``cpd_nonrigid`` called
    on its own defaults to float64).

    Raises
    ------
    ValueError
        If an option breaks its rule (:attr:`RANGES`, :data:`DTYPES`); the message names
        the option, the rule and the value.
    """

    beta: float = 2.0
    lmbda: float = 3.0
    w: float = 0.1
    max_iter: int = 150
    #: ``0`` runs exactly ``max_iter`` iterations (unless sigma^2 reaches its floor).
    tol: float = 1e-5
    #: Precision of CPD's E-step (see :func:`cpd_nonrigid`). float32 by default: on the 73
    #: 永 edge glyphs (400 points) it built the same tree as float64 (72 of 72 parents), e
    #: within 2e-5 relative, 1.35x faster end to end (bench/RESULTS.md).
    dtype: str = "float32"
    #: The mixture's weights (:func:`~registration.cpd_nonrigid`'s ``mixture_weights``):
    #: ``"uniform"`` (every model point's Gaussian alike, as CPD), ``"sampling"`` (each
    #: weighted by the outline length it stands for), or None: the method's own,
    #: ``"sampling"`` for the dynamic tree, ``"uniform"`` for the baselines (direct CPD,
    #: the static tree), which stay the paper's.
    mixture_weights: str | None = None

    #: The allowed values of each numeric option.
    RANGES: ClassVar[dict[str, Range]] = {
        "beta": Range(low=0.0, low_closed=False),
        "lmbda": Range(low=0.0, low_closed=False),
        "w": Range(low=0.0, high=1.0, high_closed=False),
        "max_iter": Range(low=1, integer=True),
        "tol": Range(low=0.0),
    }

    def __post_init__(self) -> None:
        for f in fields(self):
            self.check(f.name, getattr(self, f.name))

    def keywords(self, **overrides: Any) -> dict[str, Any]:
        """Every option as :func:`~registration.cpd_nonrigid`'s keyword arguments, with
        `overrides` in their place (a polish stage's narrower ``beta``, for example), so
        that every CPD run with these options gets each of them, one added later too."""
        return {**{f.name: getattr(self, f.name) for f in fields(self)}, **overrides}

    @classmethod
    def check(cls, name: str, value: Any) -> Any:
        """Return ``value`` if it is allowed for option ``name``, else raise ``ValueError``."""
        if name == "dtype":
            if not isinstance(value, str) or value not in DTYPES:
                raise ValueError(f"dtype must be 'float64' or 'float32'; got {value!r}")
            return value
        if name == "mixture_weights":
            if value is not None and (not isinstance(value, str) or value not in MIXTURES):
                raise ValueError(f"mixture_weights must be 'uniform', 'sampling' or None; "
                                 f"got {value!r}")
            return value
        allowed = cls.RANGES[name]
        if allowed.integer:
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) \
                    or int(value) not in allowed:
                raise ValueError(f"{name} must {allowed.rule(name)}; got {value!r}")
            return value
        if _real(name, value) not in allowed:
            raise ValueError(f"{name} must {allowed.rule(name)}; got {value!r}")
        return value


def check_run_options(sigma2: Any, num_eig: Any, backend: Any, low_rank: Any, truncate: Any,
                      normalize: Any, callback: Any, m: int, gauss_grid: Any = None) -> None:
    """Validate the options of one :func:`cpd_nonrigid` call beyond :class:`CPDOptions`
    (``m`` is the number of model points, the largest rank)."""
    if sigma2 is not None and _real("sigma2", sigma2) <= 0:
        raise ValueError(f"sigma2 must be > 0 or None; got {sigma2!r}")
    if num_eig is not None and (isinstance(num_eig, bool)
                                or not isinstance(num_eig, numbers.Integral)
                                or not 1 <= int(num_eig) <= m):
        raise ValueError(f"num_eig must be None or an integer in [1, {m}]; got {num_eig!r}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be 'native' or 'pycpd'; got {backend!r}")
    for name, v in (("low_rank", low_rank), ("truncate", truncate),
                    ("gauss_grid", gauss_grid)):
        if v is not None and not isinstance(v, bool | np.bool_):
            raise ValueError(f"{name} must be True, False or None; got {v!r}")
    if not isinstance(normalize, bool | np.bool_):
        raise ValueError(f"normalize must be True or False; got {normalize!r}")
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable or None; got {callback!r}")

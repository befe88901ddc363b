"""CPD's options are validated once (CPDOptions.check): cpd_nonrigid, CPDOptions and the
service's CPDParams (tests/service/test_cpd_params.py) refuse the same values with the same
message."""

from __future__ import annotations

import re
from dataclasses import asdict
from typing import Any

import numpy as np
import pytest

from registration import CPDOptions, cpd_nonrigid

#: (option, bad value, the message's start); each value breaks exactly one rule.
BAD_OPTIONS: list[tuple[str, Any, str]] = [
    ("beta", 0.0, "beta must be > 0; got 0.0"),
    ("beta", -2, "beta must be > 0; got -2"),
    ("beta", float("inf"), "beta must be finite; got inf"),
    ("beta", "2", "beta must be a real number; got '2'"),
    ("lmbda", 0.0, "lmbda must be > 0; got 0.0"),
    ("w", -0.1, "w must satisfy 0 <= w < 1; got -0.1"),
    ("w", 1.0, "w must satisfy 0 <= w < 1; got 1.0"),
    ("w", True, "w must be a real number; got True"),
    ("max_iter", 0, "max_iter must be an integer >= 1; got 0"),
    ("max_iter", 2.5, "max_iter must be an integer >= 1; got 2.5"),
    ("tol", -1e-3, "tol must be >= 0; got -0.001"),
    ("tol", float("nan"), "tol must be finite; got nan"),
    ("dtype", "float16", "dtype must be 'float64' or 'float32'; got 'float16'"),
]


def _shape(k: int, seed: int) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    r = 1 + 0.2 * np.cos(3 * t + seed)
    return np.column_stack([np.cos(t) * r, 0.7 * np.sin(t) * r])


@pytest.mark.parametrize(("name", "value", "message"), BAD_OPTIONS)
def test_every_surface_refuses_a_bad_option_with_the_same_message(
    name: str, value: Any, message: str
) -> None:
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        CPDOptions(**{name: value})
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        CPDOptions.check(name, value)
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        cpd_nonrigid(_shape(10, 0), _shape(12, 1), **{name: value})


def test_the_limits_of_every_range_are_allowed() -> None:
    options = CPDOptions(beta=1e-9, lmbda=1e-9, w=0.0, max_iter=1, tol=0.0, dtype="float64")
    assert asdict(options) == {"beta": 1e-9, "lmbda": 1e-9, "w": 0.0, "max_iter": 1,
                               "tol": 0.0, "dtype": "float64", "mixture_weights": None}
    assert CPDOptions(w=0.999999).w == 0.999999
    assert CPDOptions(max_iter=np.int64(3)).max_iter == 3


def test_tol_zero_runs_exactly_max_iter_iterations_everywhere() -> None:
    """Once refused by CPDOptions and the service although cpd_nonrigid documents it."""
    options = CPDOptions(tol=0, max_iter=7)
    res = cpd_nonrigid(_shape(30, 0), _shape(35, 1), **asdict(options))
    assert res.iterations == 7 and not res.converged


def test_every_option_has_a_rule_and_a_default_that_passes_it() -> None:
    defaults = asdict(CPDOptions())
    assert set(CPDOptions.RANGES) | {"dtype", "mixture_weights"} == set(defaults)
    for name, value in defaults.items():
        assert CPDOptions.check(name, value) == value
    assert CPDOptions.RANGES["w"].rule("w") == "satisfy 0 <= w < 1"
    assert CPDOptions.RANGES["max_iter"].rule("max_iter") == "be an integer >= 1"


def test_keywords_give_every_option_to_cpd_nonrigid_with_the_overrides() -> None:
    o = CPDOptions(beta=1.5, mixture_weights="sampling")
    kw = o.keywords(beta=0.75)
    assert kw == {**asdict(o), "beta": 0.75}
    model = np.c_[np.cos(np.linspace(0, 6, 40)), np.sin(np.linspace(0, 6, 40))]
    a = cpd_nonrigid(model, model * 1.1, **kw)
    b = cpd_nonrigid(model, model * 1.1, beta=0.75, lmbda=o.lmbda, w=o.w, max_iter=o.max_iter,
                     tol=o.tol, dtype=o.dtype, mixture_weights="sampling")
    np.testing.assert_array_equal(a.warped, b.warped)


def test_model_frame_normalises_the_model_as_given() -> None:
    """``model_frame`` replaces the model's own centroid and radius in the normalisation;
    its own gives the default run, bit for bit, and the transform carries the frame."""
    from registration._cpd._nonrigid import _normalisation

    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    model = np.c_[np.cos(t), 0.6 * np.sin(t)]
    subject = 1.2 * model + 0.1 * np.c_[np.sin(3 * t), np.cos(2 * t)] + [0.3, -0.2]
    own = cpd_nonrigid(model, subject, max_iter=30)
    same = cpd_nonrigid(model, subject, max_iter=30, model_frame=_normalisation(model))
    assert np.array_equal(own.warped, same.warped)
    shift, scale = np.array([0.3, -0.2]), 1.2 * float(_normalisation(model)[1])
    framed = cpd_nonrigid(model, subject, max_iter=30, model_frame=(shift, scale))
    assert np.array_equal(framed.transform.model_shift, shift)
    assert framed.transform.model_scale == scale
    assert np.allclose(framed.transform.apply(model), framed.warped, atol=1e-8)
    assert not np.allclose(framed.warped, own.warped, atol=1e-6)


@pytest.mark.parametrize("frame, normalize, message", [
    (([0.0, 0.0], 1.0), False, "model_frame needs normalize=True"),
    (([0.0, 0.0, 0.0], 1.0), True, "model_frame's shift must be 2 finite numbers"),
    (([0.0, np.nan], 1.0), True, "model_frame's shift must be 2 finite numbers"),
    (([0.0, 0.0], 0.0), True, "model_frame's scale must be finite and > 0"),
    (([0.0, 0.0], np.inf), True, "model_frame's scale must be finite and > 0"),
    ("frame", True, "model_frame must be (shift, scale)"),
])
def test_a_bad_model_frame_is_refused(frame: Any, normalize: bool, message: str) -> None:
    t = np.linspace(0, 2 * np.pi, 20, endpoint=False)
    model = np.c_[np.cos(t), np.sin(t)]
    with pytest.raises(ValueError, match=re.escape(message)):
        cpd_nonrigid(model, model, model_frame=frame, normalize=normalize)

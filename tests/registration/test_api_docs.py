"""The public API is documented in numpydoc style: a stable contract for notebook users."""

from __future__ import annotations

import inspect

import pytest

import registration

FUNCTIONS = [
    name for name in registration.__all__ if inspect.isfunction(getattr(registration, name))
]
CLASSES = [name for name in registration.__all__ if inspect.isclass(getattr(registration, name))]


@pytest.mark.parametrize("name", FUNCTIONS)
def test_public_function_has_numpydoc_sections(name: str) -> None:
    fn = getattr(registration, name)
    doc = inspect.getdoc(fn) or ""
    assert doc, f"{name} has no docstring"
    params = [p for p in inspect.signature(fn).parameters.values() if p.name != "self"]
    if params:
        assert "Parameters\n----------" in doc, f"{name}: no Parameters section"
        for p in params:
            assert p.name in doc, f"{name}: parameter {p.name!r} is not documented"
    assert "Returns\n-------" in doc, f"{name}: no Returns section"


@pytest.mark.parametrize("name", CLASSES)
def test_public_class_is_documented(name: str) -> None:
    assert (inspect.getdoc(getattr(registration, name)) or "").strip(), f"{name}: no docstring"


@pytest.mark.parametrize("name", FUNCTIONS)
def test_public_function_options_are_keyword_only(name: str) -> None:
    """Options grow as keyword-only arguments, so positional calls keep working."""
    params = list(inspect.signature(getattr(registration, name)).parameters.values())
    positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    assert len(positional) <= 3, f"{name}: {len(positional)} positional parameters"

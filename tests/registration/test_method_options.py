"""The methods' shared keyword options come from one table (registration._tree._options):
their runtime signature, their documentation, unknown keywords and defaults."""

from __future__ import annotations

import inspect
import pydoc
import re

import numpy as np
import pytest

from registration import (
    CPDOptions,
    SerialExecutor,
    build_dynamic_tree,
    build_static_tree,
    register_direct,
)
from registration._tree._options import MethodOptions, TreeOptions, takes_options
from registration._tree._resolution import DEFAULT_WORKING_POINTS

METHODS = [build_dynamic_tree, build_static_tree, register_direct]
#: Every method's keyword options and defaults, as the methods declared them one by one
#: before the table: the table must keep them.
SHARED = {
    "similarity_threshold": None, "error_threshold": None, "cpd": None, "prealign": True,
    "pose": None, "max_rotation": None, "compare_direct": False, "names": None,
    "working_points": DEFAULT_WORKING_POINTS, "executor": None, "progress": None,
}
KEYWORDS = {
    build_dynamic_tree: {**SHARED, "candidates": None, "max_candidates": 3,
                         "fold_check": True, "refine": True, "polish": True},
    build_static_tree: {**SHARED, "candidates": None},
    register_direct: SHARED,
}


def _shapes(n: int = 4) -> list[np.ndarray]:
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    return [np.c_[np.cos(t) * (1 + 0.05 * k), np.sin(t)] for k in range(n)]


@pytest.mark.parametrize("fn", METHODS)
def test_signature_lists_every_option_with_its_default(fn) -> None:
    params = inspect.signature(fn).parameters
    assert list(params)[:2] == ["shapes", "root"]
    assert params["shapes"].default is inspect.Parameter.empty
    assert params["root"].default == 0
    assert params["root"].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
    keywords = {name: p.default for name, p in params.items() if name not in ("shapes", "root")}
    assert keywords == KEYWORDS[fn]
    assert all(params[name].kind is inspect.Parameter.KEYWORD_ONLY for name in keywords)
    assert not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    assert params["cpd"].annotation == "CPDOptions | None"


@pytest.mark.parametrize("fn", METHODS)
def test_help_shows_every_option_and_documents_each_in_full(fn) -> None:
    text = pydoc.render_doc(fn, renderer=pydoc.plaintext)
    assert "working_points: 'int | None' = 400" in text
    doc = inspect.getdoc(fn) or ""
    section = doc.split("Parameters\n----------\n")[1].split("\n\nReturns")[0]
    entries = re.findall(r"^(\w+) : (.+)\n((?:    .+\n?)+)", section, re.MULTILINE)
    assert [name for name, _, _ in entries] == list(inspect.signature(fn).parameters)
    assert all(body.strip() for _, _, body in entries)  # no bare "name : type"
    assert "As for" not in doc
    for name, kind, _ in entries:
        if name in MethodOptions.__annotations__ or name in TreeOptions.__annotations__:
            assert kind in {"float, optional", "CPDOptions, optional", "bool", "int or None",
                            "int, optional", "sequence of str, optional",
                            "Executor, optional", "callable(stage, done, total), optional",
                            '{"rotation", "as_given", "upright", "affine"}, optional'}


def test_methods_document_what_they_ignore() -> None:
    static = inspect.getdoc(build_static_tree) or ""
    assert "error_threshold : float, optional\n    Ignored (the static tree rejects" in static
    direct = inspect.getdoc(register_direct) or ""
    for name in ("similarity_threshold", "error_threshold", "compare_direct"):
        assert re.search(rf"^{name} : .+\n    Ignored;", direct, re.MULTILINE), name
    dynamic = inspect.getdoc(build_dynamic_tree) or ""
    assert "error_threshold : float, optional\n    A registration is accepted" in dynamic


@pytest.mark.parametrize("fn", METHODS)
def test_unknown_keyword_is_a_type_error_as_python_raises_it(fn) -> None:
    with pytest.raises(TypeError, match=rf"^{fn.__name__}\(\) got an unexpected keyword "
                                        r"argument 'similarity'$"):
        fn(_shapes(), 0, similarity=0.1)


def test_tree_only_options_stay_specific() -> None:
    with pytest.raises(TypeError, match=r"^register_direct\(\) got an unexpected keyword "
                                        r"argument 'candidates'$"):
        register_direct(_shapes(), 0, candidates=3)
    with pytest.raises(TypeError, match=r"^build_static_tree\(\) got an unexpected keyword "
                                        r"argument 'max_candidates'$"):
        build_static_tree(_shapes(), 0, max_candidates=3)
    with pytest.raises(TypeError, match="got multiple values for argument 'root'"):
        register_direct(_shapes(), 0, root=1)
    with pytest.raises(TypeError, match="positional"):
        register_direct(_shapes(), 0, None)


@pytest.mark.parametrize("fn", METHODS)
def test_wrong_values_are_still_precise_value_errors(fn) -> None:
    with pytest.raises(ValueError, match=r"working_points must be None, 0 or an integer"):
        fn(_shapes(), 0, working_points=-5)
    with pytest.raises(ValueError, match=r"names has 2 entries for 4 shapes"):
        fn(_shapes(), 0, names=["a", "b"])


def test_positional_and_keyword_calls_run_with_the_table_defaults() -> None:
    seen: list[str] = []
    fast = CPDOptions(max_iter=20)
    direct = register_direct(_shapes(), 0, cpd=fast, executor=SerialExecutor(),
                             progress=lambda stage, done, total: seen.append(stage))
    assert direct.method == "direct" and seen
    assert direct.options["affine_prealign"] is True  # prealign's default
    static = build_static_tree(_shapes(), root=0, cpd=fast, prealign=False)
    assert static.options["affine_prealign"] is False and static.direct is None
    assert [s.name for s in static.subjects] == ["shape-1", "shape-2", "shape-3"]


def test_takes_options_refuses_a_method_it_cannot_describe() -> None:
    def bad(shapes, root=0, *, cpd=None, **options):  # an option declared twice
        """Bad.

        Returns
        -------
        None
        """

    with pytest.raises(ValueError, match="not repeat an option"):
        takes_options(MethodOptions)(bad)
    with pytest.raises(ValueError, match="'nope' is not one of the options"):
        takes_options(MethodOptions, ignored={"nope": "Ignored."})

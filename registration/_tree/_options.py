"""The keyword options the three methods share, in one table.

:class:`MethodOptions` (every method) and :class:`TreeOptions` (the two trees) are that
table: each field is an option's name and type, and its :class:`Option` (the ``Annotated``
metadata) holds its default and its documentation. :func:`takes_options` makes of it, for
a method declared ``def method(shapes, root=0, *, <its own options>, **options:
Unpack[TreeOptions])``:

- the typing of its callers' keywords (PEP 692: mypy checks each name and type);
- its runtime signature (``inspect.signature``, ``help()``, Sphinx), every option listed
  with its default;
- the options' entries in its docstring's "Parameters" section;
- its call: an unknown keyword raises TypeError as Python does, and the method's body gets
  every option, the table's default for those not given (``options["cpd"]``).
"""

from __future__ import annotations

import functools
import inspect
import re
import textwrap
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, ParamSpec, TypedDict, TypeVar, get_args, get_type_hints

from .._cpd import CPDOptions
from .._executor import Executor
from .._similarity import ProgressCallback
from ._resolution import DEFAULT_WORKING_POINTS

P = ParamSpec("P")
R = TypeVar("R")

__all__ = ["COLLECTION_PARAMETERS", "MethodOptions", "Option", "TreeOptions", "takes_options"]


@dataclass(frozen=True)
class Option:
    """An option's default and its numpydoc entry: `kind` after ``name :``, `doc` (a
    docstring-style block, dedented when rendered) below it."""

    default: Any
    kind: str
    doc: str


class MethodOptions(TypedDict, total=False):
    """The keyword options every method takes (the table; see the module docstring)."""

    similarity_threshold: Annotated[float | None, Option(None, "float, optional", """
        A subject is similar to a member when ``D[member, subject]`` (eq. 9, normalised
        shapes) is at most this. Default: automatic, per pair: the largest of CPD's
        measured capture range (D = 0.01), the D from the subject's 4th nearest shape and
        the D to the member's 4th nearest shape (see `_SimilarityRule`); a subject no
        path of such pairs reaches from the root (a collection of tight groups, e.g.
        several impressions of each design) takes instead its bottleneck D from the
        root, so the nearest pairs between groups count as similar
        (``thresholds["bridged"]``: how many subjects).""")]
    error_threshold: Annotated[float | None, Option(None, "float, optional", """
        A registration is accepted when e (eq. 10, normalised shapes) is below this.
        Default: automatic, ``3 x`` the lower quartile of the second layer's e, and never
        below half the subject's squared point spacing.""")]
    cpd: Annotated[CPDOptions | None, Option(None, "CPDOptions, optional", """
        CPD's options for every registration; default ``CPDOptions()``.""")]
    prealign: Annotated[bool, Option(True, "bool", """
        Pose handling: CPD from the pose as given, and also from the similarity's
        affine-ICP map when that is another pose that fits clearly better (see `pose`).
        False: CPD from the pose as given only (the paper's plain CPD).""")]
    pose: Annotated[str | None, Option(
        None, '{"rotation", "as_given", "upright", "affine"}, optional', """
        Which poses may be tried (see :mod:`registration._pose`): any rotation (default),
        the shapes as given only, rotations within +-`max_rotation` of them, or any affine
        map including reflections (the paper's ``det(A) != 0``). Outside "affine" the
        affine ICP never mirrors. The pose as given is always registered; another pose is
        tried when its D is below 0.6 of the pose as given's and replaces it only when
        CPD from it reaches less than 0.7 of the pose as given's e (no larger an e where
        CPD from the pose as given folds clearly).""")]
    max_rotation: Annotated[float | None, Option(None, "float, optional", """
        Half-width in degrees of the "upright" mode (default 30); given alone, it
        selects that mode (glyph scans, aligned outlines).""")]
    compare_direct: Annotated[bool, Option(False, "bool", """
        Also run direct CPD from the root on every subject, for comparison (a dynamic
        tree runs it before its polish, whose consensus reuses it, and with the tree's
        CPD options: its weighted mixture too, unlike ``register_direct``'s).""")]
    names: Annotated[Sequence[str] | None, Option(None, "sequence of str, optional", """
        A name for each shape, in the result and its messages; default ``shape-<k>``.""")]
    working_points: Annotated[int | None, Option(DEFAULT_WORKING_POINTS, "int or None", """
        Decide the tree (direct CPD: each pose) at this many points per shape, then
        register each of its edges once at the stored resolution, warm-started from the
        decision's registration (see :mod:`registration._tree._resolution`). Shapes
        with at most this many points are used as they are; None or 0 decides at the
        stored resolution. The result's
        warped points, correspondences, transforms and e are at the stored resolution; its
        attempts, thresholds, similarity, confidence and quality checks are the working
        resolution's (the confidence is calibrated on shapes of a few hundred points).""")]
    executor: Annotated[Executor | None, Option(None, "Executor, optional", """
        Where ICP and CPD run; default: serial for small jobs, else a local process pool.
        """)]
    progress: Annotated[ProgressCallback | None, Option(
        None, "callable(stage, done, total), optional", """
        Called as work completes; an exception it raises stops the run and propagates.""")]


class TreeOptions(MethodOptions, total=False):
    """The keyword options of the two tree methods: every method's, and `candidates`."""

    candidates: Annotated[int | None, Option(None, "int, optional", """
        Only pairs joining each shape to its `candidates` nearest by a cheap descriptor
        are considered (and the root to every subject). Default: all pairs for up to 64
        shapes, 12 nearest beyond.""")]


def _table(options: Any) -> dict[str, tuple[Any, Option]]:
    """Each field of a TypedDict of options: its type and its :class:`Option`."""
    table = {}
    for name, hint in get_type_hints(options, include_extras=True).items():
        kind, *extras = get_args(hint)
        (option,) = (x for x in extras if isinstance(x, Option))
        table[name] = (kind, option)
    return table


def _type_text(kind: Any) -> str:
    """A type as its source spells it (``CPDOptions | None``), without module paths."""
    text = inspect.formatannotation(kind).replace("NoneType", "None")
    return re.sub(r"\b(?:[A-Za-z_]\w*\.)+(?=[A-Za-z_])", "", text)


#: The two parameters every method starts with (positional or keyword): their numpydoc
#: entries (:func:`takes_options` puts them first in the "Parameters" section).
COLLECTION_PARAMETERS = {
    "shapes": ("sequence of array_like, shape (n_i, 2)", "The collection, in the user's "
               "coordinates; each shape is size-normalised first."),
    "root": ("int", "Index of the model shape."),
}


def _entry(name: str, kind: str, doc: str) -> str:
    """A numpydoc "Parameters" entry (`doc` is dedented)."""
    return f"{name} : {kind}\n" + textwrap.indent(inspect.cleandoc(doc), "    ")


def _parameters_doc(doc: str, first: list[str], last: list[str]) -> str:
    """`doc` with its "Parameters" section (one is made before "Returns" if it has none)
    between the entries `first` and `last`."""
    doc = inspect.cleandoc(doc)
    end = doc.index("\n\nReturns\n-------")
    head, _, own = doc[:end].partition("\n\nParameters\n----------\n")
    section = [*first, *([own] if own else []), *last]
    return head + "\n\nParameters\n----------\n" + "\n".join(section) + doc[end:]


def takes_options(
    options: Any, *, ignored: Mapping[str, str] | None = None
) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Decorate a method ``(shapes, root, *, <its own options>, **options:
    Unpack[<options>])`` (see the module docstring). Its docstring documents its own
    options only; the "Parameters" section gets `shapes` and `root` before them and the
    shared options after. `ignored` maps an option the method accepts but does not read
    to what its documentation says instead."""
    table = _table(options)
    described = {name: option.doc for name, (_, option) in table.items()}
    for name, text in (ignored or {}).items():
        if name not in table:
            raise ValueError(f"{name!r} is not one of the options")
        described[name] = text
    defaults = {name: option.default for name, (_, option) in table.items()}

    def decorate(fn: Callable[P, R]) -> Callable[P, R]:
        signature = inspect.signature(fn)
        *own, rest = signature.parameters.values()
        leading = [p.name for p in own[:len(COLLECTION_PARAMETERS)]]
        if (leading != list(COLLECTION_PARAMETERS) or rest.kind is not rest.VAR_KEYWORD
                or set(table) & {p.name for p in own}):
            raise ValueError(f"{fn.__name__} must start with (shapes, root), end with "
                             "**options and not repeat an option")
        signature = signature.replace(parameters=[*own, *(
            inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option.default,
                              annotation=_type_text(kind))
            for name, (kind, option) in table.items()
        )])
        accepted = {p.name for p in signature.parameters.values()
                    if p.kind is not p.POSITIONAL_ONLY}

        @functools.wraps(fn)
        def method(*args: P.args, **kwargs: P.kwargs) -> R:
            for name in kwargs:
                if name not in accepted:
                    raise TypeError(
                        f"{fn.__name__}() got an unexpected keyword argument {name!r}")
            return fn(*args, **{**defaults, **kwargs})

        method.__signature__ = signature  # type: ignore[attr-defined]
        if fn.__doc__ is not None:  # None under python -OO
            method.__doc__ = _parameters_doc(
                fn.__doc__,
                [_entry(name, *COLLECTION_PARAMETERS[name]) for name in leading],
                [_entry(name, option.kind, described[name])
                 for name, (_, option) in table.items()],
            )
        return method

    return decorate

"""Results of registering a root model to every shape of a collection."""

from __future__ import annotations

import gc
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._points import Normalization
from ._repr import html_table, number_text, points_text, tree_svg
from ._transform import ChainTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

__all__ = ["Attempt", "CollectionResult", "SubjectResult", "error_statistics"]


@contextmanager
def _collector_paused() -> Iterator[None]:
    """The cyclic garbage collector off while a large document without reference cycles is
    built (then back as it was). A full result is millions of lists and floats: on the 73
    full-resolution 永 glyphs ``CollectionResult.to_dict`` took 0.65-0.99 s with the
    collector walking the growing document every 700 allocations, 0.06-0.14 s without; a
    full collection afterwards included, building the service's document from it took
    0.78-0.90 s instead of 1.4-1.8 (bench/RESULTS.md 7.19)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


@dataclass(frozen=True)
class Attempt:
    """One registration tried while building a tree: member -> subject.

    ``layer`` is the layer the subject would have through this member (the member's plus
    one), whichever round of the tree's growth tried it.
    ``limit`` is the error threshold this attempt was held to (the collection's, or the
    subject's sampling floor when that is larger and the threshold is automatic).
    """

    member: int
    layer: int
    similarity: float
    error: float
    limit: float
    min_jacobian: float
    accepted: bool
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "member": self.member,
            "layer": self.layer,
            "similarity": self.similarity,
            "error": self.error,
            "limit": self.limit,
            "min_jacobian": self.min_jacobian,
            "accepted": self.accepted,
            "reason": self.reason,
        }


@dataclass
class SubjectResult:
    """Where one subject ended up, and the registration of the root model onto it.

    Attributes
    ----------
    index : int
        Position of the subject in the input list.
    name : str
    parent : int or None
        Tree parent (the root for direct CPD); None when unattached.
    layer : int or None
        Tree layer: its depth, the root being layer 1 and every subject one more than its
        parent (the length of `path`); None when unattached.
    path : list of int
        Shape indices from the root to this subject (empty when unattached).
    similarity : float or None
        D (eq. 9) from the parent to this subject, on normalised shapes.
    error : float or None
        e (eq. 10) between the warped root model and the subject, on normalised shapes.
    warped : ndarray, shape (N, 2), or None
        The root model warped onto the subject, in the subject's user coordinates.
    correspondence : ndarray of int, shape (N,), or None
        For each root-model point, the index of its most probable subject point.
    probability : ndarray, shape (N,), or None
        The posterior probability of that correspondence.
    transform : ChainTransform or None
    reason : str
        Why it is attached or not (for unattached subjects, the last rejection).
    attempts : list of Attempt
    confidence : float or None
        Estimated probability that the correspondences are right: the smallest
        calibrated confidence of the registrations on the path from the root (see
        `registration._quality`). Sort and filter by it. See also the property
        :attr:`disagreement`, a second sign from another source.
    leaf : bool
        Attached after the tree stopped growing, from its best registration, without
        being accepted by the tree's rule: a low-confidence leaf, never a parent.
    quality : dict or None
        The checks of the last registration on the path (e/h^2, distortion, anisotropy,
        CPD rotation, coverage, min Jacobian), the pose it started from and the e every
        pose reached; for a polished subject (see ``build_dynamic_tree(polish=...)``)
        also ``polish``: the e before it, its steps and checks, and what its consensus
        with a partner's registration (``partner``: the member's index, or the root's
        for its direct registration), its edge registered again from the polished
        parent, its finish from the root model and its symmetric finish (halfway to the
        subject registered back onto the root) found (each with ``kept`` and a
        ``reason``). When the decisions were taken at a working resolution
        (``working_points``), also ``working_error`` (the e decided on),
        ``stored_min_jacobian`` (the fold check at the stored resolution) and, for the
        dynamic tree's subjects, ``stored_polish``: the polish run again on the stored
        points (as ``polish``, without the consensus, every subject's edge registered
        again there and taken halfway: ``from_parent``; present when it kept a step). The
        symmetric finish records ``without_inverse``: of the root points its step is
        fitted through (every point, or at the stored resolution the 500 control points),
        how many the subject's registration back onto the root has no inverse at, also
        when that ruled the step out; those points move with their neighbours.
    """

    index: int
    name: str
    parent: int | None = None
    layer: int | None = None
    path: list[int] = field(default_factory=list)
    similarity: float | None = None
    error: float | None = None
    warped: FloatArray | None = None
    correspondence: IntArray | None = None
    probability: FloatArray | None = None
    transform: ChainTransform | None = None
    reason: str = ""
    attempts: list[Attempt] = field(default_factory=list)
    confidence: float | None = None
    leaf: bool = False
    quality: dict[str, Any] | None = None

    @property
    def disagreement(self) -> float | None:
        """How far apart two registrations of this subject that err differently put the
        root's points: the polish's forward registration and the subject registered back
        onto the root (its symmetric finish; the one run last, at the stored resolution
        when that recorded one), as the RMS distance in units of the subject's RMS radius.

        A second sign beside ``confidence``, from another source: where the two
        registrations disagree, at least one is off by about that much; where they agree,
        both may still have slid the same way. On the ground-truth chains of
        bench/RESULTS.md 7.38, sorting one collection's subjects by it finds the worst
        registered better than sorting by ``confidence`` on glyph edges and skeletons and
        MPEG-7, about as well on held-out characters and outlines, and worse on
        near-identical instances and generated shapes. The correspondence error is 1.0-1.3
        times it on glyph edges and MPEG-7, 2-5 times on outlines, 0.14-0.18 on the Chui
        series. None when no symmetric finish ran (direct CPD, the static tree,
        ``polish=False``, the root, unattached subjects, or no backward registration).
        """
        q = self.quality or {}
        for record in ("stored_polish", "polish"):
            polish = q.get(record)
            if not isinstance(polish, dict):
                continue
            sym = polish.get("symmetric")
            value = sym.get("disagreement") if isinstance(sym, dict) else None
            if isinstance(value, int | float) and math.isfinite(value):
                return float(value)
        return None

    @property
    def attached(self) -> bool:
        """In the tree: a member, a low-confidence leaf, or the root itself (layer 1)."""
        return self.layer is not None

    def __repr__(self) -> str:  # short: the arrays are not printed
        where = (
            f"layer={self.layer}, parent={self.parent}" if self.attached else "unattached"
        ) + (", leaf" if self.leaf else "")
        return (
            f"SubjectResult(index={self.index}, name={self.name!r}, {where}, "
            f"e={number_text(self.error)}, confidence={number_text(self.confidence)}, "
            f"warped={points_text(self.warped)}, attempts={len(self.attempts)})"
        )

    def _repr_html_(self) -> str:
        return html_table("SubjectResult", [
            ("index", self.index),
            ("name", self.name),
            ("layer", "unattached" if not self.attached else self.layer),
            ("parent", self.parent if self.parent is not None else "-"),
            ("path", " > ".join(map(str, self.path)) or "-"),
            ("D from parent", number_text(self.similarity)),
            ("e", number_text(self.error)),
            ("confidence", number_text(self.confidence)),
            ("disagreement", number_text(self.disagreement)),
            ("leaf", self.leaf),
            ("reason", self.reason),
            ("warped", points_text(self.warped)),
            ("attempts", len(self.attempts)),
        ])

    def to_dict(self, *, include_points: bool = True,
                transform_base: tuple[int, int] | None = None) -> dict[str, Any]:
        """JSON-ready data; `transform_base` as :meth:`ChainTransform.to_dict`'s ``base``."""
        d: dict[str, Any] = {
            "index": self.index,
            "name": self.name,
            "parent": self.parent,
            "layer": self.layer,
            "path": list(self.path),
            "similarity": self.similarity,
            "error": self.error,
            "attached": self.attached,
            "confidence": self.confidence,
            "disagreement": self.disagreement,
            "leaf": self.leaf,
            "reason": self.reason,
            "quality": self.quality,
            "attempts": [a.to_dict() for a in self.attempts],
        }
        if include_points:
            d["warped"] = None if self.warped is None else self.warped.tolist()
            d["correspondence"] = (
                None if self.correspondence is None else self.correspondence.tolist()
            )
            d["probability"] = None if self.probability is None else self.probability.tolist()
            d["transform"] = (None if self.transform is None
                              else self.transform.to_dict(base=transform_base))
        return d


def error_statistics(errors: list[float]) -> dict[str, Any]:
    """Count, mean and 95th percentile of a list of e values, as the paper reports them.

    Parameters
    ----------
    errors : list of float
        Registration errors (eq. 10).

    Returns
    -------
    dict
        ``{"count": int, "mean": float | None, "p95": float | None}``; the 95th
        percentile by linear interpolation; None for an empty list.
    """
    if not errors:
        return {"count": 0, "mean": None, "p95": None}
    arr = np.asarray(errors, dtype=np.float64)
    return {"count": len(errors), "mean": float(arr.mean()), "p95": float(np.percentile(arr, 95))}


@dataclass
class CollectionResult:
    """The registration of a root model to every other shape of a collection.

    Attributes
    ----------
    method : str
        ``"dynamic_tree"``, ``"static_tree"`` or ``"direct"``.
    root : int
    names : list of str
    subjects : list of SubjectResult
        One per non-root shape, in input order.
    thresholds : dict
        ``similarity`` and ``error`` thresholds used, and how they were chosen.
    options : dict
        CPD and ICP options, and whether an affine pre-alignment was used.
    direct : list of SubjectResult or None
        Direct CPD from the root on the same subjects, when requested for comparison.
    similarity_pairs : int
        ICP runs done for the similarity.
    similarity : ndarray, shape (n, n), or None
        The similarity D (eq. 9) the run computed: ``similarity[i, j]`` is D from shape
        ``i`` (moved by the affine map) onto shape ``j``, on normalised shapes, the direction
        the tree uses (member -> subject); NaN for pairs it did not need; 0 on the diagonal.
        Not in :meth:`to_dict` (it is n x n).
    """

    method: str
    root: int
    names: list[str]
    subjects: list[SubjectResult]
    thresholds: dict[str, Any]
    options: dict[str, Any]
    direct: list[SubjectResult] | None = None
    similarity_pairs: int = 0
    similarity: FloatArray | None = field(default=None, repr=False)

    def __repr__(self) -> str:  # short: the arrays are not printed
        c = self.summary()
        deep, every, direct = c["layer_ge_3"], c["all"], c.get("direct")
        root = self.names[self.root] if 0 <= self.root < len(self.names) else self.root
        text = (
            f"CollectionResult(method={self.method!r}, root={self.root} ({root!r}), "
            f"{c['subjects']} subjects: {c['attached']} attached ({c['leaves']} leaves), "
            f"{c['unattached']} unattached, depth {c['depth']}; "
            f"e layer>=3 mean {number_text(deep['mean'])} p95 {number_text(deep['p95'])}, "
            f"all mean {number_text(every['mean'])}"
        )
        if direct is not None:
            text += f"; direct layer>=3 mean {number_text(direct['layer_ge_3']['mean'])}"
        return text + ")"

    def _repr_html_(self) -> str:
        c = self.summary()
        deep, every, direct = c["layer_ge_3"], c["all"], c.get("direct")
        rows: list[tuple[str, Any]] = [
            ("method", self.method),
            ("root", f"{self.root}: {self.names[self.root]}"),
            ("subjects", c["subjects"]),
            ("attached (leaves)", f"{c['attached']} ({c['leaves']})"),
            ("unattached", c["unattached"]),
            ("depth", c["depth"]),
            ("e at layer >= 3: mean / p95",
             f"{number_text(deep['mean'])} / {number_text(deep['p95'])}"),
            ("e, all attached: mean / p95",
             f"{number_text(every['mean'])} / {number_text(every['p95'])}"),
        ]
        if direct is not None:
            d = direct["layer_ge_3"]
            rows.append(("direct CPD, layer >= 3: mean / p95",
                         f"{number_text(d['mean'])} / {number_text(d['p95'])}"))
        nodes = [(self.root, 1, None, "root")] + [
            (s.index, s.layer if s.layer is not None else 0, s.parent,
             "leaf" if s.leaf else ("tree" if s.attached else "unattached"))
            for s in self.subjects
        ]
        return html_table("CollectionResult", rows, after=tree_svg(self.root, self.names, nodes))

    def root_subject(self) -> SubjectResult:
        """The model itself as a subject: layer 1, error 0, the identity transform."""
        norms = [s.transform.source for s in self.subjects if s.transform is not None]
        norm = norms[0] if norms else Normalization(center=(0.0, 0.0), scale=1.0)
        return SubjectResult(
            index=self.root,
            name=self.names[self.root] if 0 <= self.root < len(self.names) else str(self.root),
            layer=1,
            path=[self.root],
            error=0.0,
            transform=ChainTransform.identity(norm, self.root),
            reason="the model (the root of the tree)",
            confidence=1.0,
        )

    def subject(self, index: int) -> SubjectResult:
        """The result for the shape at ``index`` of the input; the root's is
        :meth:`root_subject` (identity transform)."""
        for s in self.subjects:
            if s.index == index:
                return s
        if index == self.root:
            return self.root_subject()
        raise KeyError(f"no subject with index {index}")

    def transform_for(self, index: int) -> ChainTransform:
        """The root-to-subject transform (the identity for the root); ValueError if the
        subject is unattached."""
        s = self.subject(index)
        if s.transform is None:
            raise ValueError(f"subject {index} ({s.name}) is not attached: {s.reason}")
        return s.transform

    def summary(self) -> dict[str, Any]:
        """The paper's statistics: mean and 95th percentile of e at layer >= 3 (the
        subjects where a tree differs from direct CPD), on all attached subjects, per
        layer; and direct CPD's on the same subjects when it was computed."""
        attached = [s for s in self.subjects if s.attached]
        deep = [s for s in attached if s.layer is not None and s.layer >= 3]
        layers: dict[int, list[SubjectResult]] = {}
        for s in attached:
            assert s.layer is not None
            layers.setdefault(s.layer, []).append(s)
        out: dict[str, Any] = {
            "subjects": len(self.subjects),
            "attached": len(attached),
            "leaves": sum(1 for s in attached if s.leaf),
            "unattached": len(self.subjects) - len(attached),
            "depth": max(layers) if layers else 1,
            "layer_ge_3": error_statistics([s.error for s in deep if s.error is not None]),
            "all": error_statistics([s.error for s in attached if s.error is not None]),
            "per_layer": {
                str(k): error_statistics([s.error for s in v if s.error is not None])
                for k, v in sorted(layers.items())
            },
        }
        if self.direct is not None:
            by_index = {s.index: s for s in self.direct}

            def direct_errors(group: list[SubjectResult]) -> list[float]:
                return [
                    e
                    for s in group
                    if (e := by_index[s.index].error) is not None and s.index in by_index
                ]

            out["direct"] = {
                "layer_ge_3": error_statistics(direct_errors(deep)),
                "all": error_statistics(direct_errors(attached)),
                "per_layer": {
                    str(k): error_statistics(direct_errors(v)) for k, v in sorted(layers.items())
                },
            }
        return out

    def to_dict(self, *, include_points: bool = True,
                shared_steps: bool = False) -> dict[str, Any]:
        """A JSON-serialisable document of the whole result.

        ``shared_steps``: each subject's transform holds only the steps after those it
        shares with its parent's, and a ``base`` naming the parent and how many of its
        steps come first (:meth:`ChainTransform.to_dict`); :func:`registration.
        expand_shared_steps` restores the full chain. On the 73 永 edge glyphs this is a
        fraction of the size: each subject's chain otherwise repeats all its ancestors'.
        """
        by_index = {s.index: s for s in self.subjects}

        def base(s: SubjectResult) -> tuple[int, int] | None:
            parent = None if s.parent is None else by_index.get(s.parent)
            if (not shared_steps or parent is None or s.transform is None
                    or parent.transform is None):
                return None
            k = s.transform.shared_steps(parent.transform)
            return (parent.index, k) if k > 0 else None

        with _collector_paused():
            return self._document(include_points, base)

    def _document(self, include_points: bool,
                  base: Callable[[SubjectResult], tuple[int, int] | None]) -> dict[str, Any]:
        return {
            "method": self.method,
            "root": self.root,
            "names": list(self.names),
            "thresholds": dict(self.thresholds),
            "options": dict(self.options),
            "similarity_pairs": self.similarity_pairs,
            "subjects": [s.to_dict(include_points=include_points, transform_base=base(s))
                         for s in self.subjects],
            "direct": None
            if self.direct is None
            else [s.to_dict(include_points=include_points) for s in self.direct],
            "summary": self.summary(),
        }

"""A final polish of each of the tree's registrations: CPD from the root model as warped
along the subject's chain (at layer 2: its one edge) onto the subject, coarse to fine, so
the slide the chain accumulated can relax and a single edge's CPD can finish fitting.

Each edge of a tree path registers the root model, as already warped onto the parent,
onto the child; the error of one link (0.035-0.04 of the subject's size on the 永
deformation chains, near the sampling floor) adds up along the path. After the tree is
built, every attached subject at layer >= ``POLISH_MIN_LAYER`` is registered again, in
the stages of ``POLISH_BETA_FACTORS``: each stage's CPD moves the root's points, where the
previous stage (first: the chain) left them, onto the subject (the tree's CPD options but
a kernel width beta scaled by the stage's factor; the points keep the root's order), with
sigma^2 starting from that start's residual rather than from the spread of all pairs (it
starts aligned). A stage is kept only when it passes the checks the tree holds every
registration to: its warp does not fold, its e is no larger than its start's, and its own
confidence is at least ``MIN_CONFIDENCE``; a finer stage must also lower e by a fifth
(``POLISH_FINER_MAX_E_RATIO``). A rejected stage is skipped: the next starts
where the last kept one (or the chain) left the points. A chain's composed field has more
freedom than one CPD's, so its e can be lower than a wide stage's while its points have
slid: there the finer stage, from the chain, still lowers e and the correspondence error.
Figures: bench/RESULTS.md, sections 0.00 (one stage), 0.000 (coarse to fine) and 0.0000
(layer 2, skipping).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .._cpd import CPDOptions, cpd_nonrigid
from .._error import registration_error
from .._executor import Executor, owned_executor
from .._pointmap import PointTransform
from .._quality import RegistrationQuality, measure_quality
from .._result import SubjectResult
from .._similarity import ProgressCallback
from .._transform import ChainTransform
from ._collection import _Collection
from ._rules import MIN_CONFIDENCE

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Subjects at this tree layer or deeper are polished: every attached subject. Layer 2 is
#: registered from the root directly, so no chain accumulated there, but its CPD stopped
#: at its tolerance from a start far from the subject; restarted from where it stopped
#: (sigma^2 from the residual) it keeps fitting. Ground truth (bench/RESULTS.md 0.0000):
#: Chui fish 0.76 -> 0.26 of plain CPD, Chinese 0.64 -> 0.44, glyph edges and skeletons
#: within +-0.02 (their layer-2 subjects gain little).
POLISH_MIN_LAYER = 2
#: The polish's CPD stages, coarse to fine: the kernel width beta of each as a fraction of
#: the tree's. The first, with the edges' own kernel, relaxes the slide the chain
#: accumulated; the second, from there (already aligned, so a finer kernel cannot wander),
#: fits the finer deformation the edges' smooth kernel leaves out. Each stage is kept only
#: when it passes the checks; a rejected one is skipped.
POLISH_BETA_FACTORS = (1.0, 0.5)
#: A stage with a finer kernel than the first is kept only when its e is at most this
#: fraction of its start's. A finer kernel always lowers e a little: it fits where the
#: subject's own points happen to lie, sliding the model's points along the outline. Over
#: the finer stages of seven ground-truth families (bench/RESULTS.md 0.000000; geometric
#: mean change of the correspondence error), those that lowered e by less than a fifth
#: worsened the correspondences on MPEG-7 (x1.21, 68 stages) and on lmfree2d / Momocs
#: outlines of 80-120 randomly subsampled points (x1.14, 137) and did next to nothing on
#: the 永 edges and skeletons (x0.98, 26); those that lowered it by more than 30 % improved
#: them on every family but those outlines (MPEG-7 x0.81, edges x0.75, skeletons x0.85,
#: Chui x0.14-0.19). With the rule the MPEG-7 chains go from 0.81 to 0.75 of plain CPD
#: (worst run 1.28 -> 1.12) and those outlines from 1.16 to 1.12; every other family
#: moves by at most 0.015.
POLISH_FINER_MAX_E_RATIO = 0.8


@dataclass(frozen=True)
class _PolishTask:
    subject: int
    start: FloatArray  # the root model warped along the chain (subject's normalised coords)
    error: float  # the chained registration's e
    y: FloatArray  # the subject, normalised coordinates
    cpd: CPDOptions
    spacing2: float


@dataclass(frozen=True)
class _PolishOutcome:
    subject: int
    warped: FloatArray
    error: float
    correspondence: IntArray
    probability: FloatArray
    steps: tuple[PointTransform, ...]  # the stages kept, coarse to fine (none: rejected)
    quality: tuple[RegistrationQuality, ...]  # of each stage kept


def _polish_task(task: _PolishTask) -> _PolishOutcome:
    o = task.cpd
    cur, e_cur = task.start, task.error
    steps: list[PointTransform] = []
    quality: list[RegistrationQuality] = []
    corr: IntArray = np.zeros(0, dtype=np.intp)
    prob: FloatArray = np.zeros(0)
    for stage, factor in enumerate(POLISH_BETA_FACTORS):
        # the start already lies on the subject: sigma^2 from its residual (e = mean
        # squared nearest distance, both ways; sigma^2 is per coordinate), not from the
        # spread of all pairs, which would let CPD wander off again; never below the
        # squared point spacing
        sigma2 = max(0.5 * e_cur, task.spacing2)
        res = cpd_nonrigid(cur, task.y, beta=factor * o.beta, lmbda=o.lmbda, w=o.w,
                           max_iter=o.max_iter, tol=o.tol, dtype=o.dtype, sigma2=sigma2)
        warped = np.asarray(res.warped, dtype=np.float64)
        e = registration_error(warped, task.y)
        q = measure_quality(cur, warped, task.y, res.transform, e, task.spacing2)
        max_e = e_cur if stage == 0 else POLISH_FINER_MAX_E_RATIO * e_cur  # finer: see above
        if not (q.min_jacobian > 0 and e <= max_e and q.confidence >= MIN_CONFIDENCE):
            continue  # this stage is not kept; the next starts where the last kept left
        steps.append(res.transform)
        quality.append(q)
        cur, e_cur = warped, e
        corr = np.asarray(res.correspondence, dtype=np.intp)
        prob = np.asarray(res.probability, dtype=np.float64)
    return _PolishOutcome(subject=task.subject, warped=cur, error=e_cur, correspondence=corr,
                          probability=prob, steps=tuple(steps), quality=tuple(quality))


def _polished(coll: _Collection, old: SubjectResult, out: _PolishOutcome) -> SubjectResult:
    """`old` with the polished registration in place of the chained one."""
    assert old.transform is not None and old.confidence is not None and out.steps
    chain = replace(old.transform, steps=(*old.transform.steps, *out.steps))
    assert isinstance(chain, ChainTransform)
    confidence = min(old.confidence, *(q.confidence for q in out.quality))
    quality = {**(old.quality or {}), "polish": {
        "error_before": old.error, "steps": len(out.steps), **out.quality[-1].to_dict(),
        "confidence": min(q.confidence for q in out.quality),
        "min_jacobian": min(q.min_jacobian for q in out.quality)}}
    return replace(
        old, error=out.error, warped=coll.norms[out.subject].invert(out.warped),
        correspondence=out.correspondence, probability=out.probability, transform=chain,
        confidence=confidence, quality=quality,
        reason=f"{old.reason}; polished: {len(out.steps)} more CPD from the chained model "
               f"(e {old.error:.3g} -> {out.error:.3g})",
    )


def _polish_subjects(
    coll: _Collection,
    results: dict[int, SubjectResult],
    cpd: CPDOptions,
    executor: Executor | None,
    progress: ProgressCallback | None,
    min_layer: int = POLISH_MIN_LAYER,
) -> None:
    """Polish every attached subject at layer >= `min_layer` in place (see the module doc)."""
    tasks = [
        _PolishTask(subject=s, start=coll.norms[s].apply(r.warped), error=r.error,
                    y=coll.normed[s], cpd=cpd, spacing2=coll.spacing2[s])
        for s, r in sorted(results.items())
        if r.warped is not None and r.layer is not None and r.layer >= min_layer
        and r.error is not None and r.transform is not None and r.confidence is not None
    ]
    if not tasks:
        return
    with owned_executor(executor, 8 * len(tasks)) as ex:
        if progress is not None:
            progress("polish", 0, len(tasks))
        for done, (_, out) in enumerate(ex.map_unordered(_polish_task, tasks), start=1):
            if out.steps:
                results[out.subject] = _polished(coll, results[out.subject], out)
            if progress is not None:
                progress("polish", done, len(tasks))

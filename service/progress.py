"""A job's progress on a terminal, drawn the same way by ``regtree watch``, ``regtree run
--wait`` and ``regtree demo``: the current stage with its count, an overall percentage and an
estimate of the time left.

The library reports progress per stage, each with its own count: pairs of shapes for the
similarity stages (``similarity``, ``similarity round 2``, ...), registrations for the
others. A tree job runs, in order: ``similarity``; the tree's rounds of growth
(``similarity round N``, ``round N`` for N = 1, 2, ...: a dynamic tree's round N tries
the waiting subjects from the members the round before added, or from any member after a
stall's bridges, so it can attach subjects at any depth, then
``round N, again from the root`` when some of its registrations lie far above the
collection's e; a static tree reports its layers, ``similarity layer N``, ``layer N``
for N = 2, 3, ...; progress stored by earlier versions names a dynamic tree's rounds
that way too); ``similarity leaves``, ``leaves``; ``refine``; when it compares,
``similarity direct``, ``direct`` (a static tree: after the tree's stages, as it has no
polish); ``polish``; and when it decides at a working resolution below its shapes'
(coarse to fine), ``full resolution``, ``polish full resolution`` (the dynamic tree's)
and ``direct full resolution``, which count subjects. Stages with nothing to do are not
reported. A ``grouping`` job runs ``fields`` (instances), ``alignment`` (alignments to
the median field) and ``pairs`` (pairs aligned to each other).

The overall percentage places the stage within the whole run with the share of time each
phase took in measured runs (:data:`PHASE_WEIGHTS`, bench/bench_progress.py, bench/RESULTS.md
sections 5.2 and 5.3), counting only the phases the job runs. How many rounds a tree takes is
not known in advance, nor how many subjects it leaves to ``leaves``: the layers phase
advances with the registrations done in all rounds so far, then in the leaves, against
:data:`TREE_REGISTRATIONS_PER_SUBJECT` per subject, slowing down as it nears its end rather
than stopping (:func:`_saturating`). The percentage never goes back. The
time left is elapsed time x what is left / what is done; it is shown rounded up, so it never
reads 0:00 while the job runs.
"""

from __future__ import annotations

import math
import re
import shutil
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, TextIO

from service.contract.names import GROUPING_METHOD

if TYPE_CHECKING:
    from service.client import JobStatus

#: Time per phase, measured (bench/bench_progress.py; bench/RESULTS.md sections 5.2, 5.4).
#: The decisions (similarity to direct) as shares of their sum, the mean over the demo
#: collection, 20 generated shapes of 800 points and 40 永 edge glyphs. "layers" is the
#: tree's growth, its leaves included (section 5.3): on MPEG-7 classes the leaves took 0%
#: of the decisions (bridging had already run their registrations) to 42-59% (an explicit
#: similarity threshold: the tree stalls at once), while layers and leaves together took
#: 55-76% either way; so the leaves advance the layers' count of registrations
#: (:data:`LEAF_REGISTRATION_COST`) and weigh what the guessed 0.03 of their own did. The
#: stored-resolution phases relative to the same sum for shapes as large as the working
#: resolution; they grow as ``(max_points / working_points) ** 1.5``
#: (:data:`FINE_EXPONENT`, :func:`phase_weights`): a CPD at the stored resolution costs
#: between the points and their product, the decisions run at the working resolution;
#: the polish there as that ratio (:data:`STORED_POLISH_EXPONENT`).
PHASE_WEIGHTS = {
    # measured again in session 14 (bench/RESULTS.md 5.5), after the E-step's speed-ups
    # and the polish's edges from polished parents (halfway between the edge's two
    # registrations); session 7's were similarity 0.15, layers 0.41, refine 0.05, direct
    # 0.17, polish 0.22 (0.31 after the consensus and the accelerated EM), full resolution
    # 0.06, direct full resolution 0.038
    "similarity": 0.17,
    "layers": 0.26,
    "refine": 0.025,
    "direct": 0.10,
    # the symmetric finish (session 23, bench/RESULTS.md 7.16: the 73 glyphs' polish
    # 10.4-11.2 -> 12.5-13.4 s over HTTP) made it 1.2x; it was 0.45
    "polish": 0.54,
    # the tree's stored-resolution stage about doubled with its finish (session 21,
    # bench/RESULTS.md 8.4: 3.8-4.0 -> 6.7-7.8 s of the 73 glyphs' job over HTTP; 0.040),
    # then grew 1.65x with the symmetric finish (session 23, 7.16: 6.3-7.7 -> 11.6 s;
    # 0.066); without either (they moved into the polish below) bench_progress.py gives
    # 0.0143 (chains800) and 0.0074 (yong40), the 73 glyphs' HTTP job 0.012 (session 36,
    # bench/RESULTS.md 7.31)
    "full resolution": 0.011,
    # the polish again at the stored resolution (session 36, bench/RESULTS.md 7.31), at
    # its own growth (STORED_POLISH_EXPONENT): bench_progress.py (session 37, 7.32, its
    # stages at 1000 control points) gives 0.585 of the decisions on chains800 (ratio 2)
    # and 1.81 on yong40 (ratio 5.6), 0.275 at ratio 1 on both; 0.30 of these weights'
    # decisions (their sum is 1.095). Session 36's weight under FINE_EXPONENT (0.13)
    # put it at 0.37 and 1.72
    "polish full resolution": 0.30,
    "direct full resolution": 0.011,
}
#: A grouping job's phases, as shares of its run: the mean wall-clock shares of nine runs
#: with the service's process pool, 50, 100 and 200 generated impressions three times each
#: (bench/bench_progress.py ``--grouping``; bench/RESULTS.md section 5.3). Every stage's
#: time grows as the instances (8-9 pairs aligned per instance at every size; no trend of
#: the shares with n beyond the load's noise), so the shares do not depend on n.
GROUPING_WEIGHTS = {
    "fields": 0.09,
    "alignment": 0.15,
    "pairs": 0.76,
}
#: With ``max_rotation`` the first alignment round also starts from rotations in 10 degree
#: steps both ways, 3 iterations each, against 2 rounds of 8 iterations without: the
#: alignment costs ``1 + ROTATION_START_COST x starts`` as much (2.3x at 30 degrees;
#: measured 2.4x in CPU time, bench/RESULTS.md section 5.3).
ROTATION_START_COST = 3 / 16
#: How the stored-resolution weights grow with ``max_points / working_points``: measured
#: 1.65 (tree) and 1.3 (direct) between ratios 2 and 5.6 with one warm-started CPD per
#: subject and its near-linear E-step (bench/RESULTS.md section 5.2; 2.2 and 1.8 when the
#: stage ran two CPDs for a polished subject and a quadratic fold check). Measured again
#: with the polish from layer 2 and the box-wise E-step (section 5.4, serial CPU): tree
#: 0.054 / 0.061 and direct 0.039 / 0.037 of the decisions at ratios 2 / 5.6, growth
#: n^1.6; the weights are their means.
FINE_EXPONENT = 1.5
#: How the ``polish full resolution`` weight grows with the same ratio: every CPD of that
#: polish fits a fixed number of the root's points (500, its stages 1000: the
#: ``_resolution`` module's control points) to the subject's points, so its E-step grows
#: with the subject alone, and at 800 points a shape its stages fit every point. Measured
#: 1.09 between ratios 2 and 5.6 (bench/bench_progress.py, chains800 and yong40,
#: bench/RESULTS.md 7.32; 1.01 with the stages at 500).
STORED_POLISH_EXPONENT = 1.1
#: The ratio assumed for a job queued before ``max_points`` was recorded.
DEFAULT_FINE_RATIO = 4.0
#: Registrations the tree's layers run per subject, measured: 1.47 (demo), 2.38 (永 40),
#: 3.55 (800-point chains, which bridge a stalled tree one subject at a time); a dynamic tree
#: tries up to 3 candidates for a subject in a layer and may try it again in later layers;
#: a static tree registers each subject once.
TREE_REGISTRATIONS_PER_SUBJECT = 2.4
#: A registration of the ``leaves`` stage counted as this many of the layers' (measured
#: 0.39-0.95 of a layer registration's wall time within a run, mean 0.69, in seven runs
#: where the leaves ran: they run as one batch, the last layers of a stalled tree one or
#: two at a time, each with its ``similarity layer N``; bench/RESULTS.md section 5.3).
LEAF_REGISTRATION_COST = 0.7
#: Within a phase of two stages, the share of its first (the similarity of its pairs).
SIMILARITY_PART = 0.25
#: Before this much is done, the time left is not estimated.
MIN_FRACTION_FOR_ETA = 0.03

#: A stage of the tree's growth: a dynamic tree's round, a static tree's layer.
_LAYER = re.compile(r"(?:round|layer) (\d+)(?:, again from the root)?")
_PHASE_OF_STAGE = {
    "similarity": "similarity",
    "similarity leaves": "layers",  # the leaves go on with the tree's registrations
    "leaves": "layers",
    "refine": "refine",
    "polish": "polish",
    "similarity direct": "direct",
    "direct": "direct",
    "full resolution": "full resolution",
    "polish full resolution": "polish full resolution",
    "direct full resolution": "direct full resolution",
}


def clock(seconds: float) -> str:
    """``m:ss``, or ``h:mm:ss`` from an hour."""
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def left(seconds: float) -> str:
    """A time left: :func:`clock` rounded up, so that any time left reads at least 0:01."""
    return clock(math.ceil(seconds))


_GROUPING_UNITS = {"fields": "instances", "alignment": "alignments", "pairs": "pairs"}


def stage_unit(stage: str | None, method: str | None = None) -> str:
    """What a stage counts: for a grouping, instances, alignments or pairs; pairs of shapes
    for similarity stages, subjects at the stored resolution, else registrations."""
    if method == GROUPING_METHOD and stage in _GROUPING_UNITS:
        return _GROUPING_UNITS[stage]
    if (stage or "").startswith("similarity"):
        return "pairs"
    return "subjects" if (stage or "").endswith("full resolution") else "registrations"


def phase_of(stage: str, method: str = "dynamic_tree") -> str | None:
    """The phase a stage of a job of `method` belongs to (see :data:`PHASE_WEIGHTS`); None
    for one not known."""
    if method == GROUPING_METHOD:
        return stage if stage in GROUPING_WEIGHTS else None
    if _LAYER.fullmatch(stage.removeprefix("similarity ")):  # a round, or its similarity
        return "layers"
    if method == "direct" and stage == "full resolution":
        return "direct full resolution"  # register_direct's subjects are direct's
    return _PHASE_OF_STAGE.get(stage)


def stored_resolution_stage(params: dict[str, Any]) -> bool:
    """Whether a job ends with the stored-resolution stages: it decides at a working
    resolution (``working_points``) and has a shape above it (``max_points``; a job queued
    before that was recorded is assumed to)."""
    working = params.get("working_points")
    if not working:
        return False
    most = params.get("max_points")
    return most is None or int(most) > int(working)


def grouping_weights(max_rotation: float | None = None) -> dict[str, float]:
    """A grouping's phases with their shares (summing to 1); with `max_rotation` (degrees)
    the alignment tries ``1 + 2 x floor(max_rotation / 10)`` starting rotations (when
    that is more than one)."""
    raw = dict(GROUPING_WEIGHTS)
    steps = int(float(max_rotation or 0) // 10)
    if steps:
        raw["alignment"] *= 1 + ROTATION_START_COST * (1 + 2 * steps)
    total = sum(raw.values())
    return {p: w / total for p, w in raw.items()}


def phase_weights(
    method: str, *, compare_direct: bool, coarse_to_fine: bool, max_points: int | None = None,
    working_points: int | None = None, max_rotation: float | None = None,
) -> dict[str, float]:
    """The phases a job runs, in order, each with its share of the run (summing to 1);
    `max_rotation` counts for a grouping only."""
    if method == GROUPING_METHOD:
        return grouping_weights(max_rotation)
    if method == "direct":
        phases = ["direct"] + (["direct full resolution"] if coarse_to_fine else [])
    else:
        phases = ["similarity", "layers"]
        if method == "dynamic_tree":  # the polish reuses the direct registrations
            phases += ["refine", *(["direct"] if compare_direct else []), "polish"]
        elif compare_direct:
            phases.append("direct")
        if coarse_to_fine:
            phases += ["full resolution"]
            if method == "dynamic_tree":
                phases.append("polish full resolution")
            if compare_direct:
                phases.append("direct full resolution")
    ratio = DEFAULT_FINE_RATIO
    if max_points and working_points:
        ratio = max(1.0, max_points / working_points)
    growth = {"full resolution": ratio**FINE_EXPONENT,
              "direct full resolution": ratio**FINE_EXPONENT,
              "polish full resolution": ratio**STORED_POLISH_EXPONENT}
    raw = {p: PHASE_WEIGHTS[p] * growth.get(p, 1.0) for p in phases}
    total = sum(raw.values())
    return {p: w / total for p, w in raw.items()}


def _saturating(x: float) -> float:
    """``x`` up to 3/4, then on towards 1 without reaching it (slope 1 throughout)."""
    knee = 0.75
    return x if x <= knee else 1.0 - (1.0 - knee) * math.exp(-(x - knee) / (1.0 - knee))


def _within(method: str, phase: str, stage: str, f: float, subjects: int,
            before: int, done: int) -> float:
    """How far a phase is, from 0 to 1, at `stage` with `f` of its count done."""
    if phase == "layers":  # the tree's layers, then its leaves
        per_subject = 1.0 if method == "static_tree" else TREE_REGISTRATIONS_PER_SUBJECT
        regs = before + (0 if stage.startswith("similarity") else
                         done * (LEAF_REGISTRATION_COST if stage == "leaves" else 1))
        return _saturating(regs / (per_subject * max(subjects, 1)))
    if phase == "direct" and stage.startswith("similarity"):
        return SIMILARITY_PART * f
    if phase == "direct":
        return SIMILARITY_PART + (1 - SIMILARITY_PART) * f
    return f


def overall_fraction(
    method: str, stage: str | None, done: int, total: int, *, compare_direct: bool,
    coarse_to_fine: bool = False, max_points: int | None = None,
    working_points: int | None = None, subjects: int = 0, before: int = 0,
    max_rotation: float | None = None,
) -> float | None:
    """The estimated share of a running job that is done, from its current stage; None for
    a stage this does not know. `coarse_to_fine`: the job ends with the stored-resolution
    stages; `max_points`, `working_points`: the most points of its shapes and the working
    resolution (the weight of those stages grows with their ratio); `subjects`: how many
    subjects it has; `before`: the registrations done in the tree's earlier rounds
    (``round N`` or ``layer N`` stages before this one); `max_rotation`: a grouping's (its
    alignment tries more starting rotations)."""
    if not stage:
        return 0.0
    phase = phase_of(stage, method)
    weights = phase_weights(method, compare_direct=compare_direct and method != "direct",
                            coarse_to_fine=coarse_to_fine, max_points=max_points,
                            working_points=working_points, max_rotation=max_rotation)
    if phase not in weights:
        return None
    f = min(1.0, done / total) if total > 0 else 0.0
    start = 0.0
    for p, w in weights.items():
        if p == phase:
            break
        start += w
    return min(1.0, start + weights[phase] * _within(method, phase, stage, f, subjects,
                                                      before, done))


def outcome_line(state: JobStatus, summary: dict[str, Any] | None = None) -> str:
    """The line ``regtree watch``, ``run --wait`` and ``demo`` print when a job ends: its
    status, how long it ran and, with the result's summary, what was attached."""
    line = f"job {state.id} {state.status}"
    if state.started_at is not None and state.finished_at is not None:
        line += f" after {(state.finished_at - state.started_at).total_seconds():.1f} s"
    if state.status == "succeeded" and summary:
        line += f": {summary.get('attached')} of {summary.get('subjects')} subjects attached"
        if summary.get("leaves"):
            line += f" ({summary['leaves']} as low-confidence leaves)"
        line += f", tree depth {summary.get('depth')}"
    return line


def _started(state: JobStatus) -> float | None:
    """``time.monotonic()`` of the job's start, from its ``started_at``."""
    if state.started_at is None:
        return None
    started = state.started_at
    if started.tzinfo is None:
        started = started.replace(tzinfo=UTC)
    ago = (datetime.now(UTC) - started).total_seconds()
    return time.monotonic() - max(0.0, ago)


class FractionTracker:
    """The overall share of one job done, from the stages it reports in order: kept from
    going back, below 1 until the job ends, the tree's earlier layers counted (what
    :func:`overall_fraction` needs from the history). The worker keeps one per running job
    and stores its figure with the progress; :class:`Progress` keeps one per job it shows.
    """

    def __init__(self, method: str, params: dict[str, Any], n_shapes: int) -> None:
        self.method = method
        self.params = params
        self.subjects = max(0, n_shapes - 1)
        self.fraction = 0.0
        self._layers: dict[str, int] = {}  # the total of each ``round N``/``layer N`` seen

    def update(self, stage: str | None, done: int, total: int) -> float | None:
        """The share done after this progress report; None while no stage is known."""
        if stage and _LAYER.fullmatch(stage):
            self._layers[stage] = total
        params = self.params
        fraction = overall_fraction(
            self.method, stage, done, total,
            compare_direct=bool(params.get("compare_direct")),
            coarse_to_fine=stored_resolution_stage(params),
            max_points=params.get("max_points"),
            working_points=params.get("working_points"),
            subjects=self.subjects,
            before=sum(t for s, t in self._layers.items() if s != stage),
            max_rotation=params.get("max_rotation"),
        )
        if fraction is None and not self.fraction:
            return None
        # a stage this does not know keeps the estimate as it was
        self.fraction = max(self.fraction, min(fraction or 0.0, 0.99))
        return self.fraction


def seconds_left(fraction: float | None, ran: float) -> float | None:
    """The time left of a job `fraction` done after `ran` seconds, once enough is done."""
    if fraction is None or fraction < MIN_FRACTION_FOR_ETA or ran <= 0:
        return None
    return ran * (1 - fraction) / fraction


@dataclass
class Estimate:
    """What the line shows besides the stage: overall share done and the time left."""

    fraction: float | None  # None until the job runs a stage this knows
    remaining: float | None  # seconds; None until enough is done


def progress_text(state: JobStatus) -> str:
    """``running layer 3 4/7 registrations (57%)``: status, stage and its count."""
    text = state.status
    if state.cancel_requested and not state.finished:
        text += " (cancel requested)"
    if state.stage:
        text += f" {state.stage}"
    if state.total:
        text += f" {state.done}/{state.total} {stage_unit(state.stage, state.method)}"
        text += f" ({100 * state.done // state.total}%)"
    return text


class Progress:
    """Draws a job's progress: one redrawn line with a bar on a terminal, else one plain line
    per change (status, stage, done or total) and at least one every ``heartbeat`` seconds.

    Both say how many subjects the job has, the stage with its count, the overall
    percentage (never going back) and, once a little is done, the time left.
    """

    heartbeat = 30.0

    def __init__(self, job_id: int, out: TextIO, *, tty: bool | None = None) -> None:
        self.job_id = job_id
        self.out = out
        self.tty = out.isatty() if tty is None else tty
        self.started = time.monotonic()
        self._run_started: float | None = None
        self._fraction = 0.0
        self._tracker: FractionTracker | None = None
        self._last_key: tuple[Any, ...] | None = None
        self._last_line = self.started
        self._drawn = False

    def elapsed(self) -> float:
        return time.monotonic() - self.started

    def estimate(self, state: JobStatus) -> Estimate:
        """The overall share done (kept from going back) and the time left."""
        if state.status == "succeeded":
            self._fraction = 1.0
            return Estimate(1.0, 0.0)
        if state.status != "running":
            return Estimate(self._fraction if state.finished else None, None)
        if self._run_started is None:
            self._run_started = _started(state) or time.monotonic()
        if self._tracker is None:
            self._tracker = FractionTracker(state.method, state.params, state.n_shapes)
        if self._tracker.update(state.stage, state.done, state.total) is None:
            return Estimate(None, None)
        self._fraction = self._tracker.fraction
        return Estimate(self._fraction,
                        seconds_left(self._fraction, time.monotonic() - self._run_started))

    def _subjects(self, state: JobStatus) -> str:
        if state.method == GROUPING_METHOD:  # every shape is an instance to group
            return f"{state.n_shapes} instances" if state.n_shapes else ""
        return f"{state.n_shapes - 1} subjects" if state.n_shapes > 1 else ""

    @staticmethod
    def _overall(estimate: Estimate) -> str:
        if estimate.fraction is None:
            return ""
        text = f"overall {100 * estimate.fraction:.0f}%"
        if estimate.remaining is not None and estimate.fraction < 1:
            text += f", about {left(estimate.remaining)} left"
        return text

    def update(self, state: JobStatus) -> None:
        estimate = self.estimate(state)
        if self.tty:
            self._draw_line(state, estimate)
            return
        key = (state.status, state.stage, state.done, state.total, state.cancel_requested)
        now = time.monotonic()
        if key != self._last_key or now - self._last_line >= self.heartbeat:
            self._last_key = key
            self._last_line = now
            parts = [progress_text(state), self._subjects(state), self._overall(estimate)]
            text = "; ".join(p for p in parts if p)
            self.out.write(f"[{self.elapsed():7.1f} s] job {self.job_id} {text}\n")
            self.out.flush()

    def _draw_line(self, state: JobStatus, estimate: Estimate) -> None:
        columns = shutil.get_terminal_size((80, 24)).columns
        head = f"job {self.job_id} {state.status}"
        if state.cancel_requested and not state.finished:
            head += " (cancel requested)"
        if self._subjects(state):
            head += f" · {self._subjects(state)}"
        if state.stage:
            head += f" · {state.stage}"
            if state.total:
                head += f" {state.done}/{state.total}"
        tail = f" {clock(self.elapsed())}"
        bar = ""
        if estimate.fraction is not None:
            tail = f" {100 * estimate.fraction:3.0f}%"
            if estimate.remaining is not None and estimate.fraction < 1:
                tail += f" ~{left(estimate.remaining)} left"
            tail += f" {clock(self.elapsed())}"
            width = max(10, min(30, columns - len(head) - len(tail) - 5))
            filled = round(width * estimate.fraction)
            bar = f" [{'#' * filled}{'.' * (width - filled)}]"
        line = (head + bar + tail)[: max(1, columns - 1)]
        self.out.write("\r\x1b[K" + line)
        self.out.flush()
        self._drawn = True

    def end_line(self) -> None:
        """Leave the redrawn line (before printing anything else)."""
        if self.tty and self._drawn:
            self.out.write("\r\x1b[K")
            self.out.flush()
            self._drawn = False

"""A job's progress on a terminal, drawn the same way by ``regtree watch``, ``regtree run
--wait`` and ``regtree demo``: the current stage with its count, an overall percentage and an
estimate of the time left.

The library reports progress per stage (``similarity``, ``layer 2``, ``layer 3``, ...,
``leaves``, ``refine``, ``polish``, ``direct``), each with its own count: pairs of shapes for
the similarity stages, registrations (a subject from a candidate parent) for the others. The
overall percentage places the stage within the whole run: the similarity first, the tree's
layers next (how many there will be is not known in advance, so each layer is given half of
what is left of the tree's share), then leaves, refinement and polish, and direct CPD last when the
job compares with it. It never goes back, and it is an estimate, as is the time left it gives
(elapsed time x what is left / what is done).
"""

from __future__ import annotations

import re
import shutil
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from service.client import JobStatus

#: Share of a run for its similarity stages and, when the job compares, for direct CPD (the
#: tree takes the rest). Direct CPD is one registration per subject, like a tree layer.
SIMILARITY_SHARE = 0.2
DIRECT_SHARE = 0.3
#: Share of a coarse-to-fine job (``working_points``) for registering every edge at the
#: stored resolution (stages ``full resolution`` and ``direct full resolution``), after the
#: decisions at the working resolution take the rest. A job whose shapes are all small has
#: no such stage: its percentage jumps from there to 100 at the end.
FINE_SHARE = 0.5
#: Within the tree's share: the layers up to this, leaves then refinement after.
LAYERS_SHARE = 0.9
#: Before this much is done, the time left is not estimated.
MIN_FRACTION_FOR_ETA = 0.03

_LAYER = re.compile(r"(similarity )?layer (\d+)")


def clock(seconds: float) -> str:
    """``m:ss``, or ``h:mm:ss`` from an hour."""
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def stage_unit(stage: str | None) -> str:
    """What a stage counts: pairs of shapes for similarity stages, else registrations."""
    return "pairs" if (stage or "").startswith("similarity") else "registrations"


def _tree_position(stage: str, f: float) -> float | None:
    """Where a stage of the tree is, from 0 to 1 of the tree's share."""
    m = _LAYER.fullmatch(stage)
    if m:
        layer = int(m.group(2))
        start = 1.0 - 0.5 ** max(0, layer - 2)  # layer 2 from 0, layer 3 from 1/2, ...
        width = 0.5 ** max(1, layer - 1)
        # a layer's similarity is its first quarter, its registrations the rest
        within = 0.25 * f if m.group(1) else 0.25 + 0.75 * f
        return LAYERS_SHARE * (start + width * within)
    rest = 1.0 - LAYERS_SHARE
    if stage == "similarity leaves":
        return LAYERS_SHARE
    if stage == "leaves":
        return LAYERS_SHARE + rest * 0.5 * f
    if stage == "refine":
        return LAYERS_SHARE + rest * (0.5 + 0.25 * f)
    if stage == "polish":
        return LAYERS_SHARE + rest * (0.75 + 0.25 * f)
    return None


def overall_fraction(
    method: str, stage: str | None, done: int, total: int, *, compare_direct: bool,
    coarse_to_fine: bool = False,
) -> float | None:
    """The estimated share of a running job that is done, from its current stage; None for
    a stage this does not know. `coarse_to_fine`: the job decides at a working resolution
    (its stages up to ``full resolution`` take ``1 - FINE_SHARE`` of it)."""
    if not stage:
        return 0.0
    f = min(1.0, done / total) if total > 0 else 0.0
    if coarse_to_fine:
        direct = DIRECT_SHARE if compare_direct and method != "direct" else 0.0
        if stage == "full resolution":
            return 1.0 - FINE_SHARE + FINE_SHARE * (1.0 - direct) * f
        if stage == "direct full resolution":
            return 1.0 - FINE_SHARE * direct * (1.0 - f)
        coarse = overall_fraction(method, stage, done, total, compare_direct=compare_direct)
        return None if coarse is None else (1.0 - FINE_SHARE) * coarse
    if method == "direct":
        if stage == "similarity direct" or stage == "similarity":
            return SIMILARITY_SHARE * f
        return SIMILARITY_SHARE + (1 - SIMILARITY_SHARE) * f if stage == "direct" else None
    direct = DIRECT_SHARE if compare_direct else 0.0
    tree = 1.0 - SIMILARITY_SHARE - direct
    if stage == "similarity":
        return SIMILARITY_SHARE * f
    if stage in ("similarity direct", "direct"):
        within = 0.25 * f if stage == "similarity direct" else 0.25 + 0.75 * f
        return SIMILARITY_SHARE + tree + direct * within
    position = _tree_position(stage, f)
    return None if position is None else SIMILARITY_SHARE + tree * position


def _started(state: JobStatus) -> float | None:
    """``time.monotonic()`` of the job's start, from its ``started_at``."""
    if state.started_at is None:
        return None
    started = state.started_at
    if started.tzinfo is None:
        started = started.replace(tzinfo=UTC)
    ago = (datetime.now(UTC) - started).total_seconds()
    return time.monotonic() - max(0.0, ago)


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
        text += f" {state.done}/{state.total} {stage_unit(state.stage)}"
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
        compare = bool(state.params.get("compare_direct"))
        fraction = overall_fraction(
            state.method, state.stage, state.done, state.total, compare_direct=compare,
            coarse_to_fine=bool(state.params.get("working_points")),
        )
        if fraction is None:
            return Estimate(self._fraction or None, None)
        self._fraction = max(self._fraction, min(fraction, 0.99))
        ran = time.monotonic() - self._run_started
        remaining = None
        if self._fraction >= MIN_FRACTION_FOR_ETA and ran > 0:
            remaining = ran * (1 - self._fraction) / self._fraction
        return Estimate(self._fraction, remaining)

    def _subjects(self, state: JobStatus) -> str:
        return f"{state.n_shapes - 1} subjects" if state.n_shapes > 1 else ""

    @staticmethod
    def _overall(estimate: Estimate) -> str:
        if estimate.fraction is None:
            return ""
        text = f"overall {100 * estimate.fraction:.0f}%"
        if estimate.remaining is not None and estimate.fraction < 1:
            text += f", about {clock(estimate.remaining)} left"
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
        if state.n_shapes > 1:
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
                tail += f" ~{clock(estimate.remaining)} left"
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

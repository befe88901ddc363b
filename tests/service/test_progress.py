"""service/progress.py: the progress line that ``regtree watch``, ``run --wait`` and ``demo``
share, on a captured stream."""

from __future__ import annotations

import io
import re
from typing import Any

import pytest

from service.client import JobStatus
from service.progress import (
    FINE_EXPONENT,
    PHASE_WEIGHTS,
    STORED_POLISH_EXPONENT,
    FractionTracker,
    Progress,
    clock,
    left,
    overall_fraction,
    phase_of,
    phase_weights,
    stored_resolution_stage,
)

#: The stages a dynamic-tree job with direct comparison reports, in order (from the library).
STAGES = [
    ("similarity", 240),
    ("round 1", 4),
    ("similarity round 2", 30),
    ("round 2", 6),
    ("round 3", 3),
    ("similarity leaves", 10),
    ("leaves", 2),
    ("refine", 6),
    ("similarity direct", 12),
    ("direct", 15),
    ("polish", 9),
]


def _state(status: str, stage: str | None = None, done: int = 0, total: int = 0,
           **extra: Any) -> JobStatus:  # fmt: skip
    return JobStatus.from_json(
        {
            "id": 7,
            "collection_id": 1,
            "model_shape_id": 1,
            "method": extra.pop("method", "dynamic_tree"),
            "status": status,
            "n_shapes": 16,
            "params": {"compare_direct": extra.pop("compare_direct", True)},
            "progress": {"stage": stage, "done": done, "total": total},
            **extra,
        }
    )


def _run() -> list[JobStatus]:
    states = [_state("queued")]
    for stage, total in STAGES:
        states += [_state("running", stage, done, total) for done in (0, total // 2, total)]
    return [*states, _state("succeeded", "direct", 15, 15)]


def _fractions(method: str, stages: list[tuple[str, int]], **kw: Any) -> list[float | None]:
    """overall_fraction at every count of every stage, with the registrations of the
    earlier layers counted as :class:`Progress` counts them."""
    layers: dict[str, int] = {}
    out = []
    for stage, total in stages:
        if stage.startswith(("round ", "layer ")):
            layers[stage] = total
        before = sum(t for s, t in layers.items() if s != stage)
        out += [overall_fraction(method, stage, done, total, subjects=15, before=before, **kw)
                for done in range(total + 1)]
    return out


@pytest.mark.parametrize("compare_direct", [True, False])
def test_overall_fraction_only_grows_through_a_run(compare_direct: bool) -> None:
    stages = [s for s in STAGES if "direct" not in s[0] or compare_direct]
    fractions = _fractions("dynamic_tree", stages, compare_direct=compare_direct)
    assert all(f is not None for f in fractions)
    assert fractions == sorted(fractions)  # type: ignore[type-var]
    assert fractions[0] == 0.0
    assert fractions[-1] == pytest.approx(1.0)
    # a tree that needs more registrations than expected goes on growing, slower, and
    # stays below the next phase
    deep = [overall_fraction("dynamic_tree", "round 9", 1, 1, compare_direct=False,
                             subjects=15, before=b) for b in (20, 40, 80)]  # fmt: skip
    # the leaves go on with the layers' count (each registration counted at its cost)
    leaves = [overall_fraction("dynamic_tree", "leaves", d, 40, compare_direct=False,
                               subjects=15, before=81) for d in (0, 20, 40)]  # fmt: skip
    refine = overall_fraction("dynamic_tree", "refine", 0, 1, compare_direct=False)
    assert deep[0] < deep[1] < deep[2] == leaves[0] < leaves[1] < leaves[2] < refine  # type: ignore[operator]


@pytest.mark.parametrize("method", ["dynamic_tree", "direct"])
@pytest.mark.parametrize("compare_direct", [True, False])
def test_coarse_to_fine_jobs_keep_a_share_for_the_full_resolution(
    method: str, compare_direct: bool
) -> None:
    compare = compare_direct and method != "direct"
    stages = [s for s in STAGES if ("direct" not in s[0] or compare)
              and (method != "direct" or "direct" in s[0])]  # fmt: skip
    stages += [("full resolution", 15)]
    if method == "dynamic_tree":
        stages.append(("polish full resolution", 15))
    if compare:
        stages.append(("direct full resolution", 15))
    fractions = _fractions(method, stages, compare_direct=compare_direct, coarse_to_fine=True,
                           max_points=1500)  # fmt: skip
    assert all(f is not None for f in fractions)
    assert fractions == sorted(fractions)  # type: ignore[type-var]
    assert fractions[-1] == pytest.approx(1.0)
    weights = phase_weights(method, compare_direct=compare, coarse_to_fine=True,
                            max_points=1500)  # fmt: skip
    fine = [p for p in weights if p.endswith("full resolution")]
    start = overall_fraction(method, "full resolution", 0, 15, compare_direct=compare_direct,
                             coarse_to_fine=True, max_points=1500)  # fmt: skip
    assert start == pytest.approx(1 - sum(weights[p] for p in fine))


def test_phase_weights() -> None:
    """Only the phases a job runs share it; the stored-resolution share grows with the
    points of the largest shape; a job knows whether it has that stage from its params."""
    every = phase_weights("dynamic_tree", compare_direct=True, coarse_to_fine=True)
    assert list(every) == list(PHASE_WEIGHTS) and sum(every.values()) == pytest.approx(1.0)
    plain = phase_weights("dynamic_tree", compare_direct=False, coarse_to_fine=False)
    assert list(plain) == ["similarity", "layers", "refine", "polish"]  # leaves: in layers
    assert sum(plain.values()) == pytest.approx(1.0)
    static = phase_weights("static_tree", compare_direct=False, coarse_to_fine=False)
    assert list(static) == ["similarity", "layers"]
    fine = [phase_weights("dynamic_tree", compare_direct=False, coarse_to_fine=True,
                          max_points=n, working_points=400)["full resolution"]
            for n in (500, 1500, 3000)]  # fmt: skip
    assert fine == sorted(fine) and fine[0] < fine[-1]
    # against a decision's phase, the stored polish grows about as the points (its CPDs
    # fit a fixed number of the root's points), the other stored-resolution phases faster
    two, four = (phase_weights("dynamic_tree", compare_direct=True, coarse_to_fine=True,
                               max_points=n, working_points=400) for n in (800, 1600))
    for phase, growth in (("polish full resolution", 2.0 ** STORED_POLISH_EXPONENT),
                          ("full resolution", 2.0 ** FINE_EXPONENT),
                          ("direct full resolution", 2.0 ** FINE_EXPONENT)):
        assert (four[phase] / four["polish"]) / (two[phase] / two["polish"]) == (
            pytest.approx(growth))
    assert STORED_POLISH_EXPONENT < FINE_EXPONENT
    assert stored_resolution_stage({"working_points": 400, "max_points": 1200})
    assert not stored_resolution_stage({"working_points": 400, "max_points": 150})
    assert not stored_resolution_stage({"working_points": None, "max_points": 1200})
    assert stored_resolution_stage({"working_points": 400})  # queued before max_points


def test_overall_fraction_of_direct_and_unknown_stages() -> None:
    assert overall_fraction("direct", "similarity direct", 5, 10, compare_direct=False) == (
        pytest.approx(0.125)
    )
    assert overall_fraction("direct", "direct", 15, 15, compare_direct=False) == 1.0
    assert overall_fraction("dynamic_tree", "something new", 1, 2, compare_direct=True) is None
    assert overall_fraction("dynamic_tree", None, 0, 0, compare_direct=True) == 0.0


def test_layer_stages_count_as_rounds() -> None:
    """A static tree reports its layers (``layer N``), and progress stored before the
    dynamic tree named its rounds ``round N`` says ``layer N`` for them: both place the job
    where the same rounds would."""
    def renamed(stage: str) -> str:
        if stage.startswith(("round ", "similarity round ")):
            n = int(stage.rsplit(" ", 1)[1]) + 1
            return stage.replace("round", "layer").rsplit(" ", 1)[0] + f" {n}"
        return stage

    as_layers = [(renamed(s), t) for s, t in STAGES]
    assert [s for s, _ in as_layers][1:5] == ["layer 2", "similarity layer 3", "layer 3",
                                              "layer 4"]
    assert _fractions("dynamic_tree", as_layers, compare_direct=True) == _fractions(
        "dynamic_tree", STAGES, compare_direct=True)
    assert phase_of("similarity layer 3") == phase_of("round 2") == "layers"
    assert phase_of("similarity round") is None and phase_of("rounds 2") is None


def test_a_rounds_registrations_again_from_the_root_advance_the_layers() -> None:
    """``round N, again from the root`` (a round's registrations far above the
    collection's e, tried again from the root) is part of the tree's growth: its
    registrations advance the layers phase after the round's own, and the estimate never
    goes back."""
    assert phase_of("round 2, again from the root") == "layers"
    assert phase_of("round 2, again") is None
    stages = [*STAGES[:4], ("round 2, again from the root", 2), *STAGES[4:]]
    plain = _fractions("dynamic_tree", STAGES, compare_direct=True)
    again = _fractions("dynamic_tree", stages, compare_direct=True)
    assert len(again) == len(plain) + 3
    ends = [f for f in again if f is not None]
    assert ends == sorted(ends)
    tracker = FractionTracker("dynamic_tree", {"compare_direct": True}, 16)
    seen = [tracker.update(stage, done, total) for stage, total in stages
            for done in (0, total)]
    assert seen == sorted(f for f in seen if f is not None)


def test_plain_lines_give_stage_counts_subjects_and_overall() -> None:
    out = io.StringIO()
    progress = Progress(7, out, tty=False)
    for state in _run():
        progress.update(state)
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue() and "\x1b" not in out.getvalue()
    assert re.fullmatch(r"\[\s*[\d.]+ s\] job 7 queued; 15 subjects", lines[0])
    assert "similarity 120/240 pairs (50%); 15 subjects; overall" in lines[2]
    assert any("round 2 3/6 registrations (50%)" in line for line in lines)
    overall = [int(m) for m in re.findall(r"overall (\d+)%", out.getvalue())]
    assert overall == sorted(overall) and overall[-1] == 100
    assert lines[-1].endswith("job 7 succeeded direct 15/15 registrations (100%); "
                              "15 subjects; overall 100%")  # fmt: skip
    # a repeated state draws no new line
    progress.update(_run()[-1])
    assert out.getvalue().splitlines() == lines


def test_time_left_follows_the_elapsed_time(monkeypatch: pytest.MonkeyPatch) -> None:
    now = [1000.0]
    monkeypatch.setattr("service.progress.time.monotonic", lambda: now[0])
    progress = Progress(7, io.StringIO(), tty=False)
    progress.update(_state("running", "similarity", 0, 100))
    assert progress.estimate(_state("running", "similarity", 0, 100)).remaining is None
    now[0] += 30.0
    # half the similarity of a job that compares, after 30 s
    share = phase_weights("dynamic_tree", compare_direct=True, coarse_to_fine=False)
    f = 0.5 * share["similarity"]
    estimate = progress.estimate(_state("running", "similarity", 50, 100))
    assert estimate.fraction == pytest.approx(f)
    assert estimate.remaining == pytest.approx(30.0 * (1 - f) / f)
    assert clock(270.0) == "4:30" and clock(3725.0) == "1:02:05"
    # a time left is rounded up: it never reads 0:00
    assert left(0.2) == "0:01" and left(59.5) == "1:00" and left(60.0) == "1:00"


def test_terminal_line_is_redrawn_with_a_bar() -> None:
    out = io.StringIO()
    progress = Progress(7, out, tty=True)
    for state in _run():
        progress.update(state)
    progress.end_line()
    screen = out.getvalue()
    frames = [f for f in screen.split("\r\x1b[K") if f]
    assert "\n" not in screen
    assert re.search(r"job 7 running · 15 subjects · round 2 3/6 \[#+\.*\]\s+\d+%", screen)
    assert re.fullmatch(r"job 7 succeeded · 15 subjects · direct 15/15 \[#+\] 100% [\d:]+",
                        frames[-1])  # fmt: skip
    assert screen.endswith("\r\x1b[K")  # the line is cleared before anything else is printed

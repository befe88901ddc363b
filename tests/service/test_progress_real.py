"""Progress of real jobs (issue 10, item 7): the sequence of progress events a real small job
reports, through the library as the worker calls it and through HTTP as ``regtree watch``
and ``regtree demo`` read it, gives an overall percentage that never goes back, stage totals
that match the subjects, and a time left until the end; watch and demo print it alike."""

from __future__ import annotations

import io
import re
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from registration import SerialExecutor
from service.client import JobStatus
from service.jobs.runner import run_library
from service.progress import MIN_FRACTION_FOR_ETA, Progress, left, phase_of, phase_weights
from tests.service.conftest import (
    create_collection,
    family,
    submit_job,
    upload_family,
)

#: A family of 7 shapes of 60 points (6 subjects, deep enough to polish), decided at 30
#: points: every stage a tree job with direct comparison has, the stored resolution included.
N_POINTS, WORKING = 60, 30


def _job(status: str, events: list[tuple[str, int, int]], k: int | None,
         params: dict[str, Any], n_shapes: int) -> JobStatus:  # fmt: skip
    stage, done, total = events[k] if k is not None else (None, 0, 0)
    return JobStatus.from_json({
        "id": 1, "collection_id": 1, "model_shape_id": 1, "method": params["method"],
        "status": status, "n_shapes": n_shapes, "params": params,
        "progress": {"stage": stage, "done": done, "total": total},
    })  # fmt: skip


def _check_totals(events: list[tuple[str, int, int]], doc: dict[str, Any]) -> None:
    """Every stage is one :mod:`service.progress` places; its count goes from 0 to its
    total; the totals match the subjects."""
    n = len(doc["subjects"]) + 1
    subjects = n - 1
    attached = sum(1 for s in doc["subjects"] if s["attached"])
    # a single edge whose polish the working resolution did not keep is not polished again
    polished = sum(1 for s in doc["subjects"] if s["attached"]
                   and "polish_not_kept" not in (s.get("quality") or {}))
    direct = sum(1 for s in doc.get("direct") or [] if s.get("attached", True))
    expected = {"direct": subjects, "full resolution": attached,
                "polish full resolution": polished,
                "direct full resolution": direct}  # fmt: skip
    seen: dict[str, list[int]] = {}
    for stage, done, total in events:
        assert phase_of(stage) is not None, stage
        seen.setdefault(stage, []).append(done)
        assert 0 <= done <= total, (stage, done, total)
        if stage in expected:
            assert total == expected[stage], (stage, total, expected[stage])
        elif stage.startswith("similarity"):
            assert total <= n * (n - 1)
        elif stage in ("refine", "polish"):
            assert total <= subjects
    for stage, counts in seen.items():
        assert counts == sorted(counts) and counts[0] == 0, (stage, counts)


@pytest.mark.parametrize(("method", "working"), [
    ("dynamic_tree", WORKING), ("dynamic_tree", None), ("static_tree", WORKING),
    ("direct", WORKING),
])  # fmt: skip
def test_progress_events_of_a_real_job(monkeypatch: pytest.MonkeyPatch, method: str,
                                       working: int | None) -> None:  # fmt: skip
    """Every progress event of a real job (the worker's library call), replayed through
    :class:`Progress` one second apart: the percentage only grows, reaches the cap only in
    the last phase, jumps little at the end, and the time left is there (never 0:00) from
    the first few percent to the end."""
    shapes = [p for _, p in family(n_chains=2, chain_length=3, n_points=N_POINTS)]
    params = {"compare_direct": True, "working_points": working, "max_points": N_POINTS,
              "cpd": {"max_iter": 60}, "method": method}  # fmt: skip
    events: list[tuple[str, int, int]] = []
    result = run_library(method, shapes, [f"s{k}" for k in range(len(shapes))], 0,
                         params, executor=SerialExecutor(),
                         progress=lambda *e: events.append(e))  # fmt: skip
    doc = result.to_dict()
    _check_totals(events, doc)
    stages = list(dict.fromkeys(s for s, _, _ in events))
    assert ("polish" in stages) == (method == "dynamic_tree") and "direct" in stages
    assert ("full resolution" in stages) == (working is not None)
    assert ("polish full resolution" in stages) == (
        working is not None and method == "dynamic_tree")

    now = [0.0]
    monkeypatch.setattr("service.progress.time.monotonic", lambda: now[0])
    progress = Progress(1, io.StringIO(), tty=False)
    progress.update(_job("queued", events, None, params, len(shapes)))
    weights = phase_weights(method, compare_direct=method != "direct",
                            coarse_to_fine=working is not None, max_points=N_POINTS,
                            working_points=working)
    last_phase = list(weights)[-1]
    fractions: list[float] = []
    remaining: list[float] = []
    for k in range(len(events)):
        now[0] += 1.0
        state = _job("running", events, k, params, len(shapes))
        estimate = progress.estimate(state)
        assert estimate.fraction is not None
        fractions.append(estimate.fraction)
        if estimate.fraction >= MIN_FRACTION_FOR_ETA:
            assert estimate.remaining is not None and left(estimate.remaining) != "0:00"
            if remaining:
                # the time left rises only by what the clock explains (1 s at the pace so
                # far), never by a leap: the estimate of what is done never drops
                pace = (1 - fractions[-2]) / fractions[-2]
                assert estimate.remaining <= remaining[-1] + pace + 1e-9, (events[k], remaining)
            remaining.append(estimate.remaining)
        if phase_of(events[k][0], method) != last_phase:
            assert estimate.fraction < 0.99, events[k]
    assert fractions == sorted(fractions)
    # the end is not a leap: the last phase ends near 100%
    assert fractions[-1] >= 0.95, (fractions[-1], events[-1])
    final = progress.estimate(_job("succeeded", events, len(events) - 1, params, len(shapes)))
    assert final.fraction == 1.0


# --- over HTTP ------------------------------------------------------------------------------


def _key(state: dict[str, Any]) -> tuple[Any, ...]:
    p = state["progress"]  # seconds_left changes with the clock alone
    return state["status"], p["stage"], p["done"], p["total"], p["fraction"]


def _poll(client: httpx.Client, job_id: int, timeout: float = 120) -> list[dict[str, Any]]:
    """Every distinct state of a job from submission to its end, as fast as it changes."""
    states: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state = client.get(f"/v1/jobs/{job_id}").raise_for_status().json()
        key = _key(state)
        if not states or key != _key(states[-1]):
            states.append(state)
        if state["status"] in ("succeeded", "failed", "cancelled"):
            return states
        time.sleep(0.01)
    raise AssertionError(f"job {job_id} did not end: {states[-1:]}")


@pytest.fixture(scope="module")
def polled(service: Any) -> Iterator[tuple[list[dict[str, Any]], dict[str, Any]]]:
    """The states of a real coarse-to-fine job with direct comparison, polled over HTTP,
    and its result."""
    with service.client() as client:
        shapes = family(n_chains=2, chain_length=3, n_points=N_POINTS, seed=3)
        cid = create_collection(client, "progress")
        ids = upload_family(client, cid, shapes)
        job = submit_job(client, cid, ids[0], compare_direct=True, working_points=WORKING)
        states = _poll(client, job["id"])
        assert states[-1]["status"] == "succeeded", states[-1]
        result = client.get(f"/v1/jobs/{job['id']}/result").raise_for_status().json()
        yield states, result


def test_progress_over_http(polled: tuple[list[dict[str, Any]], dict[str, Any]]) -> None:
    states, result = polled
    n_shapes = len(result["subjects"]) + 1
    params = states[0]["params"]
    assert params["max_points"] == N_POINTS and params["working_points"] == WORKING
    assert all(s["n_shapes"] == n_shapes for s in states)
    running = [s for s in states if s["status"] == "running" and s["progress"]["stage"]]
    assert running, states
    events = [(s["progress"]["stage"], s["progress"]["done"], s["progress"]["total"])
              for s in running]  # fmt: skip
    # what polling saw of each stage: known, counting up, totals matching the subjects
    seen: dict[str, list[tuple[int, int]]] = {}
    for stage, done, total in events:
        assert phase_of(stage) is not None, stage
        seen.setdefault(stage, []).append((done, total))
    subjects = n_shapes - 1
    attached = sum(1 for s in result["subjects"] if s["attached"])
    for stage, counts in seen.items():
        assert [d for d, _ in counts] == sorted(d for d, _ in counts), (stage, counts)
        assert len({t for _, t in counts}) == 1, (stage, counts)
        total = counts[0][1]
        if stage == "direct":
            assert total == subjects
        if stage == "full resolution":
            assert total == attached

    # the worker's own estimate, in the job document: never going back, 1 at the end, a
    # time left once a few percent are done (what the results page shows)
    fractions = [s["progress"]["fraction"] for s in running]
    assert all(f is not None and 0 <= f < 1 for f in fractions), fractions
    assert fractions == sorted(fractions), fractions
    assert states[-1]["progress"]["fraction"] == 1.0
    assert states[-1]["progress"]["seconds_left"] is None
    for s in running:
        p = s["progress"]
        if p["fraction"] >= MIN_FRACTION_FOR_ETA:
            assert p["seconds_left"] is not None and p["seconds_left"] >= 0, p

    out = io.StringIO()
    progress = Progress(int(states[0]["id"]), out, tty=False)
    for state in states:
        progress.update(JobStatus.from_json(state))
    lines = out.getvalue().splitlines()
    overall = [int(m) for m in re.findall(r"overall (\d+)%", out.getvalue())]
    assert overall == sorted(overall) and overall[-1] == 100, lines
    assert all(f"; {subjects} subjects" in line for line in lines), lines
    # a time left on every running line once a few percent are done, never 0:00
    for line in lines:
        m = re.search(r"overall (\d+)%(, about ([\d:]+) left)?$", line)
        if " running " in line and m and int(m[1]) >= 100 * MIN_FRACTION_FOR_ETA + 1:
            assert m[2] and m[3] != "0:00", line


class _Replay:
    """Answers GET of a job with the recorded states, one per request: what ``watch`` (the
    client's ``get_job``) and the demo (``httpx`` on the job's location) read."""

    def __init__(self, states: list[dict[str, Any]], result: dict[str, Any]) -> None:
        self.states, self.doc, self.k = states, result, 0

    def _next(self) -> dict[str, Any]:
        state = self.states[min(self.k, len(self.states) - 1)]
        self.k += 1
        return state

    # the client API that watch_job uses
    def get_job(self, job_id: int) -> JobStatus:
        return JobStatus.from_json(self._next())

    def result(self, job_id: int) -> Any:
        return type("R", (), {"summary": self.doc["summary"]})()

    # the httpx API that the demo's follow_job uses
    def get(self, url: str) -> Any:
        state = self._next()
        return type("Response", (), {"raise_for_status": lambda self: self,
                                     "json": lambda self: state})()  # fmt: skip


def test_watch_and_demo_print_the_same_progress(
    polled: tuple[list[dict[str, Any]], dict[str, Any]],
) -> None:
    """The same states read by ``regtree watch`` and by ``regtree demo`` give the same
    progress lines (but for the elapsed time) and the same closing line."""
    from service.cli_client.watch import watch_job
    from service.demo_run import follow_job
    from service.progress import outcome_line

    states, result = polled
    job_id = int(states[0]["id"])
    watched, demo = io.StringIO(), io.StringIO()
    assert watch_job(_Replay(states, result), job_id, out=watched,  # type: ignore[arg-type]
                     sleep=lambda _: None) == 0  # fmt: skip
    final = follow_job(_Replay(states, result), f"/v1/jobs/{job_id}", demo,  # type: ignore[arg-type]
                       poll=0)  # fmt: skip
    assert final["status"] == "succeeded"

    def strip(text: str) -> list[str]:
        # the elapsed time and the time left depend on when each line was drawn
        return [re.sub(r"about [\d:]+ left", "about T left",
                       re.sub(r"^\[\s*[\d.]+ s\] ", "[t] ", line))
                for line in text.splitlines()]  # fmt: skip

    watch_lines, demo_lines = strip(watched.getvalue()), strip(demo.getvalue())
    assert len(demo_lines) >= 3 and watch_lines[: len(demo_lines)] == demo_lines
    closing = outcome_line(JobStatus.from_json(states[-1]), result["summary"])
    assert watch_lines[len(demo_lines)] == closing
    assert re.fullmatch(rf"job {job_id} succeeded after [\d.]+ s: \d+ of 6 subjects attached"
                        r"(?: \(\d+ as low-confidence leaves\))?, tree depth \d+", closing)
    line = re.compile(r"\[t\] job \d+ (queued|running|succeeded)"
                      r"( .+ \d+/\d+ (pairs|registrations|subjects) \(\d+%\))?"
                      r"; 6 subjects(; overall \d+%(, about T left)?)?")
    assert all(line.fullmatch(text) for text in demo_lines), demo_lines

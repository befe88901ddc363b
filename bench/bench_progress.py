"""Where a tree job's time goes, stage by stage: the measured shares that
``service/progress.py`` places its overall percentage and time left with (issue 10, item 7).

Runs ``build_dynamic_tree`` with ``compare_direct=True`` (what ``regtree demo`` runs) and the
service's defaults otherwise (coarse to fine at 400 points, polish on, a local process pool
as the service's worker uses) on three collections, recording every progress event with
its time:

- ``demo``: the bundled demo collection (``service/demo``, 16 shapes of 150 points: no
  stored-resolution stage);
- ``chains800``: a generated family of the same kind at 800 points per shape
  (:func:`registration.synthetic.chained_family`, 4 chains x 5): a small coarse-to-fine job;
- ``yong40``: the first 40 永 edge glyphs of ``../shared/data/glyphs_yong/points`` at their
  stored resolution (about 1000-2300 points), pose upright +-30 deg as for glyph images
  (skipped, and said so, when the data is missing).

A stage lasts from its first event to the next stage's first event (the last one to the
method's return); the time before the first event goes to the first stage. Stages are
grouped as ``service/progress.py`` weighs them: similarity (the first all-pairs stage),
layers (``layer N`` and ``similarity layer N``), leaves (``similarity leaves``, ``leaves``),
refine, polish, direct (``similarity direct``, ``direct``), full resolution and direct full
resolution. Printed: seconds and share of each group, the shares of the groups without
direct CPD (a job that does not compare), and the share ``service/progress.py`` gives each
(:func:`service.progress.phase_weights`, from the largest shape's points).

    .venv/bin/python bench/bench_progress.py [--sets demo,chains800,yong40] [--json PATH]

(``REGTREE_DATA=/path/to/shared/data`` when the data is not at ``../shared/data``.)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import time
from pathlib import Path
from typing import Any

import numpy as np

from registration import LocalProcessExecutor, build_dynamic_tree
from registration.synthetic import chained_family
from service.progress import phase_weights

DATA = Path(os.environ.get("REGTREE_DATA",
                           Path(__file__).resolve().parents[1].parent / "shared" / "data"))
GLYPHS = DATA / "glyphs_yong"

WORKING_POINTS = 400  # the default working resolution
GROUPS = ["similarity", "layers", "leaves", "refine", "polish", "direct", "full resolution",
          "direct full resolution"]
_LAYER = re.compile(r"(similarity )?layer \d+")


def group_of(stage: str) -> str:
    if _LAYER.fullmatch(stage):
        return "layers"
    if stage in ("similarity leaves", "leaves"):
        return "leaves"
    if stage in ("similarity direct", "direct"):
        return "direct"
    return stage


def load_set(name: str) -> tuple[list[np.ndarray], dict[str, Any]] | None:
    if name == "demo":
        from service.demo_run import load_demo_shapes

        return list(load_demo_shapes()[1].values()), {}
    if name == "chains800":
        family = chained_family(n_chains=4, chain_length=5, n_points=800, seed=1)
        return list(family.to_npz_dict().values()), {}
    if name == "yong40":
        files = sorted((GLYPHS / "points").glob("*_edge.txt"))[:40]
        if not files:
            print(f"yong40: skipped, {GLYPHS} is missing")
            return None
        return [np.loadtxt(f).reshape(-1, 2) for f in files], {"max_rotation": 30.0}
    raise SystemExit(f"unknown set {name!r}")


def measure(shapes: list[np.ndarray], options: dict[str, Any]) -> dict[str, Any]:
    events: list[tuple[float, str, int, int]] = []

    def record(stage: str, done: int, total: int) -> None:
        events.append((time.perf_counter(), stage, done, total))

    with LocalProcessExecutor() as executor:
        t0 = time.perf_counter()
        result = build_dynamic_tree(shapes, 0, compare_direct=True, executor=executor,
                                    progress=record, **options)
        t1 = time.perf_counter()
    starts: list[tuple[float, str]] = []
    for t, stage, _, _ in events:
        if not starts or starts[-1][1] != stage:
            starts.append((t, stage))
    seconds = dict.fromkeys(GROUPS, 0.0)
    stage_seconds: dict[str, float] = {}
    for k, (t, stage) in enumerate(starts):
        begin = t0 if k == 0 else t
        end = starts[k + 1][0] if k + 1 < len(starts) else t1
        seconds[group_of(stage)] = seconds.get(group_of(stage), 0.0) + end - begin
        stage_seconds[stage] = stage_seconds.get(stage, 0.0) + end - begin
    totals: dict[str, int] = {}
    for _, stage, _, total in events:
        totals[stage] = total  # the last total a stage reported
    summary = result.summary()
    layer_regs = sum(t for s, t in totals.items() if re.fullmatch(r"layer \d+", s))
    return {"wall": t1 - t0, "seconds": seconds, "stage_seconds": stage_seconds,
            "stage_totals": totals, "layer_registrations": layer_regs,
            "subjects": len(shapes) - 1, "attached": summary.get("attached"),
            "points": [int(min(len(s) for s in shapes)), int(max(len(s) for s in shapes))]}


def shares(seconds: dict[str, float], without_direct: bool = False) -> dict[str, float]:
    keep = {g: s for g, s in seconds.items()
            if not (without_direct and g in ("direct", "direct full resolution"))}
    total = sum(keep.values()) or 1.0
    return {g: s / total for g, s in keep.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", default="demo,chains800,yong40")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    report: dict[str, Any] = {}
    for name in args.sets.split(","):
        loaded = load_set(name)
        if loaded is None:
            continue
        shapes, options = loaded
        m = measure(shapes, options)
        report[name] = m
        print(f"\n{name}: {m['subjects']} subjects, {m['points'][0]}-{m['points'][1]} points, "
              f"{m['attached']} attached, {m['wall']:.1f} s")
        with_d, without_d = shares(m["seconds"]), shares(m["seconds"], without_direct=True)
        model = phase_weights("dynamic_tree", compare_direct=True,
                              coarse_to_fine=m["points"][1] > WORKING_POINTS,
                              max_points=m["points"][1], working_points=WORKING_POINTS)
        print(f"  {'stage group':24s} {'s':>7s} {'share':>6s} {'no direct':>9s} "
              f"{'progress.py':>11s}")
        for g in GROUPS:
            nd = f"{100 * without_d[g]:8.1f}%" if g in without_d else f"{'-':>9s}"
            print(f"  {g:24s} {m['seconds'][g]:7.2f} {100 * with_d[g]:5.1f}% {nd} "
                  f"{100 * model.get(g, 0.0):10.1f}%")
        print("  stages (s, last total): " + ", ".join(
            f"{s} {m['stage_seconds'][s]:.2f} s {t}" for s, t in m["stage_totals"].items()))
        print(f"  tree registrations per subject in the layers: "
              f"{m['layer_registrations'] / m['subjects']:.2f}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()

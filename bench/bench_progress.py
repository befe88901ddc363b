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
  (skipped, and said so, when the data is missing);
- ``mpeg7-horse``, ``mpeg7-camel``, ``mpeg7-bat``, ``mpeg7-deer`` (not in the default list):
  one MPEG-7 class of ``../shared/data/mpeg7`` (20 shapes, resampled to 400 points, root
  ``<class>-1``, every orientation as section 0.2 ran them), classes whose trees stop with
  subjects waiting: where the ``leaves`` stages have work (skipped when the data is missing);
- ``mpeg7-mixed`` (not in the default list): the first 5 shapes of each of the 8 MPEG-7
  classes, 40 shapes at 400 points, root ``fish-1``: a tree that spends its bridging budget
  and leaves the rest to ``leaves``;
- ``mixed`` (not in the default list, no data needed): two generated families of unlike
  outlines in one collection (:func:`mixed_family`), whose other family's shapes wait for
  ``leaves``.

``--grouping 50,100,200`` times a ``grouping`` job's stages instead (``group_instances``,
the service's defaults): generated impressions of 40 procedural moulds x 5
(``bench_grouping.stroke_moulds``, each scan through the service's image ingestion), the
first 10, 20 and 40 moulds, each run twice: serially, timed by this process's CPU time
(which other processes' load does not change), and with a local process pool (the service's
executor), timed by the wall clock. Printed: each stage's seconds and share, the time
before the first event and after the last one, the shares the CPU times give for a pool of
``--processes``, and how each stage's CPU time scales with the number of instances, fitted
as ``stage / fields ~ n ** c`` (``fields`` is one step per instance).

A stage lasts from its first event to the next stage's first event (the last one to the
method's return); the time before the first event goes to the first stage. Stages are
grouped as ``service/progress.py`` weighs them: similarity (the first all-pairs stage),
layers (the dynamic tree's rounds, ``round N`` and ``similarity round N``; a static tree's
``layer N`` and ``similarity layer N``), leaves (``similarity leaves``, ``leaves``;
``service/progress.py`` counts them with the layers, and the line "layers + leaves" shows
their sum as a share of the decisions, similarity to direct), refine, polish, direct
(``similarity direct``, ``direct``), full resolution, polish full resolution and direct
full resolution. Printed:
seconds and share of each group, the shares of the groups without direct CPD (a job that
does not compare), and the share ``service/progress.py`` gives each
(:func:`service.progress.phase_weights`, from the largest shape's points). ``--serial``
times a tree set serially by CPU time; ``--similarity-threshold D`` gives the tree an
explicit threshold (no bridging: a stalled tree leaves its waiting subjects to ``leaves``).

    .venv/bin/python bench/bench_progress.py [--sets demo,chains800,yong40] [--json PATH]
    .venv/bin/python bench/bench_progress.py --sets mpeg7-horse,mpeg7-camel,mixed \
        [--similarity-threshold 0.015] [--serial]
    .venv/bin/python bench/bench_progress.py --sets none --grouping 50,100,200

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

from registration import (
    LocalProcessExecutor,
    SerialExecutor,
    build_dynamic_tree,
    group_instances,
    resample,
)
from registration.synthetic import chained_family, deformation_chains
from service.progress import PHASE_WEIGHTS, overall_fraction, phase_weights

DATA = Path(os.environ.get("REGTREE_DATA",
                           Path(__file__).resolve().parents[1].parent / "shared" / "data"))
GLYPHS = DATA / "glyphs_yong"
MPEG7 = DATA / "mpeg7"
MPEG7_CLASSES = ["fish", "lmfish", "flatfish", "horse", "bird", "bat", "camel", "deer"]

WORKING_POINTS = 400  # the default working resolution
GROUPS = ["similarity", "layers", "leaves", "refine", "polish", "direct", "full resolution",
          "polish full resolution", "direct full resolution"]
_LAYER = re.compile(r"(similarity )?(round|layer) \d+(, again from the root)?")


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
    if name == "mpeg7-mixed":
        found = [f for cls in MPEG7_CLASSES for f in sorted(
            (MPEG7 / cls).glob(f"{cls}-*.npy"), key=lambda p: int(p.stem.split("-")[-1]))[:5]]
        if len(found) < 5 * len(MPEG7_CLASSES):
            print(f"{name}: skipped, {MPEG7} is missing or incomplete")
            return None
        return [resample(np.load(f), WORKING_POINTS) for f in found], {}
    if name.startswith("mpeg7-"):
        cls = name.removeprefix("mpeg7-")
        found = sorted((MPEG7 / cls).glob(f"{cls}-*.npy"), key=lambda p: int(p.stem.split("-")[-1]))
        if not found:
            print(f"{name}: skipped, {MPEG7 / cls} is missing")
            return None
        return [resample(np.load(f), WORKING_POINTS) for f in found], {}
    if name == "mixed":
        return mixed_family(), {}
    raise SystemExit(f"unknown set {name!r}")


def star(points: int = 2000, arms: int = 5) -> np.ndarray:
    """A densely sampled star outline (unlike :func:`chained_family`'s blob)."""
    t = np.linspace(0, 2 * np.pi, points, endpoint=False)
    r = 1.0 + 0.45 * np.cos(arms * t)
    return np.c_[r * np.cos(t), r * np.sin(t)]


def mixed_family() -> list[np.ndarray]:
    """20 shapes of two classes: a chained family (root first, 10 subjects) and 9 warped
    stars, which no shape of the first class registers onto well."""
    first = chained_family(n_chains=2, chain_length=5, n_points=WORKING_POINTS, seed=2)
    stars = deformation_chains(star(), n_chains=3, chain_length=3, n_points=WORKING_POINTS,
                               seed=2)
    return list(first.shapes) + list(stars.shapes)


def measure(shapes: list[np.ndarray], options: dict[str, Any], serial: bool = False
            ) -> dict[str, Any]:
    """Seconds of each stage of one tree run: with a local process pool and the wall clock,
    or with `serial`, all in this process and its CPU time (``time.process_time``, which
    other processes' load does not change)."""
    events: list[tuple[float, str, int, int]] = []
    clock = time.process_time if serial else time.perf_counter

    def record(stage: str, done: int, total: int) -> None:
        events.append((clock(), stage, done, total))

    executor = SerialExecutor() if serial else LocalProcessExecutor()
    try:
        t0 = clock()
        result = build_dynamic_tree(shapes, 0, compare_direct=True, executor=executor,
                                    progress=record, **options)
        t1 = clock()
    finally:
        if isinstance(executor, LocalProcessExecutor):
            executor.close()
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
    layer_regs = sum(t for s, t in totals.items() if re.fullmatch(r"(round|layer) \d+", s))
    return {"wall": t1 - t0, "seconds": seconds, "stage_seconds": stage_seconds,
            "stage_totals": totals, "layer_registrations": layer_regs,
            "subjects": len(shapes) - 1, "attached": summary.get("attached"),
            "leaves": summary.get("leaves", 0),
            "points": [int(min(len(s) for s in shapes)), int(max(len(s) for s in shapes))]}


GROUPING_STAGES = ["fields", "alignment", "pairs"]


def grouping_scans(moulds: int, impressions: int = 5, seed: int = 0) -> list[np.ndarray]:
    """`impressions` generated scans of each of `moulds` procedural moulds, as points,
    mould by mould (the first k moulds' scans are the first k x `impressions`)."""
    from bench_grouping import stroke_moulds, to_points

    from registration.impressions import impression_set

    shapes, _ = impression_set(stroke_moulds(moulds, seed), impressions, to_points=to_points,
                               seed=seed)
    return shapes


def measure_grouping(shapes: list[np.ndarray], serial: bool, **options: Any) -> dict[str, Any]:
    """Seconds of each grouping stage (a stage from its first event to the next stage's),
    and before the first event and after the last one, in one ``group_instances`` run:
    with `serial`, all in this process and timed by its CPU time (``time.process_time``,
    which other processes' load does not change); else with a local process pool (the
    service's executor) and timed by the wall clock."""
    clock = time.process_time if serial else time.perf_counter
    events: list[tuple[float, str, int, int]] = []
    executor = SerialExecutor() if serial else LocalProcessExecutor()
    try:
        t0 = clock()
        result = group_instances(shapes, executor=executor, **options,
                                 progress=lambda s, d, t: events.append((clock(), s, d, t)))
        t1 = clock()
    finally:
        if isinstance(executor, LocalProcessExecutor):
            executor.close()
    first: dict[str, float] = {}
    totals: dict[str, int] = {}
    for t, stage, _, total in events:
        first.setdefault(stage, t)
        totals[stage] = total
    order = sorted(first, key=first.__getitem__)
    seconds = {stage: (first[order[k + 1]] if k + 1 < len(order) else events[-1][0])
               - first[stage] for k, stage in enumerate(order)}
    # as the percentage sees them: the time before the first event with the first stage,
    # after the last one with the last (which it shows at the 99% cap)
    seconds[order[0]] += events[0][0] - t0
    seconds[order[-1]] += t1 - events[-1][0]
    return {"seconds_total": t1 - t0, "before": events[0][0] - t0, "after": t1 - events[-1][0],
            "seconds": seconds, "totals": totals, "groups": result.n_groups}


def fit_exponent(ns: list[int], values: list[float]) -> float:
    """c of ``values ~ n ** c``, least squares in logs."""
    return float(np.polyfit(np.log(ns), np.log(np.maximum(values, 1e-9)), 1)[0])


def _grouping_rows(title: str, runs: dict[int, dict[str, Any]]) -> None:
    print(f"  {title}")
    print(f"  {'n':>4s} {'total s':>8s} {'before':>7s} " + " ".join(
        f"{g + ' s':>12s} {'share':>6s}" for g in GROUPING_STAGES)
        + f" {'after':>7s} {'ms/pair':>7s}")
    for n, m in runs.items():
        sec = m["seconds"]
        cells = [f"{sec.get(g, 0.0):12.2f} {100 * sec.get(g, 0.0) / m['seconds_total']:5.1f}%"
                 for g in GROUPING_STAGES]
        per_pair = 1000 * sec.get("pairs", 0.0) / max(m["totals"].get("pairs", 1), 1)
        print(f"  {n:4d} {m['seconds_total']:8.2f} {m['before']:7.3f} " + " ".join(cells)
              + f" {m['after']:7.3f} {per_pair:7.1f}")


def grouping_report(sizes: list[int], options: dict[str, Any], processes: int
                    ) -> dict[str, Any]:
    moulds = max(sizes) // 5
    t = time.perf_counter()
    scans = grouping_scans(moulds)
    print(f"\ngrouping: {len(scans)} generated scans of {moulds} moulds "
          f"({np.mean([len(x) for x in scans]):.0f} points), made in "
          f"{time.perf_counter() - t:.1f} s; options {options or 'default'}")
    cpu = {n: measure_grouping(scans[:n], True, **options) for n in sizes}
    pool = {n: measure_grouping(scans[:n], False, **options) for n in sizes}
    _grouping_rows("CPU seconds, serial executor (load-independent):", cpu)
    _grouping_rows("wall seconds, local process pool (the service's; shares the loaded "
                   "machine):", pool)
    print(f"  shares for a pool of {processes} (CPU, pairs / {processes}):")
    for n, m in cpu.items():
        sec = {g: m["seconds"][g] / (processes if g == "pairs" else 1) for g in GROUPING_STAGES}
        whole = sum(sec.values())
        print(f"  {n:4d} " + " ".join(f"{g} {100 * v / whole:5.1f}%" for g, v in sec.items()))
    ns = sorted(cpu)
    if len(ns) > 1:
        print("  scaling, CPU stage / fields ~ n ** c (fields ~ n): " + ", ".join(
            f"{g} c={fit_exponent(ns, [cpu[n]['seconds'][g] / cpu[n]['seconds']['fields'] for n in ns]):+.2f}"  # noqa: E501
            for g in GROUPING_STAGES[1:]))
        print("  pairs per instance: " + ", ".join(
            f"{n} {cpu[n]['totals']['pairs'] / n:.1f}" for n in ns))
    return {"cpu": {str(n): m for n, m in cpu.items()},
            "pool": {str(n): m for n, m in pool.items()}}


def shares(seconds: dict[str, float], without_direct: bool = False) -> dict[str, float]:
    keep = {g: s for g, s in seconds.items()
            if not (without_direct and g in ("direct", "direct full resolution"))}
    total = sum(keep.values()) or 1.0
    return {g: s / total for g, s in keep.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", default="demo,chains800,yong40")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--grouping", default="",
                        help="instance counts of grouping runs, e.g. 50,100,200")
    parser.add_argument("--grouping-max-rotation", type=float, default=None)
    parser.add_argument("--similarity-threshold", type=float, default=None,
                        help="tree sets: an explicit D threshold (no bridging: a stalled "
                        "tree leaves its waiting subjects to the leaves stage)")
    parser.add_argument("--serial", action="store_true",
                        help="tree sets: CPU time of a serial run instead of a pool's wall time")
    parser.add_argument("--processes", type=int, default=2,
                        help="pool size the grouping shares are shown for")
    args = parser.parse_args()
    report: dict[str, Any] = {}
    if args.grouping:
        options = ({} if args.grouping_max_rotation is None
                   else {"max_rotation": args.grouping_max_rotation})
        report["grouping"] = grouping_report([int(n) for n in args.grouping.split(",")],
                                             options, args.processes)
    for name in args.sets.split(","):
        if name == "none":
            continue
        loaded = load_set(name)
        if loaded is None:
            continue
        shapes, options = loaded
        if args.similarity_threshold is not None:
            options = {**options, "similarity_threshold": args.similarity_threshold}
        m = measure(shapes, options, serial=args.serial)
        report[name] = m
        print(f"\n{name}: {m['subjects']} subjects, {m['points'][0]}-{m['points'][1]} points, "
              f"{m['attached']} attached ({m['leaves']} as leaves), {m['wall']:.1f} s "
              f"{'CPU, serial' if args.serial else 'wall, pool'}")
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
        decisions = sum(m["seconds"][g] for g in GROUPS[:6])
        print(f"  layers + leaves: {100 * (m['seconds']['layers'] + m['seconds']['leaves']) / decisions:.1f}% "  # noqa: E501
              f"of the decisions (progress.py {100 * PHASE_WEIGHTS['layers'] / sum(PHASE_WEIGHTS[g] for g in GROUPS[:6] if g in PHASE_WEIGHTS):.1f}%)")  # noqa: E501
        print(f"  tree registrations per subject in the layers: "
              f"{m['layer_registrations'] / m['subjects']:.2f}")
        leaf_regs = m["stage_totals"].get("leaves", 0)
        if leaf_regs:
            # the leaves' cost per registration against the layers', and their share of the
            # decisions (similarity to direct) as PHASE_WEIGHTS counts it
            per_leaf = m["seconds"]["leaves"] / leaf_regs
            per_layer = m["seconds"]["layers"] / max(m["layer_registrations"], 1)
            decisions = sum(m["seconds"][g] for g in GROUPS[:6])
            # where service/progress.py places the leaves' start and end, against the share
            # of the run's time elapsed then
            totals = m["stage_totals"]
            layer_regs = m["layer_registrations"]
            at = [overall_fraction("dynamic_tree", st, d, max(leaf_regs, 1), compare_direct=True,
                                   subjects=m["subjects"], before=layer_regs)
                  for st, d in (("similarity leaves", 0), ("leaves", leaf_regs))]
            whole = sum(m["seconds"].values())
            true = [(m["seconds"]["similarity"] + m["seconds"]["layers"]) / whole,
                    (m["seconds"]["similarity"] + m["seconds"]["layers"]
                     + m["seconds"]["leaves"]) / whole]
            print(f"  leaves start / end: {100 * true[0]:.1f}% / {100 * true[1]:.1f}% of the run's "
                  f"time, progress.py {100 * (at[0] or 0):.1f}% / {100 * (at[1] or 0):.1f}% "
                  f"({len([s for s in totals if s.startswith(('round ', 'layer '))])} rounds)")
            print(f"  leaves: {leaf_regs} registrations for {m['leaves']} leaves, "
                  f"{per_leaf:.3f} s each against {per_layer:.3f} s in the layers "
                  f"({per_leaf / per_layer:.2f}x); {100 * m['seconds']['leaves'] / decisions:.1f}% "
                  f"of the decisions")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()

"""Issue 9 item 3: the automatic similarity rule's bridges, before and after, side by side.

Before: a pair is similar when D <= max(0.01, D of the subject's 4th nearest, D of the
member's 4th nearest). After: the same, and a subject that rule leaves unreachable from the
root takes its bottleneck D from the root as its limit (``_bridge_limits``). "Before" is
the same code with ``_bridge_limits`` returning nothing, in the same process.

Collections:

- ``archive``: the first N impressions of the 永 designs from ``bench/bench_archive.py``
  (round-robin over the designs; its cache, or generated as it does);
- ``yong``: the 73 永 edge glyphs (``../shared/data/glyphs_yong/points/*_edge.txt``),
  with the default ``working_points``: is the rule the same before and after?

For each: the pairs the tree computes up front, how many subjects the rule's graph reaches
from the root before, how many limits the bridges raise, and (``--tree``) the dynamic tree
both ways: subjects attached in the tree, low-confidence leaves, and for the archive how
many tree edges join two impressions of the same design.

    .venv/bin/python bench/bench_bridge.py [--sizes 150,500] [--yong] [--tree]
        [--processes N]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

import registration._tree._rules as rules
from registration import LocalProcessExecutor, build_dynamic_tree
from registration._executor import Executor
from registration._pose import PoseSpec
from registration._tree._collection import _Collection, _TreeStart
from registration._tree._resolution import DEFAULT_WORKING_POINTS, coarse_collection

HERE = Path(__file__).resolve().parent


@contextmanager
def before() -> Iterator[None]:
    """The rule as it was: no bridges."""
    saved = rules._bridge_limits
    rules._bridge_limits = lambda *a, **k: {}
    try:
        yield
    finally:
        rules._bridge_limits = saved


def rule_figures(shapes: Sequence[np.ndarray], ex: Executor) -> dict[str, object]:
    coll = coarse_collection(_Collection.prepare(shapes, 0, None), DEFAULT_WORKING_POINTS)
    start = _TreeStart.prepare(coll, None, None, PoseSpec.resolve(None, None), ex, None)
    new = start.rule
    with before():
        old = rules._SimilarityRule.build(start.sim, None, 0)
    return {
        "pairs": start.sim.computed,
        "unreached_before": len(new.bridged),
        "same_rule": old.into == new.into and old.out_of == new.out_of,
        "raised": sorted(round(v, 4) for v in new.bridged.values())[:5],
    }


def tree_figures(shapes: Sequence[np.ndarray], truth: np.ndarray | None,
                 ex: Executor) -> dict[str, object]:
    t0 = time.perf_counter()
    res = build_dynamic_tree(shapes, root=0, executor=ex)
    subs = res.subjects
    tree = [s for s in subs if s.parent is not None and not s.leaf]
    out: dict[str, object] = {
        "in_tree": len(tree),
        "leaves": sum(1 for s in subs if s.leaf),
        "none": sum(1 for s in subs if s.parent is None),
        "max_layer": max((s.layer or 0) for s in tree) if tree else 0,
        "bridged": res.thresholds.get("bridged"),
        "wall_s": round(time.perf_counter() - t0, 1),
        "parents": [s.parent for s in subs],
    }
    if truth is not None and tree:
        out["same_design_edges"] = sum(1 for s in tree if truth[s.parent] == truth[s.index])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="150,500")
    ap.add_argument("--yong", action="store_true")
    ap.add_argument("--tree", action="store_true")
    ap.add_argument("--processes", type=int, default=None)
    a = ap.parse_args()
    sets: list[tuple[str, list[np.ndarray], np.ndarray | None]] = []
    sizes = [int(s) for s in a.sizes.split(",") if s]
    if sizes:
        import bench_archive as ba  # type: ignore[import-not-found]

        shapes, truth = ba.archive(max(sizes), 0, 400, Path("/tmp/regtree_archive_0_400.npz"))
        for n in sizes:
            sets.append((f"archive {n} ({len(set(truth[:n].tolist()))} designs)",
                         shapes[:n], truth[:n]))
    if a.yong:
        files = sorted((HERE.parent.parent / "shared/data/glyphs_yong/points").glob("*_edge.txt"))
        if not files:
            files = sorted(Path("/work/shared/data/glyphs_yong/points").glob("*_edge.txt"))
        if not files:
            raise SystemExit("the 永 edge glyphs (shared/data/glyphs_yong/points) are missing")
        sets.append((f"yong edges ({len(files)})", [np.loadtxt(f) for f in files], None))
    with LocalProcessExecutor(a.processes) as ex:
        for name, shapes, truth in sets:
            print(f"== {name}: {len(shapes)} shapes", flush=True)
            print("  rule:", rule_figures(shapes, ex), flush=True)
            if a.tree:
                new = tree_figures(shapes, truth, ex)
                print("  tree after: ", {k: v for k, v in new.items() if k != "parents"},
                      flush=True)
                with before():
                    old = tree_figures(shapes, truth, ex)
                print("  tree before:", {k: v for k, v in old.items() if k != "parents"},
                      flush=True)
                print("  same parents:", old["parents"] == new["parents"], flush=True)


if __name__ == "__main__":
    main()

"""Coarse to fine (issue 9, item 1): the tree decided at 400 points, its edges registered at
the stored resolution, against the same method run entirely at the stored resolution.

Two parts, each method pair run side by side in this process (default options otherwise):

- ``yong``: the 73 永 edge glyphs of ``../shared/data/glyphs_yong/points`` as stored
  (1167-2244 points): ``build_dynamic_tree(shapes, 0)`` (coarse to fine, the default
  ``working_points=400``) against ``working_points=None``; and ``register_direct`` the same
  two ways (one edge per subject, the same path both ways: the cleanest comparison of the
  registrations themselves). Reported: wall time, e (eq. 10, stored resolution) mean and
  p95, parents that agree, and how far apart the two runs' results are, per subject, in
  units of the subject's RMS radius: the RMS distance between the warped root models
  ("warped"), and between the subject points the correspondences pick ("corr").
- ``control``: the stored-resolution stage's CPDs fitted on every model point against
  ``FINE_CONTROL_POINTS`` (500) of them, on the same coarse trees of eight 永 edge
  designs (``deformation_chains``, at most 1800 points a shape, root 0): ground truth
  (all subjects, far half = chain steps 4-6) and the stage's CPU time, serial.
- ``gt``: ground truth. :func:`registration.synthetic.deformation_chains` families of
  three 永 edge designs (rows 0, 36, 72 of index.csv; 4 chains x 6 steps), every shape
  sampling ``--gt-points`` (1200) of the dense edge points, root 0: the RMS distance of
  each warped root point from its true image (units of the subject's RMS radius) for the
  tree coarse to fine, the tree at full resolution and plain CPD at full resolution
  (``register_direct(prealign=False, working_points=None)``).

    .venv/bin/python bench/bench_resolution.py [--part yong|gt|control|all] [--limit N]
        [--gt-points 1200] [--gt-designs 3] [--json PATH]

(``REGTREE_DATA=/path/to/shared/data`` when the data is not at ``../shared/data``.)
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from registration import CollectionResult, build_dynamic_tree, register_direct
from registration.synthetic import correspondence_error, deformation_chains

#: ``../shared/data`` beside the project; ``REGTREE_DATA`` points elsewhere (a worktree).
DATA = Path(os.environ.get("REGTREE_DATA",
                           Path(__file__).resolve().parents[1].parent / "shared" / "data"))
GLYPHS = DATA / "glyphs_yong"


def load_edges(limit: int | None) -> tuple[list[np.ndarray], list[str]]:
    files = sorted((GLYPHS / "points").glob("*_edge.txt"))[:limit]
    return ([np.loadtxt(f).reshape(-1, 2) for f in files],
            [f.name.removesuffix("_edge.txt") for f in files])


def timed(fn: Any, *args: Any, **kw: Any) -> tuple[CollectionResult, float]:
    t0 = time.perf_counter()
    res = fn(*args, **kw)
    return res, time.perf_counter() - t0


def errors(res: CollectionResult, deep: bool = False) -> np.ndarray:
    return np.array([s.error for s in res.subjects if s.error is not None
                     and (not deep or (s.layer or 0) >= 3)])


def compare(shapes: list[np.ndarray], a: CollectionResult,
            b: CollectionResult) -> dict[str, Any]:
    """How far apart two results on the same shapes are, subject by subject."""
    warped, corr, same_parent = [], [], []
    for sa, sb in zip(a.subjects, b.subjects, strict=True):
        if sa.warped is None or sb.warped is None:
            continue
        assert sa.correspondence is not None and sb.correspondence is not None
        assert sa.transform is not None
        y = shapes[sa.index]
        scale = sa.transform.target.scale
        warped.append(float(np.sqrt(np.mean(np.sum((sa.warped - sb.warped) ** 2, 1)))) / scale)
        picked = y[sa.correspondence] - y[sb.correspondence]
        corr.append(float(np.sqrt(np.mean(np.sum(picked**2, 1)))) / scale)
        same_parent.append(sa.parent == sb.parent)
    w, c, sp = np.array(warped), np.array(corr), np.array(same_parent)
    out = {"n": len(w), "parents_agree": int(sp.sum()),
           "warped_median": float(np.median(w)), "warped_p95": float(np.percentile(w, 95)),
           "corr_median": float(np.median(c)), "corr_p95": float(np.percentile(c, 95))}
    if sp.any():
        out["same_parent_warped_median"] = float(np.median(w[sp]))
        out["same_parent_corr_median"] = float(np.median(c[sp]))
    return out


def line(name: str, res: CollectionResult, t: float) -> str:
    e, d = errors(res), errors(res, deep=True)
    conf = np.array([s.confidence for s in res.subjects if s.confidence is not None])
    return (f"{name:<22} {t:8.1f}  {e.mean():.5f} {np.percentile(e, 95):.5f}  "
            f"{d.mean() if len(d) else float('nan'):.5f} ({len(d):2d})  "
            f"{conf.mean():.3f}  {sum(s.leaf for s in res.subjects):3d}")


def part_yong(limit: int | None) -> dict[str, Any]:
    shapes, names = load_edges(limit)
    if not shapes:
        print(f"NOTE: {GLYPHS} is missing: skipping the 永 part")
        return {}
    sizes = [len(s) for s in shapes]
    print(f"{len(shapes)} 永 edge glyphs, {min(sizes)}-{max(sizes)} points "
          f"(median {int(np.median(sizes))}), root 0")
    out: dict[str, Any] = {}
    print(f"{'run':<22} {'seconds':>8}  e mean  e p95    e L>=3 (n)  conf  leaves")
    for label, fn in (("tree", build_dynamic_tree), ("direct", register_direct)):
        c2f, tc = timed(fn, shapes, 0, names=names)
        print(line(f"{label} c2f (400)", c2f, tc), flush=True)
        full, tf = timed(fn, shapes, 0, names=names, working_points=None)
        print(line(f"{label} full res", full, tf), flush=True)
        cmp = compare(shapes, c2f, full)
        print(f"  {label}: c2f/full time {tc / tf:.2f}, e mean ratio "
              f"{errors(c2f).mean() / errors(full).mean():.3f}; parents agree "
              f"{cmp['parents_agree']}/{cmp['n']}; c2f vs full per subject: warped "
              f"median {cmp['warped_median']:.4f} p95 {cmp['warped_p95']:.4f}, corr median "
              f"{cmp['corr_median']:.4f} p95 {cmp['corr_p95']:.4f}"
              + (f"; same parent: warped {cmp['same_parent_warped_median']:.4f} corr "
                 f"{cmp['same_parent_corr_median']:.4f}" if label == "tree"
                 and "same_parent_warped_median" in cmp else ""), flush=True)
        ratio = errors(c2f) / errors(full)
        print(f"  e c2f/full per subject: median {np.median(ratio):.3f}, "
              f"5-95% {np.percentile(ratio, 5):.3f}-{np.percentile(ratio, 95):.3f}, "
              f"max {ratio.max():.3f}", flush=True)
        out[label] = {"c2f_s": tc, "full_s": tf, "e_c2f": float(errors(c2f).mean()),
                      "e_full": float(errors(full).mean()), **cmp}
    return out


def design_ids() -> list[str]:
    """The designs of ``glyphs_yong/index.csv`` in its order; none when it is missing."""
    index = GLYPHS / "index.csv"
    if not index.exists():
        return []
    with index.open(newline="") as fh:
        return [row["id"] for row in csv.DictReader(fh)]


def part_gt(points: int, designs: int) -> dict[str, Any]:
    ids = design_ids()
    if not ids:
        print(f"NOTE: {GLYPHS} is missing: skipping the ground-truth part")
        return {}
    runs = {
        "tree c2f": lambda s: build_dynamic_tree(s, 0),
        "tree full": lambda s: build_dynamic_tree(s, 0, working_points=None),
        "plain CPD full": lambda s: register_direct(s, 0, prealign=False, working_points=None),
    }
    gt: dict[str, list[float]] = {k: [] for k in runs}
    secs = dict.fromkeys(runs, 0.0)
    for design in (ids[0], ids[36], ids[72])[:designs]:
        dense = np.loadtxt(GLYPHS / "points" / f"{design}_edge.txt")
        fam = deformation_chains(dense, n_points=min(points, len(dense)), seed=0)
        truth = fam.root_images(0)
        for name, run in runs.items():
            res, t = timed(run, fam.shapes)
            secs[name] += t
            errs = [correspondence_error(s.warped, truth[s.index], fam.shapes[s.index])
                    for s in res.subjects if s.warped is not None]
            gt[name].extend(errs)
            print(f"  {design:<24} {name:<15} GT {np.mean(errs):.4f}  {t:6.1f} s", flush=True)
    print(f"{'run':<15} {'GT mean':>8} {'GT p95':>8} {'/ plain':>8} {'seconds':>8}")
    plain = float(np.mean(gt["plain CPD full"]))
    for name, v in gt.items():
        print(f"{name:<15} {np.mean(v):8.4f} {np.percentile(v, 95):8.4f} "
              f"{np.mean(v) / plain:8.2f} {secs[name]:8.1f}")
    return {name: {"gt_mean": float(np.mean(v)), "seconds": secs[name]}
            for name, v in gt.items()}


def part_control(points: int, designs: list[int]) -> dict[str, Any]:
    """The stored-resolution stage with its CPDs' fields fitted on every model point
    against :data:`FINE_CONTROL_POINTS` of them, on one coarse tree per family (captured
    from the default run, then the stage run again serially, both ways, in this process),
    the dynamic tree's polish there included as the default runs it (every CPD of that
    polish fits its field with the same control points)."""
    import copy

    from registration import SerialExecutor
    from registration._tree import _methods, _resolution

    ids = design_ids()
    if not ids:
        print(f"NOTE: {GLYPHS} is missing: skipping the control-point part")
        return {}
    stage = _resolution.at_stored_resolution
    captured: dict[str, Any] = {}

    def capture(result: CollectionResult, *args: Any, **kwargs: Any) -> CollectionResult:
        captured["args"] = (copy.deepcopy(result), *args[:4])
        captured["polish"] = kwargs.get("polish", False)
        return stage(result, *args, **kwargs)

    settings = {"every point": 10**9, "control": _resolution.FINE_CONTROL_POINTS}
    default = _resolution.FINE_CONTROL_POINTS
    gt: dict[str, list[float]] = {k: [] for k in settings}
    far: dict[str, list[float]] = {k: [] for k in settings}
    cpu = dict.fromkeys(settings, 0.0)
    _methods.at_stored_resolution = capture  # type: ignore[assignment]
    try:
        for row in designs:
            design = ids[row]
            dense = np.loadtxt(GLYPHS / "points" / f"{design}_edge.txt")
            fam = deformation_chains(dense, n_points=min(points, len(dense)), seed=0)
            truth = fam.root_images(0)
            build_dynamic_tree(fam.shapes, 0)
            coarse_result, full, coarse, cpd, wp = captured["args"]
            line = f"{design[:26]:<26} {len(dense):5d}"
            for name, k in settings.items():
                _resolution.FINE_CONTROL_POINTS = k
                t = time.process_time()
                res = stage(copy.deepcopy(coarse_result), full, coarse, cpd, wp,
                            SerialExecutor(), None, polish=captured["polish"])
                cpu[name] += time.process_time() - t
                errs = {s.index: correspondence_error(s.warped, truth[s.index],
                                                      fam.shapes[s.index])
                        for s in res.subjects if s.warped is not None and s.index != 0}
                deep = [e for i, e in errs.items() if fam.depth[i] >= 4]
                gt[name].extend(errs.values())
                far[name].extend(deep)
                line += f"  {name}: GT {np.mean(list(errs.values())):.4f} far {np.mean(deep):.4f}"
            print(line, flush=True)
    finally:
        _methods.at_stored_resolution = stage
        _resolution.FINE_CONTROL_POINTS = default
    base, base_far = np.mean(gt["every point"]), np.mean(far["every point"])
    out = {}
    for name in settings:
        out[name] = {"gt": float(np.mean(gt[name])), "far": float(np.mean(far[name])),
                     "cpu_s": cpu[name]}
        print(f"{name:<12} GT {out[name]['gt']:.4f} ({out[name]['gt'] / base:.3f}x)  far "
              f"{out[name]['far']:.4f} ({out[name]['far'] / base_far:.3f}x)  stage CPU "
              f"{cpu[name]:.1f} s")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--part", choices=["yong", "gt", "control", "all"], default="all")
    ap.add_argument("--limit", type=int, default=None, help="first N glyphs only")
    ap.add_argument("--gt-points", type=int, default=1200)
    ap.add_argument("--gt-designs", type=int, default=3, help="the first 1-3 of rows 0, 36, 72")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    out: dict[str, Any] = {}
    if args.part in ("yong", "all"):
        out["yong"] = part_yong(args.limit)
    if args.part in ("gt", "all"):
        out["gt"] = part_gt(args.gt_points, args.gt_designs)
    if args.part in ("control", "all"):
        out["control"] = part_control(1800, [0, 36, 72, 12, 50, 20, 60, 5])
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""Correspondences on real shapes: homologous landmarks of the lmfree2d classes.

The ground-truth benchmark (bench_groundtruth.py) knows every point's true image because it
deforms one shape synthetically. Here the shapes are real and different (9 lmfree2d
classes x 10 outlines: Bell, Comma, Device8, Face, Flatfish, Hammer, Heart, Horseshoe,
Key), and the truth is sparse: each outline comes with 8 homologous landmarks placed by
hand. Every method registers the root's outline onto every other one with default options;
the root's landmarks are then moved by the subject's reported transform (the chain the tree
reports maps the root's coordinates onto the subject's) and compared with the subject's
own. Landmark error = RMS distance between the two, in units of the subject's RMS radius.
Methods: plain CPD (``register_direct(prealign=False)``, the paper's baseline and the
ratios' denominator), direct CPD (``register_direct`` defaults) and the dynamic tree; roots:
the first and the sixth outline of each class. The landmarks carry their annotators'
placement noise, which no registration can remove: ratios near 1 on a class say little.

Reads ../shared/data/lmfree2d; says so and exits 0 when it is missing.

    .venv/bin/python bench/bench_landmarks.py [--roots 0 5] [--only Bell Key] [--json F]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from registration import CollectionResult, build_dynamic_tree, register_direct  # noqa: E402

DATA = REPO.parent / "shared" / "data" / "lmfree2d"
METHODS = ("plain", "direct", "tree")


def _read(path: Path) -> dict[int, np.ndarray]:
    """Shape id -> its (n, 2) points, in file order."""
    out: dict[int, list[list[float]]] = {}
    with path.open(newline="") as fh:
        for row in csv.DictReader(fh):
            out.setdefault(int(row["Shape"]), []).append([float(row["X"]), float(row["Y"])])
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


def load_class(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The outlines of one class and their landmarks, in shape-id order."""
    contours = _read(folder / "contours.csv")
    landmarks = _read(folder / "landmarks.csv")
    ids = sorted(set(contours) & set(landmarks))
    return [contours[i] for i in ids], [landmarks[i] for i in ids]


def run(method: str, shapes: list[np.ndarray], root: int) -> CollectionResult:
    if method == "plain":
        return register_direct(shapes, root=root, prealign=False)
    if method == "direct":
        return register_direct(shapes, root=root)
    return build_dynamic_tree(shapes, root=root)


def landmark_errors(result: CollectionResult, shapes: list[np.ndarray],
                    landmarks: list[np.ndarray], root: int) -> dict[int, float]:
    """Subject -> the RMS landmark error over its radius (NaN: no registration)."""
    out: dict[int, float] = {}
    for s in result.subjects:
        if s.index == root:
            continue
        y = shapes[s.index]
        radius = float(np.sqrt(((y - y.mean(axis=0)) ** 2).sum(axis=1).mean()))
        if s.transform is None:
            out[s.index] = float("nan")
            continue
        moved = s.transform.apply(landmarks[root])
        out[s.index] = float(np.sqrt(((moved - landmarks[s.index]) ** 2).sum(axis=1).mean())
                             / radius)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--roots", type=int, nargs="*", default=[0, 5],
                    help="root outlines (positions in each class, default 0 5)")
    ap.add_argument("--only", nargs="*", default=None, help="classes to run")
    ap.add_argument("--json", type=Path, default=None, help="dump every per-subject number")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"{DATA} is missing (the shared data folder sits beside the project): "
              "nothing to run")
        return 0
    classes = sorted(p.name for p in DATA.iterdir()
                     if (p / "contours.csv").exists() and (p / "landmarks.csv").exists())
    if args.only:
        classes = [c for c in classes if c in set(args.only)]
    rows: list[dict[str, Any]] = []
    seconds = dict.fromkeys(METHODS, 0.0)
    print(f"lmfree2d landmarks: {len(classes)} classes, roots {args.roots}; landmark error "
          "over the subject's RMS radius, mean (p95) over subjects, default options\n")
    print(f"{'class':10s} {'n':>3s} | {'plain':>15s} {'direct':>15s} {'tree':>15s} | "
          f"{'tree/pl':>7s} {'dir/pl':>6s} | unattached")
    pooled: dict[str, list[float]] = {m: [] for m in METHODS}
    worse: list[str] = []  # classes where the tree is worse than plain CPD
    for cls in classes:
        shapes, landmarks = load_class(DATA / cls)
        errs: dict[str, list[float]] = {m: [] for m in METHODS}
        for root in args.roots:
            if not 0 <= root < len(shapes):
                continue
            for method in METHODS:
                t = time.perf_counter()
                result = run(method, shapes, root)
                seconds[method] += time.perf_counter() - t
                for subject, e in landmark_errors(result, shapes, landmarks, root).items():
                    errs[method].append(e)
                    rows.append({"class": cls, "root": root, "method": method,
                                 "subject": subject, "landmark_error": e})
        for m in METHODS:
            pooled[m] += errs[m]

        def cell(v: list[float]) -> str:
            a = np.asarray(v, dtype=np.float64)
            a = a[np.isfinite(a)]
            return f"{a.mean():.4f} ({np.percentile(a, 95):.3f})" if a.size else "-"

        pl = np.nanmean(errs["plain"])
        if np.nanmean(errs["tree"]) > pl:
            worse.append(cls)
        print(f"{cls:10s} {len(errs['tree']):3d} | {cell(errs['plain']):>15s} "
              f"{cell(errs['direct']):>15s} {cell(errs['tree']):>15s} | "
              f"{np.nanmean(errs['tree']) / pl:7.3f} {np.nanmean(errs['direct']) / pl:6.3f} | "
              f"{int(np.isnan(errs['tree']).sum())}")
    if pooled["plain"]:
        pl = np.nanmean(pooled["plain"])
        print(f"{'ALL':10s} {len(pooled['tree']):3d} | {np.nanmean(pooled['plain']):15.4f} "
              f"{np.nanmean(pooled['direct']):15.4f} {np.nanmean(pooled['tree']):15.4f} | "
              f"{np.nanmean(pooled['tree']) / pl:7.3f} {np.nanmean(pooled['direct']) / pl:6.3f}")
        print(f"classes where the tree is worse than plain CPD: {', '.join(worse) or 'none'}")
    print("seconds: " + "  ".join(f"{m} {seconds[m]:.1f}" for m in METHODS))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
        print(f"per-subject numbers written to {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The paper's protocol (Du et al. 2016, Table 1-3): direct CPD vs static tree vs dynamic tree.

For every data set and root model, the root is registered to every other shape four
ways: plain CPD (no pre-alignment, as the paper's baseline), direct CPD after the affine-
ICP pre-alignment (regtree's `register_direct` default), the static tree and the dynamic
tree. The table gives the mean and 95th percentile of e (eq. 10, size-normalised shapes)
on the subjects the dynamic tree placed at layer >= 3 (the paper's statistic: on layer 2
the dynamic tree *is* direct CPD), for every method on those same subjects. Where ground
truth exists (Chui & Rangarajan deformation series, a generated chained family) it also
gives the RMS ground-truth correspondence error (relative to the subject's RMS radius).

Reads ../shared/data; data sets that are missing are reported and skipped (the generated
family always runs).

    .venv/bin/python bench/bench_tree.py [--only NAME ...] [--points 400] [--out bench/RESULTS.md]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from registration import (
    CollectionResult,
    LocalProcessExecutor,
    SubjectResult,
    build_dynamic_tree,
    build_static_tree,
    register_direct,
    resample,
)
from registration.synthetic import chained_family, correspondence_error

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass
class Dataset:
    name: str
    shapes: list[np.ndarray]
    names: list[str]
    # ground truth: for subject k, where each root point should land, else None
    truth: Callable[[int], np.ndarray] | None = None


def _mpeg7(cls: str, points: int) -> Dataset | None:
    files = sorted((DATA / "mpeg7" / cls).glob(f"{cls}-*.npy"),
                   key=lambda p: int(p.stem.split("-")[-1]))
    if not files:
        return None
    return Dataset(f"mpeg7-{cls}", [resample(np.load(f), points) for f in files],
                   [f.stem for f in files])


def _glyphs(kind: str, points: int) -> Dataset | None:
    folder = DATA / "glyphs_yong" / "points"
    files = sorted(folder.glob(f"*_{kind}.txt"))
    if not files:
        return None
    return Dataset(f"yong-{kind}", [resample(np.loadtxt(f), points) for f in files],
                   [f.name.removesuffix(f"_{kind}.txt") for f in files])


def _nsfishes(limit: int) -> Dataset | None:
    path = DATA / "momocs" / "nsfishes.npz"
    if not path.exists():
        return None
    d = np.load(path)
    keys = sorted(d.files)[:limit]
    return Dataset("nsfishes", [np.asarray(d[k], dtype=float) for k in keys], keys)


def _chui(kind: str, trials: int) -> Dataset | None:
    files = [DATA / "chui_rangarajan" / f"{kind}_def_{lvl}.npz" for lvl in range(1, 6)]
    if not all(f.exists() for f in files):
        return None
    shapes, names, gts, clean = [], [], [], []
    model = None
    for lvl, f in enumerate(files, start=1):
        d = np.load(f)
        if model is None:
            model = d["X"][0]
            shapes.append(model)
            clean.append(model)
            names.append("model")
            gts.append(np.arange(len(model)))
        gt = d["gt_index_into_X"]
        for t in range(trials):
            shapes.append(d["Y"][t])
            clean.append(d["Y_clean"][t])
            names.append(f"def{lvl}-trial{t}")
            gts.append(gt)

    def truth(k: int) -> np.ndarray:
        # Y row i is the image of model row gt[i] (deformation series: no outliers)
        image = np.empty_like(shapes[0])
        image[gts[k]] = clean[k]
        return image

    return Dataset(f"chui-{kind}-def1-5", shapes, names, truth)


def _generated() -> Dataset:
    fam = chained_family(n_chains=4, chain_length=6, n_points=200, step=0.35, seed=7)

    def truth(k: int) -> np.ndarray:
        return fam.root_images[k]

    return Dataset("generated-chains", fam.shapes, fam.names, truth)


def load_all(points: int, ns_limit: int, chui_trials: int) -> tuple[list[Dataset], list[str]]:
    makers: list[tuple[str, Callable[[], Dataset | None]]] = [
        *[(f"mpeg7-{c}", lambda c=c: _mpeg7(c, points))  # type: ignore[misc]
          for c in ("fish", "lmfish", "flatfish", "horse", "bird", "bat", "camel", "deer")],
        ("yong-edge", lambda: _glyphs("edge", points)),
        ("yong-skel", lambda: _glyphs("skel", points)),
        ("nsfishes", lambda: _nsfishes(ns_limit)),
        ("chui-fish", lambda: _chui("fish", chui_trials)),
        ("chui-chinese", lambda: _chui("chinese", chui_trials)),
        ("generated-chains", _generated),
    ]
    found, missing = [], []
    for name, make in makers:
        ds = make()
        if ds is None:
            missing.append(name)
        else:
            found.append(ds)
    return found, missing


def _stats(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    a = np.asarray(values)
    return float(a.mean()), float(np.percentile(a, 95))


def _ce(ds: Dataset, s: SubjectResult) -> float | None:
    if ds.truth is None or s.warped is None:
        return None
    return correspondence_error(s.warped, ds.truth(s.index), ds.shapes[s.index])


def evaluate(
    ds: Dataset, dyn: CollectionResult, sta: CollectionResult, plain: CollectionResult
) -> dict[str, object]:
    assert dyn.direct is not None
    deep = [s for s in dyn.subjects if s.attached and s.layer is not None and s.layer >= 3]
    idx = {s.index for s in deep}
    direct = {s.index: s for s in dyn.direct}
    static = {s.index: s for s in sta.subjects}
    plain_by = {s.index: s for s in plain.subjects}
    conf = [s.confidence for s in dyn.subjects if s.confidence is not None]
    row: dict[str, object] = {
        "dataset": f"{ds.name} (root {ds.names[dyn.root]})",
        "shapes": len(ds.shapes),
        "attached": sum(s.attached for s in dyn.subjects),
        "leaves": sum(s.leaf for s in dyn.subjects),
        "confidence": (float(np.median(conf)) if conf else float("nan"),
                       float(np.mean(np.asarray(conf) >= 0.5)) if conf else float("nan")),
        "rotated": sum(1 for s in dyn.subjects if s.quality and s.quality["pose"] == "rotated"),
        "depth": dyn.summary()["depth"],
        "n_deep": len(deep),
        "thresholds": (dyn.thresholds["similarity"], dyn.thresholds["error"]),
    }
    for label, group in [
        ("plain", [plain_by[i] for i in sorted(idx)]),
        ("direct", [direct[i] for i in sorted(idx)]),
        ("static", [static[i] for i in sorted(idx) if static[i].attached]),
        ("dynamic", deep),
    ]:
        row[f"{label}_e"] = _stats([s.error for s in group if s.error is not None])
        ces = [c for s in group if (c := _ce(ds, s)) is not None]
        row[f"{label}_ce"] = _stats(ces) if ces else None
    return row


def fmt(v: float) -> str:
    return "n/a" if not np.isfinite(v) else f"{v:.4g}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--points", type=int, default=400, help="resample image sets to this")
    ap.add_argument("--ns-limit", type=int, default=218)
    ap.add_argument("--chui-trials", type=int, default=8)
    ap.add_argument("--roots", default="0,2",
                    help="comma-separated root indices, each run separately (the paper "
                    "reports two models per data set)")
    ap.add_argument("--pose", default=None,
                    help="pose mode of the pre-alignment (default: the library's)")
    ap.add_argument("--max-rotation", type=float, default=None,
                    help="upright collections: ICP starts within +- this many degrees")
    ap.add_argument("--no-prealign", action="store_true",
                    help="no affine pre-alignment before CPD in the trees and direct CPD")
    ap.add_argument("--out", type=Path, default=None, help="also write a markdown table here")
    args = ap.parse_args()
    datasets, missing = load_all(args.points, args.ns_limit, args.chui_trials)
    if missing:
        print(f"NOTE: {DATA} lacks: {', '.join(missing)} (skipped)")
    if args.only:
        datasets = [d for d in datasets if d.name in args.only or
                    any(d.name.startswith(o) for o in args.only)]
    rows = []
    roots = [int(r) for r in args.roots.split(",")]
    with LocalProcessExecutor() as ex:
        for ds in datasets:
            for root in roots:
                t0 = time.perf_counter()
                opts = {"pose": args.pose, "max_rotation": args.max_rotation,
                        "prealign": not args.no_prealign}
                dyn = build_dynamic_tree(ds.shapes, root, names=ds.names, compare_direct=True,
                                         executor=ex, **opts)
                t1 = time.perf_counter()
                # the same (automatic, per-pair) similarity rule as the dynamic tree
                sta = build_static_tree(ds.shapes, root, names=ds.names, executor=ex, **opts)
                t2 = time.perf_counter()
                plain = register_direct(ds.shapes, root, names=ds.names, executor=ex,
                                        prealign=False)
                row = evaluate(ds, dyn, sta, plain)
                row["seconds"] = (t1 - t0, t2 - t1)
                rows.append(row)
                print(_line(row), flush=True)
    table = _markdown(rows)
    print()
    print(table)
    print(f"\noptions: pose={args.pose}, max_rotation={args.max_rotation}, "
          f"prealign={not args.no_prealign} (None: the library's default)")
    if args.out is not None:
        args.out.write_text(table + "\n")


def _line(r: dict[str, object]) -> str:
    de, se, ye = r["direct_e"], r["static_e"], r["dynamic_e"]
    assert isinstance(de, tuple) and isinstance(ye, tuple) and isinstance(se, tuple)
    pe = r["plain_e"]
    assert isinstance(pe, tuple)
    return (f"{r['dataset']:22s} shapes={r['shapes']} attached={r['attached']} "
            f"(leaves {r['leaves']}, rotated poses {r['rotated']}) "
            f"depth={r['depth']} layer>=3: {r['n_deep']}  e mean/p95 plain "
            f"{fmt(pe[0])}/{fmt(pe[1])} direct "
            f"{fmt(de[0])}/{fmt(de[1])} static {fmt(se[0])}/{fmt(se[1])} dynamic "
            f"{fmt(ye[0])}/{fmt(ye[1])}  seconds {r['seconds']}")


def _markdown(rows: list[dict[str, object]]) -> str:
    out = [
        "| data set (root) | shapes | registered (leaves) | confidence median, share >= 0.5 "
        "| depth | layer >= 3 | plain CPD e mean / p95 "
        "| direct CPD e mean / p95 | static e mean / p95 | dynamic e mean / p95 | "
        "dynamic / plain (mean, p95) | dynamic / direct (mean, p95) | GT corr. error plain / "
        "direct / static / dynamic (mean) | thresholds (D, e) | seconds (dynamic+direct, "
        "static) |",
        "|" + "---|" * 15,
    ]
    for r in rows:
        pe, de, se, ye = r["plain_e"], r["direct_e"], r["static_e"], r["dynamic_e"]
        assert isinstance(de, tuple) and isinstance(se, tuple) and isinstance(ye, tuple)
        assert isinstance(pe, tuple)
        ratio = (f"{ye[0] / de[0]:.2f}, {ye[1] / de[1]:.2f}"
                 if np.isfinite(de[0]) and de[0] > 0 and np.isfinite(ye[0]) else "n/a")
        ratio_p = (f"{ye[0] / pe[0]:.2f}, {ye[1] / pe[1]:.2f}"
                   if np.isfinite(pe[0]) and pe[0] > 0 and np.isfinite(ye[0]) else "n/a")
        cf = r["confidence"]
        assert isinstance(cf, tuple)
        ce = "n/a"
        if r.get("dynamic_ce"):
            parts = []
            for k in ("plain_ce", "direct_ce", "static_ce", "dynamic_ce"):
                v = r.get(k)
                parts.append(fmt(v[0]) if isinstance(v, tuple) else "n/a")
            ce = " / ".join(parts)
        th = r["thresholds"]
        sec = r["seconds"]
        assert isinstance(th, tuple) and isinstance(sec, tuple)
        out.append(
            f"| {r['dataset']} | {r['shapes']} | {r['attached']} ({r['leaves']}) | "
            f"{cf[0]:.2f}, {cf[1]:.2f} | {r['depth']} | "
            f"{r['n_deep']} | {fmt(pe[0])} / {fmt(pe[1])} | {fmt(de[0])} / {fmt(de[1])} | "
            f"{fmt(se[0])} / {fmt(se[1])} | "
            f"{fmt(ye[0])} / {fmt(ye[1])} | {ratio_p} | {ratio} | {ce} | "
            f"{fmt(th[0])}, {fmt(th[1])} | "
            f"{sec[0]:.0f}, {sec[1]:.0f} |"
        )
    return "\n".join(out)


if __name__ == "__main__":
    main()

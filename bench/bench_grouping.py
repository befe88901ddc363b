"""Grouping impressions by mould (issue 11): adjusted Rand index and time.

Settings (each: moulds x impressions, simulated by :mod:`registration.impressions`, each
scan encoded as PNG and turned into points by the service's image ingestion,
``service.ingest.points_from_image``, mode ``contour``):

- ``yong``: 40 distinct 永 designs (``../shared/data/glyphs_yong/png``, thresholded at
  128; designs that render identically are merged first) x 5 impressions;
- ``yong-recut``: 20 designs, each with a twin whose one stroke end is recut (one stroke
  width shorter or longer), x 5 impressions: 40 moulds that differ in pairs by one stroke;
- ``strokes``: a second character drawn procedurally (``draw_strokes``), 40 "carvers"
  that place its strokes differently (ends moved by up to 4 % of the size), x 5;
- ``mpeg7``: 40 MPEG-7 silhouettes (``../shared/data/mpeg7``) as moulds, x 5;
- ``time``: 200 instances (40 x 5 of ``yong``), wall time of ``group_instances``;
- ``service``: the ``yong`` scans as PNG files through the service end to end: uploaded
  to a local ``regtree serve`` (image ingestion there), grouped by a ``grouping`` job
  (not in the default list: it starts a server).

For every setting: same-mould and different-mould distance quantiles (the data for the
automatic threshold), the threshold chosen, ARI against the true moulds.

    .venv/bin/python bench/bench_grouping.py [--settings yong,yong-recut,...] [--seed 0]
        [--moulds 40] [--impressions 5] [--cache DIR] [--rules]
"""

from __future__ import annotations

import argparse
import io
import resource
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.cluster.hierarchy import fcluster

from registration import group_instances
from registration._grouping import ATTACH_FACTOR, _attach_lone
from registration.impressions import (
    draw_strokes,
    identical_moulds,
    impression_set,
    recut_stroke_end,
)
from service.ingest import points_from_image

# ../shared/data beside the project (or beside the folder holding its worktrees)
DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents[1:]
             if (p / "shared" / "data").is_dir()),
            Path(__file__).resolve().parents[1].parent / "shared" / "data")
GLYPHS = DATA / "glyphs_yong" / "png"
MPEG7 = DATA / "mpeg7"
TARGET_POINTS = 3000
#: Cuts of the average-linkage tree shown beside the default one (the automatic threshold
#: is NOISE_FACTOR x the noise level, within bounds).
CUT_FACTORS = (1.5, 1.75, 2.0, 2.25, 2.5, 3.0, 3.5)


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Hubert and Arabie's adjusted Rand index of two labelings."""
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    table = np.zeros((ai.max() + 1, bi.max() + 1))
    np.add.at(table, (ai, bi), 1)

    def pairs(x: np.ndarray) -> float:
        return float((x * (x - 1) / 2).sum())

    index, rows, cols = pairs(table), pairs(table.sum(1)), pairs(table.sum(0))
    expected = rows * cols / (len(a) * (len(a) - 1) / 2)
    top = (rows + cols) / 2
    return 1.0 if top == expected else (index - expected) / (top - expected)


def to_points(img: np.ndarray) -> np.ndarray:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return points_from_image(buf.getvalue(), mode="contour", target_points=TARGET_POINTS)


def yong_moulds(count: int, seed: int) -> list[np.ndarray]:
    files = sorted(GLYPHS.glob("*.png"))
    masks = [np.asarray(Image.open(f).convert("L")) < 128 for f in files]
    groups = identical_moulds(masks)
    print(f"  {len(files)} designs, {len(groups)} distinct after merging identical renders")
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(groups), size=min(count, len(groups)), replace=False)
    return [masks[groups[int(g)][0]] for g in pick]


def recut_moulds(count: int, seed: int) -> list[np.ndarray]:
    base = yong_moulds(count // 2, seed + 1)
    out = []
    for k, m in enumerate(base):
        r = recut_stroke_end(m, seed=seed + k)
        out += [m, r.mould]
    return out


STROKES_BASE = np.array([  # a character like 王 with a dot: 4 horizontals, 1 vertical, dot
    [0.18, 0.20, 0.82, 0.20], [0.25, 0.50, 0.75, 0.50], [0.12, 0.82, 0.88, 0.82],
    [0.50, 0.20, 0.50, 0.82], [0.70, 0.60, 0.78, 0.70], [0.30, 0.30, 0.38, 0.40],
])


def stroke_moulds(count: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        s = STROKES_BASE + rng.uniform(-0.04, 0.04, STROKES_BASE.shape)
        out.append(draw_strokes(s, size=200, width=rng.uniform(0.05, 0.09)))
    return out


def mpeg7_moulds(count: int, seed: int) -> list[np.ndarray]:
    from matplotlib.path import Path as MPath

    files = sorted(MPEG7.glob("*/*.npy"))
    rng = np.random.default_rng(seed)
    out = []
    for f in rng.choice(len(files), size=min(count, len(files)), replace=False):
        c = np.load(files[int(f)]).astype(np.float64)
        c = (c - c.min(0)) * (220.0 / np.ptp(c, axis=0).max()) + 18
        yy, xx = np.mgrid[0:256, 0:256] + 0.5
        inside = MPath(c).contains_points(np.c_[xx.ravel(), yy.ravel()])
        out.append(inside.reshape(256, 256))
    return out


SETTINGS: dict[str, Callable[[int, int], list[np.ndarray]]] = {
    "yong": yong_moulds, "yong-recut": recut_moulds, "strokes": stroke_moulds,
    "mpeg7": mpeg7_moulds,
}
NEEDS_DATA = {"yong", "yong-recut", "mpeg7", "time", "service"}


def distance_quantiles(D: np.ndarray, truth: np.ndarray) -> str:
    same = truth[:, None] == truth[None, :]
    iu = np.triu_indices(len(truth), 1)
    known = ~np.isnan(D[iu])
    s = D[iu][known & same[iu]]
    d = D[iu][known & ~same[iu]]

    def q(x: np.ndarray, p: float) -> str:
        return f"{np.quantile(x, p):.3f}" if len(x) else "-"

    return (f"same n={len(s)} median {q(s, .5)} p95 {q(s, .95)} max {q(s, 1)} | "
            f"different n={len(d)} min {q(d, 0)} p5 {q(d, .05)} median {q(d, .5)}")


def scans(name: str, moulds: int, n: int, seed: int, cache: Path | None
          ) -> tuple[list[np.ndarray], np.ndarray]:
    """The setting's scans as points; with `cache`, kept in (and read back from) a pickle
    named after the setting and its arguments."""
    import pickle

    base = "yong" if name == "time" else name
    path = None if cache is None else cache / f"{base}-{moulds}x{n}-seed{seed}.pkl"
    if path is not None and path.is_file():
        with path.open("rb") as f:
            shapes, truth = pickle.load(f)
        print(f"  scans read from {path}")
        return shapes, truth
    shapes, truth = impression_set(SETTINGS[base](moulds, seed), n, to_points=to_points,
                                   seed=seed)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as f:
            pickle.dump((shapes, truth), f)
    return shapes, truth


def run(name: str, moulds: int, n: int, seed: int, cache: Path | None = None,
        rules: bool = False) -> dict[str, float]:
    t0 = time.perf_counter()
    shapes, truth = scans(name, moulds, n, seed, cache)
    t1 = time.perf_counter()
    c1 = _cpu()
    res = group_instances(shapes)
    t2 = time.perf_counter()
    cpu = _cpu() - c1
    ari = adjusted_rand_index(res.labels, truth)
    print(f"  {len(shapes)} instances ({np.mean([len(s) for s in shapes]):.0f} points), "
          f"simulated + ingested in {t1 - t0:.1f} s")
    print(f"  {distance_quantiles(res.distances, truth)}")
    print(f"  noise level {res.noise_level:.4f}, threshold {res.threshold:.4f} "
          f"({res.threshold_source}), {res.n_groups} groups for {len(set(truth))} moulds, "
          f"{res.pairs_computed} pairs, ARI {ari:.3f}, group_instances {t2 - t1:.1f} s "
          f"wall, {cpu:.1f} s CPU (this process and its pool)")
    for rule, attach in (("cut only", False), ("cut + lone prints attached", True)):
        sweep = {}
        for f in CUT_FACTORS:
            thr = f * res.noise_level
            labels = np.asarray(fcluster(res.linkage, thr, "distance") - 1, dtype=np.intp)
            if attach:
                labels = _attach_lone(res.distances, labels, ATTACH_FACTOR * thr)
            sweep[f] = adjusted_rand_index(labels, truth)
        print(f"  ARI by cut (x noise level), {rule}: "
              + ", ".join(f"{f:g}x {a:.3f}" for f, a in sweep.items()))
    if rules:
        from grouping_rules import rule_table

        table = rule_table(res.distances, np.asarray(truth), adjusted_rand_index)
        subs = list(next(iter(table.values())))
        print(f"  ARI by rule (same distances){'':14s}" + "".join(f"{s:>10s}" for s in subs))
        for rule_name, row in table.items():
            print(f"    {rule_name:40s}" + "".join(f"{row[s]:10.3f}" for s in subs))
    return {"ari": ari, "seconds": t2 - t1, "cpu": cpu, "threshold": res.threshold}


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the process pool)."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def run_service(moulds: int, n: int, seed: int) -> dict[str, float]:
    """The ``yong`` scans (the same images) written as PNG files, uploaded to a local
    ``regtree serve`` (one worker) with ``regtree``'s client, grouped by a grouping job."""
    import tempfile

    from bench_service import local_service

    from registration.impressions import simulate_impressions
    from service.client import RegtreeClient

    ms = yong_moulds(moulds, seed)
    rng = np.random.default_rng(seed)  # as impression_set draws them: the same scans
    with tempfile.TemporaryDirectory() as tmp:
        files, truth = [], []
        for k, m in enumerate(ms):
            for j, img in enumerate(simulate_impressions(m, n, seed=rng)):
                path = Path(tmp) / f"m{k:02d}_{j}.png"
                Image.fromarray(img).save(path)
                files.append(path)
                truth.append(k)
        for attempt in range(3):  # a loaded machine may start the server slowly
            try:
                with local_service(1, Path(tmp)) as url, RegtreeClient(url) as rt:
                    cid = rt.create_collection("bench-grouping").id
                    t0 = time.perf_counter()
                    shapes = rt.upload_files(cid, files, mode="contour",
                                             target_points=TARGET_POINTS)
                    t1 = time.perf_counter()
                    job = rt.wait(rt.start_grouping(cid).id, timeout=3600)
                    t2 = time.perf_counter()
                    doc = rt.groups(job.id)
                break
            except RuntimeError as e:
                if attempt == 2 or "did not start" not in str(e):
                    raise
                print(f"  {e}: trying again")
    labels = np.array([doc.labels[str(s.id)] for s in shapes])
    ari = adjusted_rand_index(labels, np.asarray(truth))
    print(f"  {len(files)} PNGs uploaded in {t1 - t0:.1f} s; grouping job {t2 - t1:.1f} s "
          f"(queue to succeeded); {doc.n_groups} groups for {len(ms)} moulds, threshold "
          f"{doc.threshold:.4f}, ARI {ari:.3f}")
    return {"ari": ari, "seconds": t2 - t1}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--settings", default="yong,yong-recut,strokes,mpeg7,time")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--moulds", type=int, default=40)
    ap.add_argument("--impressions", type=int, default=5)
    ap.add_argument("--rules", action="store_true",
                    help="also score other cut rules on the same distances (grouping_rules.py)")
    ap.add_argument("--cache", type=Path, default=None,
                    help="keep the simulated, ingested scans in this folder and reuse them")
    args = ap.parse_args()
    for name in args.settings.split(","):
        if name not in SETTINGS and name not in ("time", "service"):
            raise SystemExit(f"unknown setting {name!r}")
        print(f"== {name}")
        if name in NEEDS_DATA and not DATA.is_dir():
            print(f"  SKIPPED: {DATA} is missing (the shared data folder sits beside the "
                  "project; see its README.md)")
            continue
        if name == "service":
            run_service(args.moulds, args.impressions, args.seed)
        else:
            run(name, args.moulds, args.impressions, args.seed, args.cache, args.rules)


if __name__ == "__main__":
    main()

"""Archive scale (issue 9): similarity and whole-job time from 250 to 2000 shapes.

The collection: noisy impressions of the 永 designs (``../shared/data/glyphs_yong/png``,
designs that render identically merged), simulated by :mod:`registration.impressions`, each
scan encoded as PNG and turned into ~400 contour points by the service's image ingestion
(``service.ingest.points_from_image``), the path a user's scans take. Impressions are made
round-robin over the designs, so every size holds every design. The generated points are
cached in ``--cache`` (default ``/tmp/regtree_archive_<seed>.npz``).

For every size: the similarity stage alone (:func:`similarity_matrix` on the pairs the tree
would use: all pairs up to ``MAX_EXHAUSTIVE_SHAPES``, else the descriptor candidates), and,
unless ``--similarity-only``, the whole dynamic-tree job (``build_dynamic_tree`` with the
default options, one local process pool): seconds, ICP pairs, seconds per shape, and the
growth exponent between consecutive sizes.

    .venv/bin/python bench/bench_archive.py [--sizes 250,500,1000,2000] [--seed 0]
        [--points 400] [--similarity-only] [--processes N]
"""

from __future__ import annotations

import argparse
import io
import math
import multiprocessing
import resource
import time
from pathlib import Path

import numpy as np
from PIL import Image

from registration import LocalProcessExecutor, build_dynamic_tree, similarity_matrix
from registration._candidates import candidate_pairs
from registration._points import normalise
from registration._tree._collection import DEFAULT_CANDIDATES, MAX_EXHAUSTIVE_SHAPES
from registration.impressions import identical_moulds, simulate_impressions

DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents[1:]
             if (p / "shared" / "data").is_dir()),
            Path(__file__).resolve().parents[1].parent / "shared" / "data")
GLYPHS = DATA / "glyphs_yong" / "png"


def _impressions(args: tuple[np.ndarray, int, int, int]) -> list[np.ndarray]:
    from service.ingest import points_from_image

    mould, n, seed, points = args
    out = []
    for img in simulate_impressions(mould, n, seed=seed):
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="PNG")
        out.append(points_from_image(buf.getvalue(), mode="contour", target_points=points))
    return out


def archive(n: int, seed: int, points: int, cache: Path) -> tuple[list[np.ndarray], np.ndarray]:
    """``n`` impressions, round-robin over the distinct 永 designs, and each one's design."""
    if cache.exists():
        z = np.load(cache, allow_pickle=False)
        if int(z["points"]) == points and len(z["truth"]) >= n:
            offsets = z["offsets"]
            flat = z["flat"]
            shapes = [flat[offsets[k]:offsets[k + 1]] for k in range(n)]
            return shapes, z["truth"][:n]
    files = sorted(GLYPHS.glob("*.png"))
    if not files:
        raise SystemExit(f"{GLYPHS} is missing: this benchmark needs the 永 glyph scans")
    masks = [np.asarray(Image.open(f).convert("L")) < 128 for f in files]
    designs = [masks[g[0]] for g in identical_moulds(masks)]
    per = math.ceil(n / len(designs))
    jobs = [(m, per, seed * 1000 + k, points) for k, m in enumerate(designs)]
    t0 = time.perf_counter()
    with multiprocessing.get_context("fork").Pool() as pool:
        made = pool.map(_impressions, jobs)
    # round-robin: impression i of every design before impression i + 1 of any
    shapes, truth = [], []
    for i in range(per):
        for k, group in enumerate(made):
            shapes.append(group[i])
            truth.append(k)
    print(f"  generated {len(shapes)} impressions of {len(designs)} designs in "
          f"{time.perf_counter() - t0:.0f} s; cached in {cache}")
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in shapes])])
    np.savez(cache, flat=np.concatenate(shapes), offsets=offsets, truth=np.asarray(truth),
             points=points)
    return shapes[:n], np.asarray(truth[:n])


def tree_pairs(normed: list[np.ndarray], root: int) -> list[tuple[int, int]]:
    """The pairs the dynamic tree computes up front (automatic similarity threshold)."""
    n = len(normed)
    if n <= MAX_EXHAUSTIVE_SHAPES:
        return [(i, j) for i in range(n) for j in range(n) if i != j]
    allowed = set(candidate_pairs(normed, DEFAULT_CANDIDATES))
    return sorted(allowed | {(root, s) for s in range(n) if s != root})


def cpu_seconds() -> float:
    """CPU time of this process and of its reaped children (the pool's processes, once
    the pool is closed): a measure that does not depend on what else loads the machine."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def slope(prev: tuple[int, float] | None, n: int, t: float) -> str:
    if prev is None:
        return "-"
    return f"{math.log(t / prev[1]) / math.log(n / prev[0]):.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="250,500,1000,2000")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--points", type=int, default=400)
    ap.add_argument("--processes", type=int, default=None)
    ap.add_argument("--similarity-only", action="store_true")
    ap.add_argument("--cache", type=Path, default=None)
    a = ap.parse_args()
    sizes = [int(s) for s in a.sizes.split(",")]
    cache = a.cache or Path(f"/tmp/regtree_archive_{a.seed}_{a.points}.npz")
    shapes_all, truth_all = archive(max(sizes), a.seed, a.points, cache)
    npts = [len(s) for s in shapes_all]
    print(f"{len(shapes_all)} impressions of {len(set(truth_all.tolist()))} 永 designs, "
          f"{np.median(npts):.0f} points median ({min(npts)}-{max(npts)}); "
          f"exact all-pairs up to {MAX_EXHAUSTIVE_SHAPES} shapes")
    print()
    print("wall: seconds on the clock; cpu: CPU seconds of this process and its pool (what the\n"
          "slopes and per-shape figures use: the machine is shared)")
    print(f"{'shapes':>6} {'ICP pairs':>9} {'desc s':>6} {'sim wall':>8} {'sim cpu':>7} "
          f"{'cpu ms/shape':>12} {'slope':>5}"
          + ("" if a.similarity_only else
             f" {'job wall':>8} {'job cpu':>7} {'cpu ms/shape':>12} {'slope':>5} "
             f"{'attached':>8} {'leaves':>6}"))
    prev_sim: tuple[int, float] | None = None
    prev_job: tuple[int, float] | None = None
    per_shape: dict[int, float] = {}
    for n in sizes:
        shapes = shapes_all[:n]
        normed = [normalise(s)[0] for s in shapes]
        c0 = cpu_seconds()
        with LocalProcessExecutor(a.processes) as ex:
            t0 = time.perf_counter()
            pairs = tree_pairs(normed, root=0)
            t_desc = time.perf_counter() - t0
            sim = similarity_matrix(shapes, pairs=pairs, executor=ex)
            t_sim = time.perf_counter() - t0
        c_sim = cpu_seconds() - c0
        row = (f"{n:>6} {sim.computed:>9} {t_desc:>6.2f} {t_sim:>8.1f} {c_sim:>7.1f} "
               f"{1000 * c_sim / n:>12.1f} {slope(prev_sim, n, c_sim):>5}")
        prev_sim = (n, c_sim)
        if not a.similarity_only:
            c0 = cpu_seconds()
            with LocalProcessExecutor(a.processes) as ex:
                t0 = time.perf_counter()
                res = build_dynamic_tree(shapes, root=0, executor=ex)
                t_job = time.perf_counter() - t0
            c_job = cpu_seconds() - c0
            subs = res.to_dict()["subjects"]
            attached = sum(1 for s in subs if s["parent"] is not None)
            leaves = sum(1 for s in res.subjects if s.leaf)
            row += (f" {t_job:>8.1f} {c_job:>7.1f} {1000 * c_job / n:>12.1f} "
                    f"{slope(prev_job, n, c_job):>5} {attached:>8} {leaves:>6}")
            prev_job = (n, c_job)
            per_shape[n] = c_job / n
        print(row, flush=True)
    if len(per_shape) >= 2:
        lo, hi = min(per_shape), max(per_shape)
        print(f"\njob CPU time per shape at {hi} vs {lo}: {per_shape[hi] / per_shape[lo]:.2f}x")


if __name__ == "__main__":
    main()

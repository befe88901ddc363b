"""All-pairs similarity (affine ICP, eq. 9) of a collection: ours vs a plain loop.

Reads the 永 glyph edge points from ../shared/data (46 fonts, each resampled to ~1000
points); says so and falls back to a generated family when the folder is missing.

    .venv/bin/python bench/bench_similarity.py [--shapes 46] [--points 1000]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from registration import (
    LocalProcessExecutor,
    SerialExecutor,
    normalise,
    resample,
    similarity_matrix,
)
from registration.synthetic import chained_family

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def load_shapes(n: int, points: int) -> tuple[list[np.ndarray], str]:
    folder = DATA / "glyphs_yong" / "points"
    files = sorted(folder.glob("*_edge.txt"))
    if not files:
        print(f"NOTE: {folder} is missing: using a generated family instead of real glyphs")
        fam = chained_family(n_chains=5, chain_length=(n - 1) // 5 + 1, n_points=points)
        return fam.shapes[:n], "generated chained family"
    shapes = [resample(np.loadtxt(f), points) for f in files[:n]]
    return shapes, f"glyphs_yong edges ({folder})"


def plain_loop(shapes: list[np.ndarray]) -> np.ndarray:
    """The plain approach: one start (centroids aligned, identity), full-resolution
    KD-tree ICP for every ordered pair."""
    normed = [normalise(s)[0] for s in shapes]
    n = len(normed)
    D = np.zeros((n, n))
    trees = [cKDTree(p) for p in normed]
    for i in range(n):
        x = normed[i]
        for j in range(n):
            if i == j:
                continue
            y = normed[j]
            A, t = np.eye(2), np.zeros(2)
            prev = np.inf
            for _ in range(100):
                tx = x @ A.T + t
                fwd, c = trees[j].query(tx)
                bwd, d = cKDTree(tx).query(y)
                dist = np.mean(fwd**2) + np.mean(bwd**2)
                if prev - dist <= 1e-6 * dist:
                    break
                prev = dist
                r = np.concatenate([x, x[d]])
                s = np.concatenate([y[c], y])
                a, b = r - r.mean(0), s - s.mean(0)
                A = (b.T @ a) @ np.linalg.inv(a.T @ a)
                t = s.mean(0) - A @ r.mean(0)
            D[i, j] = dist
    return D


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--shapes", type=int, default=46)
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--skip-plain", action="store_true")
    args = ap.parse_args()
    shapes, source = load_shapes(args.shapes, args.points)
    n = len(shapes)
    print(f"{n} shapes from {source}, {np.mean([len(s) for s in shapes]):.0f} points on "
          f"average, {n * (n - 1)} ordered pairs")
    rows = []
    t0 = time.perf_counter()
    sim1 = similarity_matrix(shapes, executor=SerialExecutor())
    rows.append(("regtree, serial", time.perf_counter() - t0, sim1.D))
    with LocalProcessExecutor() as ex:
        t0 = time.perf_counter()
        sim2 = similarity_matrix(shapes, executor=ex)
        rows.append((f"regtree, {ex.max_workers} processes (incl. start-up)",
                     time.perf_counter() - t0, sim2.D))
    if not args.skip_plain:
        t0 = time.perf_counter()
        D_plain = plain_loop(shapes)
        rows.append(("plain loop, one start, serial", time.perf_counter() - t0, D_plain))
    ref = rows[0][2]
    off = ~np.eye(n, dtype=bool)
    print(f"\n{'implementation':42s} {'seconds':>8s} {'ms/pair':>8s} {'median D':>10s}"
          f" {'pairs where D > 1.5x ours':>26s}")
    for name, sec, D in rows:
        worse = int(np.sum(D[off] > 1.5 * ref[off]))
        print(f"{name:42s} {sec:8.2f} {1e3 * sec / (n * (n - 1)):8.2f} "
              f"{np.median(D[off]):10.4g} {worse:26d}")
    plain_sec = rows[-1][1]
    if not args.skip_plain:
        print(f"\nspeed-up vs plain loop: serial {plain_sec / rows[0][1]:.1f}x, "
              f"pool {plain_sec / rows[1][1]:.1f}x")


if __name__ == "__main__":
    main()

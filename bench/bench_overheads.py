"""Benchmark: the costs around CPD's E-step, each against the way it was done before, side
by side in one process (issue 9).

Run from the project root::

    .venv/bin/python bench/bench_overheads.py [--data /work/shared/data] [--glyphs 20]

Four comparisons on the 永 edge glyphs of ``glyphs_yong`` (the first ``--glyphs`` designs):

1. **The field's kernel product** (``_cpd._field.kernel_product``: a warp, its Jacobian, CPD's
   final warp) dense against the Chebyshev grid it now takes when cheaper, at 200-1200 points
   a side, beta 1 and 2, 6 weight columns (a Jacobian's); CPU ms, and the grid's largest error
   over ``sum_j |q_j|``.
2. **Reusing the E-step's choice** (``_cpd._estep.ENGINE_REUSE_FACTOR``): the dynamic tree on
   the glyphs at 400 points, serially, with the cost estimates made every iteration (factor 1,
   as before) and reused within the factor; CPU seconds of each, best of two, and the sum of
   e over the subjects (the same tree up to rounding).
3. **BLAS threads in pool processes** (``_pool._limit_blas_threads``): the dynamic tree on the
   first 12 glyphs at their stored resolution (coarse to fine) on the default process pool,
   with each process's BLAS left to its own threads (as before) and limited to its share of
   the CPUs; wall and the pool's CPU seconds. Run on a quiet machine: the gap grows with the
   machine's other load.

4. **Block size** of the dense E-step and of the final posterior pass
   (``_cpd._field._BLOCK_ELEMS``): 1 << 22 elements (as before) against the current size,
   at 500 x N (the stored-resolution stage's control points), M x N and 2M x 2N; CPU ms.

BLAS runs on one thread in this process (as in the pool's processes).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from registration import _pool, build_dynamic_tree  # noqa: E402
from registration._cpd import _estep  # noqa: E402
from registration._cpd._field import _gauss_kernel, kernel_product  # noqa: E402
from registration._executor import SerialExecutor  # noqa: E402
from registration._points import farthest_point_indices, normalise  # noqa: E402


def cpu_ms(fn: Callable[..., Any], reps: int, *args: Any) -> float:
    fn(*args)
    t = time.process_time()
    for _ in range(reps):
        fn(*args)
    return (time.process_time() - t) / reps * 1e3


def _dense_product(z: np.ndarray, cp: np.ndarray, q: np.ndarray, beta: float) -> np.ndarray:
    out: np.ndarray = _gauss_kernel(z, cp, beta) @ q
    return out


def field_products(glyphs: list[np.ndarray]) -> None:
    print("1. field kernel product, 6 columns: CPU ms dense / grid, grid error / sum|q|")
    a, b = normalise(glyphs[0])[0], normalise(glyphs[-1])[0]
    q_all = np.random.default_rng(0).normal(size=(len(a), 6)) * 50.0
    for beta in (2.0, 1.0):
        for n in (200, 400, 800, 1200):
            cp = a[farthest_point_indices(a, min(n, len(a)))]
            z = b[farthest_point_indices(b, min(n, len(b)))]
            q = q_all[: len(cp)]
            reps = max(3, int(4e6 / (len(cp) * len(z))))
            dense = cpu_ms(_dense_product, reps, z, cp, q, beta)
            grid = cpu_ms(kernel_product, reps, z, cp, q, beta)
            err = np.max(np.abs(kernel_product(z, cp, q, beta) - _dense_product(z, cp, q, beta)))
            print(f"   beta {beta:.0f}  {len(z):5d} x {len(cp):5d}: {dense:7.2f} / {grid:7.2f} ms"
                  f"  ({dense / grid:4.1f}x)  error {err / np.abs(q).sum(axis=0).max():.1e}")


def engine_reuse(glyphs: list[np.ndarray]) -> None:
    print("2. dynamic tree at 400 points, serial: CPU s (best of 2), sum of e")
    shapes = [g[farthest_point_indices(g, 400)] for g in glyphs]
    best: dict[float, float] = {}
    kept = _estep.ENGINE_REUSE_FACTOR
    try:
        for _ in range(2):
            for factor in (1.0, kept):
                _estep.ENGINE_REUSE_FACTOR = factor
                t = time.process_time()
                r = build_dynamic_tree(shapes, root=0, executor=SerialExecutor())
                cpu = time.process_time() - t
                best[factor] = min(best.get(factor, np.inf), cpu)
                e = sum(s.error or 0.0 for s in r.subjects)
                print(f"   reuse factor {factor:4.2f}: {cpu:6.1f} s  sum e {e:.9f}", flush=True)
    finally:
        _estep.ENGINE_REUSE_FACTOR = kept
    print(f"   best: estimated every iteration {best[1.0]:.1f} s, reused {best[kept]:.1f} s "
          f"({best[kept] / best[1.0]:.2f}x)")


def pool_blas(glyphs: list[np.ndarray]) -> None:
    print("3. dynamic tree, 12 glyphs at the stored resolution, default pool: wall / pool CPU s")
    shapes = glyphs[:12]
    kept = _pool._limit_blas_threads
    try:
        for _ in range(2):
            for name, limit in (("BLAS as it comes", lambda threads: None), ("limited", kept)):
                _pool._limit_blas_threads = limit  # a forked pool process runs this one
                c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t = time.perf_counter()
                build_dynamic_tree(shapes, root=0)
                wall = time.perf_counter() - t
                c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu = c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime
                print(f"   {name:17s} {wall:6.1f} s wall  {cpu:6.1f} s CPU", flush=True)
    finally:
        _pool._limit_blas_threads = kept


def block_sizes(glyphs: list[np.ndarray]) -> None:
    """The dense E-step and the final posterior pass in blocks of 1 << 22 elements (as
    before) and of ``_field._BLOCK_ELEMS`` (now 1 << 18), on two glyphs: 500 of the first's
    points against the second, both as stored, and both doubled (each point and a copy
    1e-3 away)."""
    from registration._cpd import _field

    now = _field._BLOCK_ELEMS
    print(f"4. dense float32 E-step / posterior pass: CPU ms in blocks of {1 << 22} and "
          f"{now} elements")
    a, b = normalise(glyphs[0])[0], normalise(glyphs[1])[0]
    sizes = [(a[farthest_point_indices(a, 500)], b), (a, b)]
    big = [np.vstack([p, p + 1e-3]) for p in (a, b)]
    sizes.append((big[0], big[1]))
    try:
        for t, x in sizes:
            row = []
            for blocks in (1 << 22, now):
                _estep._BLOCK_ELEMS = _field._BLOCK_ELEMS = blocks
                es = _estep._EStep(x, len(t), 0.1, "float32")
                row.append((cpu_ms(es.dense, 5, t, 0.01),
                            cpu_ms(_estep._posterior_max_dense, 3, t, x, 0.01, 0.1)))
            print(f"   {len(t):5d} x {len(x):5d}: E-step {row[0][0]:7.1f} / {row[1][0]:7.1f} "
                  f"({row[1][0] / row[0][0]:.2f}x), posterior {row[0][1]:7.1f} / "
                  f"{row[1][1]:7.1f} ({row[1][1] / row[0][1]:.2f}x)", flush=True)
    finally:
        _estep._BLOCK_ELEMS = _field._BLOCK_ELEMS = now


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("/work/shared/data"))
    ap.add_argument("--glyphs", type=int, default=20)
    args = ap.parse_args()
    files = sorted((args.data / "glyphs_yong" / "points").glob("*_edge.txt"))
    if not files:
        raise SystemExit(f"NOTE: no glyphs under {args.data / 'glyphs_yong'}: this benchmark "
                         "needs the shared data (--data)")
    glyphs = [np.loadtxt(f) for f in files[: args.glyphs]]
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        field_products(glyphs)
        block_sizes(glyphs)
        engine_reuse(glyphs)
    pool_blas(glyphs)


if __name__ == "__main__":
    main()

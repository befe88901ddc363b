"""Benchmark: our CPD non-rigid (registration._cpd) against pycpd, rustcpd and probreg.

Run from the project root::

    .venv/bin/python bench/bench_cpd.py [--pairs 2] [--points 1000] [--repeat 3] [--quick]

Data: MPEG-7 fish contours from ``../shared/data/mpeg7/fish`` (relative to the project
root, or ``$REGTREE_DATA``), resampled by arc length to ``--points`` points.  If the folder
is missing the script says so and uses generated fish-like curves instead.  Ground truth:
the subject is a known smooth synthetic warp (a few Gaussian RBF bumps plus a mild affine
map) of the model, with its points shuffled and jittered by 0.2% of the shape's RMS
radius, so every model point has a known true image.  "gt err" is the mean distance from
warped model point i to the true image of model point i, in % of the subject's RMS radius.

Two modes: "fixed" (150 iterations, tol=0: same work everywhere) and "default" (each
implementation's own default stopping rule with our parameters beta=2, lambda=3, w=0.1).
Timings are wall-clock, best of ``--repeat`` runs (pycpd: one run), in this one process,
so every implementation sees the same machine load.  ms/iteration is total/iterations and
so includes setup (kernel, eigendecomposition, final correspondence pass).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from registration._cpd import cpd_nonrigid  # noqa: E402
from registration._cpd._mstep import _cached_factor  # noqa: E402

BETA, LMBDA, W = 2.0, 3.0, 0.1


# ----------------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------------
def resample_closed(c: np.ndarray, k: int) -> np.ndarray:
    """Resample a closed contour to k points equally spaced in arc length."""
    c = np.asarray(c, dtype=np.float64)
    cc = np.vstack([c, c[:1]])
    seg = np.linalg.norm(np.diff(cc, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], k, endpoint=False)
    return np.column_stack([np.interp(t, s, cc[:, 0]), np.interp(t, s, cc[:, 1])])


def generated_fish(k: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    body = np.column_stack([np.cos(t), 0.45 * np.sin(t) * (1 + 0.3 * np.cos(t))])
    tail = 0.35 * np.exp(-((t - np.pi) ** 2) / 0.05)[:, None] * np.array([-1.0, 0.0])
    pts = (body + tail) * (150 + 20 * rng.random()) + 250
    return resample_closed(pts, k)


def load_shapes(n_pairs: int, k: int) -> tuple[list[np.ndarray], str]:
    base = Path(os.environ.get("REGTREE_DATA", ROOT.parent / "shared" / "data"))
    folder = base / "mpeg7" / "fish"
    files = sorted(folder.glob("fish-*.npy"), key=lambda p: int(p.stem.split("-")[1]))
    if files:
        chosen = files[: n_pairs]
        return ([resample_closed(np.load(f), k) for f in chosen],
                f"MPEG-7 fish contours {[f.name for f in chosen]} from {folder}, "
                f"resampled to {k} points")
    return ([generated_fish(k, s) for s in range(n_pairs)],
            f"NOTE: {folder} not found -- using generated fish-like curves ({k} points)")


def known_warp(p: np.ndarray, ref: np.ndarray, seed: int) -> np.ndarray:
    """Smooth warp: mild affine + three Gaussian RBF bumps (in units of ref's RMS radius)."""
    rng = np.random.default_rng(seed)
    c = ref.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((ref - c) ** 2, axis=1))))
    z = (p - c) / s
    a = np.eye(2) + 0.08 * rng.standard_normal((2, 2))
    out = z @ a.T
    for _ in range(3):
        ctr = z[rng.integers(len(z))]
        amp = 0.25 * rng.standard_normal(2)
        out += amp * np.exp(-np.sum((z - ctr) ** 2, axis=1) / (2 * 0.6**2))[:, None]
    return out * s * 1.05 + c + np.array([12.0, -7.0])


def make_pair(shape: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(seed)
    model = shape
    truth = known_warp(model, model, seed)
    scale = float(np.sqrt(np.mean(np.sum((truth - truth.mean(0)) ** 2, axis=1))))
    subject = truth + 0.002 * scale * rng.standard_normal(truth.shape)
    perm = rng.permutation(len(subject))
    return model, subject[perm], truth, scale


# ----------------------------------------------------------------------------------------
# implementations: each returns (warped, iterations)
# ----------------------------------------------------------------------------------------
Runner = Callable[[np.ndarray, np.ndarray, bool], tuple[np.ndarray, int]]


def ours(**kw: Any) -> Runner:
    def run(model: np.ndarray, subject: np.ndarray, fixed: bool) -> tuple[np.ndarray, int]:
        opts: dict[str, Any] = dict(beta=BETA, lmbda=LMBDA, w=W, **kw)
        if fixed:
            opts.update(tol=0.0, max_iter=150)
        r = cpd_nonrigid(model, subject, **opts)
        return np.asarray(r.warped), r.iterations
    return run


def run_pycpd(model: np.ndarray, subject: np.ndarray, fixed: bool) -> tuple[np.ndarray, int]:
    # pycpd does not normalise: our wrapper normalises around it exactly like MATLAB.
    # Default stopping = pycpd's own rule (|sigma2 - sigma2_old| <= 1e-3, 100 iterations).
    opts: dict[str, Any] = dict(tol=0.0, max_iter=150) if fixed else dict(tol=1e-3, max_iter=100)
    r = cpd_nonrigid(model, subject, beta=BETA, lmbda=LMBDA, w=W, backend="pycpd", **opts)
    return np.asarray(r.warped), r.iterations


def rustcpd_runner(**kw: Any) -> Runner | str:
    try:
        import rustcpd
    except Exception as exc:
        return f"not available: {type(exc).__name__}: {exc}"

    def run(model: np.ndarray, subject: np.ndarray, fixed: bool) -> tuple[np.ndarray, int]:
        opts: dict[str, Any] = dict(tolerance=0.0, max_iterations=150) if fixed else {}
        r = rustcpd.register_deformable(subject, model, alpha=LMBDA, beta=BETA,
                                        normalize=True, outlier_weight=W, **kw, **opts)
        return np.asarray(r.points), int(r.iterations)
    return run


def probreg_runner() -> Runner | str:
    try:
        from probreg import cpd
    except Exception as exc:
        return f"not available: {type(exc).__name__}: {str(exc)[:70]}"

    def run(model: np.ndarray, subject: np.ndarray, fixed: bool) -> tuple[np.ndarray, int]:
        # probreg works in the caller's frame: normalise like MATLAB around it.
        xd, yd = subject.mean(0), model.mean(0)
        xs = np.sqrt(np.mean(np.sum((subject - xd) ** 2, 1)))
        ys = np.sqrt(np.mean(np.sum((model - yd) ** 2, 1)))
        # probreg's CPD is 3D: pad with z = 0.  It does not report its iteration count, so
        # the maximum (150 fixed / its default 50) is used for ms/iteration.
        src = np.column_stack([(model - yd) / ys, np.zeros(len(model))])
        tgt = np.column_stack([(subject - xd) / xs, np.zeros(len(subject))])
        reg = cpd.NonRigidCPD(src, beta=BETA, lmd=LMBDA)
        res = reg.registration(tgt, w=W, maxiter=150, tol=0.0) if fixed else \
            reg.registration(tgt, w=W)
        warped = res.transformation.transform(src)[:, :2] * xs + xd
        return warped, 150 if fixed else 50
    return run


# ----------------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="skip pycpd in fixed mode")
    ap.add_argument("--only", nargs="+", metavar="PREFIX",
                    help="run only implementations whose name starts with one of these")
    args = ap.parse_args()

    shapes, note = load_shapes(args.pairs, args.points)
    print(note)
    pairs = [make_pair(s, seed=i + 1) for i, s in enumerate(shapes)]

    impls: list[tuple[str, Runner | str, int]] = [
        ("ours (auto: low-rank + truncation)", ours(), args.repeat),
        ("ours float32 (auto)", ours(dtype="float32"), args.repeat),
        ("ours float32, gauss_grid=False", ours(dtype="float32", gauss_grid=False),
         args.repeat),
        ("ours dense f64 (no low-rank, no trunc)", ours(low_rank=False, truncate=False), 1),
        ("ours low-rank only", ours(truncate=False), args.repeat),
        ("pycpd 2.0.0", run_pycpd, 1),
        ("rustcpd (exact kernel)", rustcpd_runner(low_rank=None), args.repeat),
        ("rustcpd (default low_rank=300)", rustcpd_runner(), args.repeat),
        ("probreg", probreg_runner(), 1),
    ]

    if args.only:
        impls = [i for i in impls if i[0].startswith(tuple(args.only))]

    for mode in ("fixed", "default"):
        fixed = mode == "fixed"
        print(f"\n== mode: {mode} "
              + ("(150 iterations, tol=0)" if fixed else "(each implementation's default stop)"))
        header = (f"{'implementation':40s} {'ms/iter':>9s} {'total ms':>10s} {'iters':>7s} "
                  f"{'gt err %':>9s} {'pycpd/ours':>11s} {'t/rustcpd':>9s}")
        print(header)
        print("-" * len(header))
        rows: dict[str, tuple[float, float, float, float]] = {}
        for name, runner, rep in impls:
            if isinstance(runner, str):
                print(f"{name:40s} {runner}")
                continue
            if fixed and args.quick and name.startswith("pycpd"):
                print(f"{name:40s} skipped (--quick)")
                continue
            tot, its, errs = 0.0, 0, []
            for model, subject, truth, scale in pairs:
                best = np.inf
                for _ in range(rep):
                    _cached_factor.cache_clear()  # each run makes its kernel's factor
                    t0 = time.perf_counter()
                    warped, it = runner(model, subject, fixed)
                    best = min(best, time.perf_counter() - t0)
                tot += best
                its += it
                errs.append(float(np.mean(np.linalg.norm(warped - truth, axis=1))) / scale)
            npair = len(pairs)
            rows[name] = (tot / its * 1e3, tot / npair * 1e3, its / npair,
                          100 * float(np.mean(errs)))
        ref = rows.get("pycpd 2.0.0")
        rust = rows.get("rustcpd (default low_rank=300)")
        for name, (msit, total, mean_its, err) in rows.items():
            ratio = f"{ref[0] / msit:10.1f}x" if ref else "n/a"
            vs_rust = f"{total / rust[1]:8.3f}x" if rust else "n/a"
            print(f"{name:40s} {msit:9.2f} {total:10.1f} {mean_its:7.1f} {err:9.3f} {ratio:>11s} "
                  f"{vs_rust:>9s}")


if __name__ == "__main__":
    main()

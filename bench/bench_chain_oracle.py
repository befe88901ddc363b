"""How good can any tree be? Ground-truth error along the TRUE generation path.

The dynamic tree registers a subject by chaining CPD registrations along a path of
similar shapes. On the glyph chains of ``bench_groundtruth.py`` the best path a tree
could pick is the one the chains were generated along (root, step 1, step 2, ...): every
edge then bridges exactly one warp step. This script registers each chain along that
oracle path with the tree's own CPD options (the member's warped model registered onto
the next shape, as the tree does) and prints, per generation depth, the ground-truth
correspondence error of plain CPD (the paper's baseline), the dynamic tree (defaults)
and the oracle path, side by side.

The oracle is a floor for the tree's far-half error with this CPD: a tree cannot
choose better parents than the true ones, only different CPD edges could do better.

    .venv/bin/python bench/bench_chain_oracle.py [--designs ID,...] [--seeds 2] [--kinds edge,skel]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from registration import CPDOptions, build_dynamic_tree, cpd_nonrigid, register_direct
from registration.synthetic import correspondence_error, deformation_chains

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GLYPHS = DATA / "glyphs_yong"
METHODS = ("plain", "tree", "oracle")


def glyph_ids() -> list[str]:
    return sorted(p.name[: -len("_edge.txt")] for p in (GLYPHS / "points").glob("*_edge.txt"))


def oracle_chain(fam: object, cpd: CPDOptions) -> dict[int, np.ndarray]:
    """Warped root model on every shape, registered step by step along its chain."""
    shapes, depth, chain = fam.shapes, fam.depth, fam.chain  # type: ignore[attr-defined]
    warped: dict[int, np.ndarray] = {}
    for c in sorted({chain[k] for k in range(1, len(shapes))}):
        q = np.asarray(shapes[0], dtype=np.float64)
        steps = sorted((k for k in range(1, len(shapes)) if chain[k] == c), key=lambda k: depth[k])
        for k in steps:
            res = cpd_nonrigid(q, shapes[k], beta=cpd.beta, lmbda=cpd.lmbda, w=cpd.w,
                               max_iter=cpd.max_iter, tol=cpd.tol, dtype=cpd.dtype)
            q = np.asarray(res.warped, dtype=np.float64)
            warped[k] = q
    return warped


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--designs", default=None, help="comma-separated glyph ids (default: 3 spread)")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--kinds", default="edge,skel")
    args = ap.parse_args()
    if not (GLYPHS / "points").is_dir():
        raise SystemExit(f"NOTE: {GLYPHS} is missing: this benchmark needs ../shared/data")
    ids = glyph_ids()
    spread = np.unique(np.round(np.linspace(0, len(ids) - 1, 3)).astype(int))
    designs = args.designs.split(",") if args.designs else [ids[p] for p in spread]
    cpd = CPDOptions()
    for kind in args.kinds.split(","):
        errs: dict[str, dict[int, list[float]]] = {m: {} for m in METHODS}
        for design in designs:
            dense = np.loadtxt(GLYPHS / "points" / f"{design}_{kind}.txt")
            for seed in range(args.seeds):
                fam = deformation_chains(dense, seed=seed)
                truth = fam.root_images(0)
                warped = {
                    "plain": register_direct(fam.shapes, root=0, prealign=False),
                    "tree": build_dynamic_tree(fam.shapes, root=0),
                }
                oracle = oracle_chain(fam, cpd)
                for k in range(1, len(fam.shapes)):
                    got = {m: warped[m].subject(k).warped for m in ("plain", "tree")}
                    got["oracle"] = oracle[k]
                    for m in METHODS:
                        w = got[m]
                        if w is not None:
                            e = correspondence_error(w, truth[k], fam.shapes[k])
                            errs[m].setdefault(fam.depth[k], []).append(e)
                print(f"  done {kind} {design} seed {seed}", flush=True)
        depths = sorted(errs["plain"])
        print(f"\nyong-{kind}: mean GT error by depth "
              f"({len(designs)} designs x {args.seeds} seeds, root 0)")
        print("method  " + " ".join(f"  d={d}  " for d in depths) + " |  far (4-6) | far / plain")
        far_plain = float(np.mean([e for d in depths if d >= 4 for e in errs["plain"][d]]))
        for m in METHODS:
            far = float(np.mean([e for d in depths if d >= 4 for e in errs[m][d]]))
            print(f"{m:7s} " + " ".join(f"{np.mean(errs[m][d]):.4f} " for d in depths)
                  + f" |   {far:.4f}   |   {far / far_plain:.2f}")


if __name__ == "__main__":
    main()

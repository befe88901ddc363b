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

Two more columns ask what one CPD from the root can reach when it starts in the right
place: ``truth``, CPD with the tree's options started at the subject's true image (the
root's points where the truth puts them, ``init_warped``, sigma^2 the subject's squared
point spacing), and ``truth-fine``, the same with the polish's finish's kernel
(``FINISH_BETA_FACTOR`` of beta, ``FINISH_LMBDA_FACTOR`` times lambda). Where the first
stays far from the truth, a single field of the edges' width cannot hold the chained
deformation (CPD's fixed point near the truth is not the truth); where the second stays
near it but the tree does not, what the tree lacks is the start (its registrations sit in
a slid basin, which e does not see), not the model.

``--other`` runs the ``glyph-other`` characters of ``bench_groundtruth.py`` (rendered from
the installed Noto CJK fonts; 400 edge points a shape, seed 0) instead of the 永 designs.

    .venv/bin/python bench/bench_chain_oracle.py [--designs ID,...] [--seeds 2] [--kinds edge,skel]
    .venv/bin/python bench/bench_chain_oracle.py --other [--characters 書水心東龍]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from registration import CPDOptions, build_dynamic_tree, cpd_nonrigid, register_direct
from registration._points import mean_spacing2
from registration._tree._polish import FINISH_BETA_FACTOR, FINISH_LMBDA_FACTOR
from registration.synthetic import correspondence_error, deformation_chains

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GLYPHS = DATA / "glyphs_yong"
METHODS = ("plain", "tree", "oracle", "truth", "truth-fine")


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


def from_truth(fam: object, truth: list[np.ndarray], cpd: CPDOptions, beta_factor: float = 1.0,
               lmbda_factor: float = 1.0) -> dict[int, np.ndarray]:
    """Warped root model on every shape: one CPD from the root started at the shape's true
    image (sigma^2 its squared point spacing), kernel and regulariser scaled by the
    factors."""
    shapes = fam.shapes  # type: ignore[attr-defined]
    warped: dict[int, np.ndarray] = {}
    for k in range(1, len(shapes)):
        y = np.asarray(shapes[k], dtype=np.float64)
        res = cpd_nonrigid(shapes[0], y, beta=beta_factor * cpd.beta,
                           lmbda=lmbda_factor * cpd.lmbda, w=cpd.w, max_iter=cpd.max_iter,
                           tol=cpd.tol, dtype=cpd.dtype, init_warped=truth[k],
                           sigma2=mean_spacing2(y))
        warped[k] = np.asarray(res.warped, dtype=np.float64)
    return warped


def families(args: argparse.Namespace) -> list[tuple[str, str, object]]:
    """(set, run label, deformation chains) for every run asked for."""
    runs: list[tuple[str, str, object]] = []
    if args.other:
        import bench_groundtruth as bg  # a sibling script: its glyph rendering

        for char in args.characters:
            for font_name, font in bg.OTHER_FONTS.items():
                if not font.exists():
                    print(f"NOTE: {font} is missing: skipping {char} {font_name}")
                    continue
                dense = bg.glyph_points(char, font, "edges")
                runs.append(("glyph-other", f"{char} {font_name}",
                             deformation_chains(dense, seed=0)))
        return runs
    if not (GLYPHS / "points").is_dir():
        raise SystemExit(f"NOTE: {GLYPHS} is missing: this benchmark needs ../shared/data")
    ids = glyph_ids()
    spread = np.unique(np.round(np.linspace(0, len(ids) - 1, 3)).astype(int))
    designs = args.designs.split(",") if args.designs else [ids[p] for p in spread]
    for kind in args.kinds.split(","):
        for design in designs:
            dense = np.loadtxt(GLYPHS / "points" / f"{design}_{kind}.txt")
            for seed in range(args.seeds):
                runs.append((f"yong-{kind}", f"{design} seed {seed}",
                             deformation_chains(dense, seed=seed)))
    return runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--designs", default=None, help="comma-separated glyph ids (default: 3 spread)")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--kinds", default="edge,skel")
    ap.add_argument("--other", action="store_true",
                    help="the glyph-other characters instead of the 永 designs")
    ap.add_argument("--characters", default="書水心東龍",
                    help="with --other: the characters (default 書水心東龍)")
    args = ap.parse_args()
    cpd = CPDOptions()
    by_set: dict[str, list[tuple[str, dict[str, dict[int, list[float]]]]]] = {}
    for name, label, fam in families(args):
        truth = fam.root_images(0)  # type: ignore[attr-defined]
        shapes = fam.shapes  # type: ignore[attr-defined]
        results = {
            "plain": register_direct(shapes, root=0, prealign=False),
            "tree": build_dynamic_tree(shapes, root=0),
        }
        extra = {"oracle": oracle_chain(fam, cpd), "truth": from_truth(fam, truth, cpd),
                 "truth-fine": from_truth(fam, truth, cpd, FINISH_BETA_FACTOR,
                                          FINISH_LMBDA_FACTOR)}
        errs: dict[str, dict[int, list[float]]] = {m: {} for m in METHODS}
        for k in range(1, len(shapes)):
            got = {m: results[m].subject(k).warped for m in ("plain", "tree")}
            got.update({m: extra[m][k] for m in extra})
            for m in METHODS:
                w = got[m]
                if w is not None:
                    e = correspondence_error(w, truth[k], shapes[k])
                    errs[m].setdefault(fam.depth[k], []).append(e)  # type: ignore[attr-defined]
        by_set.setdefault(name, []).append((label, errs))
        far = {m: float(np.mean([e for d, es in errs[m].items() if d >= 4 for e in es]))
               for m in METHODS}
        print(f"  {name} {label}: far half / plain " + "  ".join(
            f"{m} {far[m] / far['plain']:.2f}" for m in METHODS[1:]), flush=True)
    for name, runs in by_set.items():
        errs = {m: {} for m in METHODS}
        for _, run in runs:
            for m in METHODS:
                for d, es in run[m].items():
                    errs[m].setdefault(d, []).extend(es)
        depths = sorted(errs["plain"])
        print(f"\n{name}: mean GT error by depth ({len(runs)} runs, root 0)")
        print("method     " + " ".join(f"  d={d}  " for d in depths)
              + " |  far (4-6) | far / plain")
        far_plain = float(np.mean([e for d in depths if d >= 4 for e in errs["plain"][d]]))
        for m in METHODS:
            far = float(np.mean([e for d in depths if d >= 4 for e in errs[m][d]]))
            print(f"{m:10s} " + " ".join(f"{np.mean(errs[m][d]):.4f} " for d in depths)
                  + f" |   {far:.4f}   |   {far / far_plain:.2f}")


if __name__ == "__main__":
    main()

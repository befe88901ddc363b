"""Variants of the tree's final polish, on the ground-truth runs of bench_groundtruth.py.

The dynamic tree is built once per run with ``polish=False`` (cached under
``bench/out/polish_cache``), plain CPD beside it; then each variant re-registers every
attached subject at layer >= 3 from where the chain left the root model, with the
acceptance checks of ``registration/_tree/_polish.py`` (no fold, e no larger than the
start's, confidence >= 0.2; a rejected stage ends the variant). With ``stages:2,1`` this
reproduced the library's polish of its first sessions offline (same GT errors as
bench_groundtruth.py then); the library's polish has grown since (``library`` below).
Printed: GT correspondence error / plain CPD's (all subjects / far half) per run, pooled
per family, and the worst run.

Variants (comma-separated, ``--variants``):

- ``none``: the tree as built;
- ``stages:B1:B2:...``: one CPD stage per kernel width (beta, absolute; the edges use 2),
  each from the previous kept stage, sigma^2 from half the start's e (>= h^2);
- ``skip:B1:B2:...``: as ``stages``, but a rejected stage is skipped, not the end;
- ``end:B1:B2:...``: the stages run on whatever their e (fold and confidence still end
  them); the last whose e is no larger than the chain's is kept;
- ``lam:L``: one stage at beta 2 with lambda L;
- ``floor:F``: one stage that stops once sigma^2 reaches F h^2;
- ``dense``: one stage whose model adds, to each point, the midpoint to its nearest
  neighbour (twice the points; only the root's points are read back);
- ``l2/VARIANT``: VARIANT from layer 2 on (the subjects registered from the root directly);
- ``chained``: layers in order, a subject's start is the edge from its parent's polished
  registration (a CPD at the default sigma^2), then one stage; else as ``stages:2``.
- ``library``: the library's polish (``registration/_tree/_polish.py``: its stages from
  layer 2, and from layer 3 the consensus), with plain CPD's registration from the cache
  standing in for the root's direct one (the library's has the pose handling);
  ``library:em``: the same with plain EM in its CPD (no ``accelerate``); ``library:d0``
  / ``library:d1``: the direct registration not polished / polished by the finer stage
  only; ``library:tolX``: the consensus kept at an e up to X times the chain's (default:
  the library's); ``library:wX``: the start moved X of the way to the direct registration
  (default 0.5). Not reproduced: the edge registered again from a polished parent
  (bench/RESULTS.md 7.7) and the finish from the root model (7.12).

    .venv/bin/python bench/bench_polish_variants.py --data /work/shared/data \\
        --families edge skel fish chinese --designs 0 --seeds 1 \\
        --variants none,stages:2,stages:2:1,stages:1:1
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_groundtruth as bg

from registration import CPDOptions, build_dynamic_tree, cpd_nonrigid, register_direct
from registration._cpd import _nonrigid
from registration._error import registration_error
from registration._points import mean_spacing2 as _spacing2
from registration._points import normalise, sampling_irregularity
from registration._quality import measure_quality
from registration._tree._rules import MIN_CONFIDENCE
from registration._tree._symmetric import RIDGE

CACHE = Path(__file__).resolve().parent / "out" / "polish_cache"
CPD = CPDOptions()
Array = np.ndarray


def _cpd(start: Array, y: Array, sigma2: float | None, beta: float = CPD.beta,
         lmbda: float = CPD.lmbda, floor: float | None = None) -> tuple[Array, Any]:
    old = _nonrigid.SIGMA2_FLOOR_REL
    if floor is not None:
        _nonrigid.SIGMA2_FLOOR_REL = floor  # relative to the normalised subject (RMS 1)
    try:
        r = cpd_nonrigid(start, y, beta=beta, lmbda=lmbda, w=CPD.w, max_iter=CPD.max_iter,
                         tol=CPD.tol, dtype=CPD.dtype, sigma2=sigma2)
    finally:
        _nonrigid.SIGMA2_FLOOR_REL = old
    return np.asarray(r.warped, dtype=np.float64), r


def _stage(start: Array, y: Array, h2: float, **kw: Any) -> tuple[Array, bool]:
    """One CPD stage from `start`, and whether it passes the polish's checks."""
    e0 = registration_error(start, y)
    out, r = _cpd(start, y, max(0.5 * e0, h2), **kw)
    e = registration_error(out, y)
    q = measure_quality(start, out, y, r.transform, e, h2)
    return out, bool(e <= e0 and q.min_jacobian > 0 and q.confidence >= MIN_CONFIDENCE)


def _polish(variant: str, start: Array, y: Array, h2: float) -> Array:
    kind, _, arg = variant.partition(":")
    if kind == "stages":
        cur = start
        for beta in (float(b) for b in arg.split(":")):
            out, ok = _stage(cur, y, h2, beta=beta)
            if not ok:
                break
            cur = out
        return cur
    if kind == "skip":  # a rejected stage is skipped: the next starts from the last kept
        cur = start
        for beta in (float(b) for b in arg.split(":")):
            out, ok = _stage(cur, y, h2, beta=beta)
            cur = out if ok else cur
        return cur
    if kind == "end":  # the stages run on regardless of e; the last one whose e is no
        # larger than the start's (and that passes the other checks) is kept
        e0, cur, best = registration_error(start, y), start, start
        for beta in (float(b) for b in arg.split(":")):
            e_cur = registration_error(cur, y)
            out, r = _cpd(cur, y, max(0.5 * e_cur, h2), beta=beta)
            e = registration_error(out, y)
            q = measure_quality(cur, out, y, r.transform, e, h2)
            if not (q.min_jacobian > 0 and q.confidence >= MIN_CONFIDENCE):
                break
            cur = out
            if e <= e0:
                best = out
        return best
    if kind == "lam":
        out, ok = _stage(start, y, h2, lmbda=float(arg))
    elif kind == "floor":
        out, ok = _stage(start, y, h2, floor=float(arg) * h2)
    elif kind == "dense":
        _, j = cKDTree(start).query(start, k=2)
        dense = np.vstack([start, 0.5 * (start + start[j[:, 1]])])
        full, _ = _cpd(dense, y, max(0.5 * registration_error(start, y), h2))
        out = full[: len(start)]
        ok = registration_error(out, y) <= registration_error(start, y)
    else:
        raise SystemExit(f"unknown variant {variant!r}")
    return out if ok else start


def _library(start: Array, y: Array, h2: float, other: Array | None, opts: list[str],
             model_irregularity: float) -> Array:
    """The library's polish of one subject (see ``library`` in the module doc)."""
    from registration._cpd import interpolating_field
    from registration._tree import _polish as pm

    real = pm.cpd_nonrigid

    def run(*a: Any, **kw: Any) -> Any:
        return real(*a, **{**kw, "accelerate": kw.get("accelerate", False)
                           and "em" not in opts})

    pm.cpd_nonrigid = run
    try:
        chain = pm._stages(start, registration_error(start, y), y, CPD, h2,
                           model_irregularity)
        if other is None:
            return chain.warped
        factors = pm.POLISH_BETA_FACTORS
        if "d0" in opts:
            polished = other
        else:
            if "d1" in opts:
                pm.POLISH_BETA_FACTORS = factors[1:]
            try:
                polished = pm._stages(other, registration_error(other, y), y, CPD, h2,
                                      model_irregularity).warped
            finally:
                pm.POLISH_BETA_FACTORS = factors
        weight = next((float(o[1:]) for o in opts if o.startswith("w")), 0.5)
        step = interpolating_field(chain.warped, chain.warped + weight * (polished - chain.warped),
                                   pm.CONSENSUS_KERNEL_FACTOR * CPD.beta, RIDGE)
        half, jac = step.apply_with_jacobian(chain.warped)
        if not float(np.linalg.det(jac).min()) > 0:
            return chain.warped
        found = pm._stages(half, registration_error(half, y), y, CPD, h2, model_irregularity)
        tol = next((float(o[3:]) for o in opts if o.startswith("tol")),
                   pm.CONSENSUS_MAX_E_RATIO)
        return (found.warped if found.steps and found.error <= tol * chain.error
                else chain.warped)
    finally:
        pm.cpd_nonrigid = real


def _built(case: bg.Case) -> dict[str, Any]:
    CACHE.mkdir(parents=True, exist_ok=True)
    key = CACHE / f"{case.label.replace(' ', '_')}_r{case.root}.pkl"
    if key.exists():
        return pickle.loads(key.read_bytes())  # type: ignore[no-any-return]
    tree = build_dynamic_tree(case.shapes, root=case.root, polish=False)
    plain = register_direct(case.shapes, root=case.root, prealign=False)
    d = {"tree": {s.index: (s.warped, s.layer, s.parent) for s in tree.subjects},
         "plain": {s.index: s.warped for s in plain.subjects}}
    key.write_bytes(pickle.dumps(d))
    return d


def run_variant(variant: str, case: bg.Case, d: dict[str, Any]) -> list[tuple[float, float, bool]]:
    """(GT error, plain CPD's GT error, far) per subject."""
    tree, plain = d["tree"], d["plain"]
    nrm = [normalise(p) for p in case.shapes]
    h2 = [_spacing2(p) for p, _ in nrm]
    root_irregularity = sampling_irregularity(nrm[case.root][0])
    out: dict[int, Array] = {}
    for k in sorted(tree, key=lambda k: tree[k][1] or 0):
        warped, layer, parent = tree[k]
        if warped is None or k == case.root:
            continue
        y, nm = nrm[k]
        start = nm.apply(warped)
        kind, min_layer = variant, 3
        if kind.startswith("library") and layer is not None and layer >= 2:
            other = nm.apply(plain[k]) if layer >= 3 else None
            out[k] = nm.invert(_library(start, y, h2[k], other, kind.split(":")[1:],
                                        root_irregularity))
            continue
        if variant.startswith("l2/"):  # the same variant from layer 2 on
            kind, min_layer = variant[3:], 2
        if kind != "none" and layer is not None and layer >= min_layer:
            if kind == "chained" and parent != case.root and parent in out:
                edge, _ = _cpd(nrm[parent][1].apply(out[parent]), y, None)
                first = edge if registration_error(edge, y) <= registration_error(start, y) \
                    else start
                start = _polish("stages:2", first, y, h2[k])
            else:
                start = _polish("stages:2" if kind == "chained" else kind, start, y, h2[k])
        out[k] = nm.invert(start)
    rows = []
    for k, w in out.items():
        g = bg.gt_error(w, case.truth[k], case.shapes[k])
        p = bg.gt_error(plain[k], case.truth[k], case.shapes[k])
        assert g is not None and p is not None
        rows.append((g, p, case.distance[k] >= case.far_from))
    return rows


def _ratio(rows: list[tuple[float, float, bool]], far: bool = False) -> float:
    sel = [r for r in rows if r[2] or not far]
    return float(np.mean([r[0] for r in sel]) / np.mean([r[1] for r in sel])) if sel else np.nan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=bg.DATA)
    ap.add_argument("--families", nargs="*", default=["edge", "skel", "fish", "chinese"],
                    help="edge skel fish chinese generated mpeg7 outline outline-random")
    ap.add_argument("--designs", default="0,72", help="glyph ids or rows of index.csv")
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--variants", default="none,stages:2,stages:2:1")
    args = ap.parse_args()
    bg.DATA, bg.GLYPHS = args.data, args.data / "glyphs_yong"
    bg.CHUI = args.data / "chui_rangarajan"
    if not args.data.is_dir():
        raise SystemExit(f"NOTE: {args.data} is missing: this benchmark needs the shared data")
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    seeds = list(range(args.seeds))
    for fam in args.families:
        if fam in ("edge", "skel"):
            cases = bg.glyph_cases(fam, bg.pick_designs(args.designs, 0), seeds, True)
        elif fam in ("fish", "chinese"):
            cases = bg.chui_cases(fam, list(range(args.trials)))
        elif fam == "generated":
            cases = bg.generated_cases(seeds)
        elif fam in ("mpeg7", "outline", "outline-random"):
            cases = bg.outline_cases(fam, seeds)
        else:
            raise SystemExit(f"unknown family {fam!r}")
        per: dict[str, list[list[tuple[float, float, bool]]]] = {v: [] for v in variants}
        for case in cases:
            d = _built(case)
            line = []
            for v in variants:
                t0 = time.perf_counter()
                rows = run_variant(v, case, d)
                per[v].append(rows)
                line.append(f"{v} {_ratio(rows):.3f}/{_ratio(rows, True):.3f} "
                            f"({time.perf_counter() - t0:.0f}s)")
            print(f"{case.label} r{case.root}: " + "  ".join(line), flush=True)
        print(f"== {fam}: variant / plain CPD, pooled all, far, worst run (all)")
        for v in variants:
            rows = [r for run in per[v] for r in run]
            worst = max(_ratio(run) for run in per[v])
            print(f"   {v:16s} {_ratio(rows):.3f} {_ratio(rows, True):.3f} {worst:.3f}",
                  flush=True)


if __name__ == "__main__":
    main()

"""Which GT-free score ranks the registrations of one subject as their ground truth does?

The tree's final polish (``registration/_tree/_polish.py``) makes several registrations
of each subject (the chain's, its stages, the edge registered again from the polished
parent, the root's direct registration, the steps halfway) and chooses among them. Near
the subject's sampling floor e (eq. 10) stops ranking them: this benchmark measures how
well each candidate score does instead, on the ground-truth families of
``bench_groundtruth.py`` (their default roots, first seeds).

For every case the dynamic tree is built with its defaults (serially), every
registration its polish computes is recorded (in the subject's normalised coordinates),
and for each subject the distinct ones (RMS apart by 1e-4 or more) are compared:

- "pairwise": over the pairs of a subject's registrations whose GT errors differ by 10 %
  or more, the fraction the score orders as GT does (0.5: no better than a coin);
- "pick": the mean GT error of the registration with the least score, per subject;
- beside them: the oracle (least GT error) and the tree's own final registration.

Scores: ``e``; its halves ``e_ms`` (model to subject) and ``e_sm``; ``V``, the spacing
distortion of the whole map from the root model
(:func:`registration._quality.spacing_distortion`); the penalised e ``e(1+kV)`` for
several k (bench/RESULTS.md 7.8: weight 10 in the polish's stages, measured and
reverted). Also printed: e of the true correspondences in units of the subject's h^2,
and how often the final e lies below it (the registration fitting the subject's own
samples closer than the truth does).

    .venv/bin/python bench/bench_polish_scores.py [--families yong-edge yong-skel mpeg7 ...]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_groundtruth as bg

import registration._tree._polish as polish
from registration import build_dynamic_tree, normalise, registration_error
from registration._executor import SerialExecutor
from registration._points import mean_spacing2
from registration._quality import nearest_spacing, spacing_distortion

WEIGHTS = (3.0, 10.0, 30.0, 100.0)
FAMILIES = ("yong-edge", "yong-skel", "mpeg7", "outline", "outline-random", "glyph-other",
            "chui")


def cases(family: str) -> list[bg.Case]:
    if family in ("yong-edge", "yong-skel"):
        kind = family.split("-")[1]
        designs = bg.pick_designs(None, 3)
        return [c for d in designs for c in bg.glyph_cases(kind, [d], [0, 1], mid_root=False)]
    if family in ("mpeg7", "outline", "outline-random"):
        return bg.outline_cases(family, [0])
    if family == "glyph-other":
        return bg.other_glyph_cases([0])
    if family == "chui":
        return bg.chui_cases("fish", [0, 1, 2]) + bg.chui_cases("chinese", [0, 1, 2])
    raise SystemExit(f"unknown family {family!r}")


class Recorder:
    """Wraps the polish's functions to record every registration of each subject."""

    def __init__(self) -> None:
        self.found: dict[int, list[np.ndarray]] = {}
        self.subject = -1
        real_task, real_stages = polish._polish_task, polish._stages

        def task(t: Any) -> Any:
            self.subject = t.subject
            self.found.setdefault(t.subject, []).append(np.array(t.start))
            return real_task(t)

        def stages(*a: Any, **k: Any) -> Any:
            out = real_stages(*a, **k)
            self.found.setdefault(self.subject, []).append(np.array(out.warped))
            return out

        polish._polish_task, polish._stages = task, stages  # type: ignore[assignment]


def scores(w: np.ndarray, y: np.ndarray, root_spacing: np.ndarray) -> dict[str, float]:
    from scipy.spatial import cKDTree

    d_ms, _ = cKDTree(y).query(w)
    d_sm, _ = cKDTree(w).query(y)
    e = registration_error(w, y)
    v = spacing_distortion(w, root_spacing)
    out = {"e": e, "e_ms": float(np.mean(d_ms**2)), "e_sm": float(np.mean(d_sm**2)), "V": v}
    for k in WEIGHTS:
        out[f"e(1+{k:g}V)"] = e * (1.0 + k * v)
    return out


def run_family(family: str, rec: Recorder) -> dict[str, Any]:
    hits: dict[str, int] = {}
    picks: dict[str, list[float]] = {}
    n_pairs, oracle, final, e_true, below = 0, [], [], [], []
    for case in cases(family):
        rec.found.clear()
        tree = build_dynamic_tree(case.shapes, root=case.root, executor=SerialExecutor())
        root_spacing = nearest_spacing(normalise(case.shapes[case.root])[0])
        for k, regs in rec.found.items():
            y, norm = normalise(case.shapes[k])
            truth = norm.apply(case.truth[k])
            has = np.isfinite(truth).all(axis=1)
            fin = norm.apply(tree.subject(k).warped)
            distinct: list[np.ndarray] = []
            for w in [*regs, fin]:
                if all(np.sqrt(((w - c) ** 2).sum(1).mean()) >= 1e-4 for c in distinct):
                    distinct.append(w)
            gts = [float(np.sqrt(((w[has] - truth[has]) ** 2).sum(1).mean())) for w in distinct]
            oracle.append(min(gts))
            final.append(float(np.sqrt(((fin[has] - truth[has]) ** 2).sum(1).mean())))
            if has.all():
                h2 = mean_spacing2(y)
                e_true.append(registration_error(truth, y) / h2)
                below.append(registration_error(fin, y) / h2 < e_true[-1])
            sc = [scores(w, y, root_spacing) for w in distinct]
            for name in sc[0]:
                picks.setdefault(name, []).append(gts[int(np.argmin([s[name] for s in sc]))])
            for a, b in itertools.combinations(range(len(distinct)), 2):
                if abs(gts[a] - gts[b]) < 0.1 * min(gts[a], gts[b]):
                    continue
                n_pairs += 1
                for name in sc[0]:
                    hits[name] = hits.get(name, 0) + int(
                        (sc[a][name] < sc[b][name]) == (gts[a] < gts[b]))
        print(f"  {case.label}: {len(rec.found)} subjects", flush=True)
    return {"pairs": n_pairs, "hits": hits, "picks": picks, "oracle": oracle, "final": final,
            "e_true": e_true, "below": below}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    args = ap.parse_args()
    if not bg.DATA.is_dir():
        raise SystemExit(f"NOTE: {bg.DATA} is missing: this benchmark needs ../shared/data")
    rec = Recorder()
    for family in args.families:
        print(f"\n{family}")
        r = run_family(family, rec)
        if not r["final"]:
            print("  no subject polished")
            continue
        et = np.array(r["e_true"])
        print(f"  subjects {len(r['final'])}, pairs {r['pairs']}; GT error: tree final "
              f"{np.mean(r['final']):.4f}, oracle among its registrations "
              f"{np.mean(r['oracle']):.4f}")
        if len(et):
            print(f"  e of the true correspondences / h^2: median {np.median(et):.2f} "
                  f"(10-90 %: {np.quantile(et, 0.1):.2f}-{np.quantile(et, 0.9):.2f}); "
                  f"final e below it: {np.mean(r['below']):.0%}")
        print(f"  {'score':12s} {'pairwise':>8s} {'pick':>8s}")
        for name in sorted(r["hits"], key=lambda n: -r["hits"][n]):
            print(f"  {name:12s} {r['hits'][name] / max(r['pairs'], 1):8.3f} "
                  f"{np.mean(r['picks'][name]):8.4f}")


if __name__ == "__main__":
    main()

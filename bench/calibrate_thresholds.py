"""Calibrate what decides a registration's fate on data with ground-truth correspondences.

Two things come from here:

1. The automatic thresholds of `build_dynamic_tree` (how CPD's success depends on D of
   eq. 9; how e of eq. 10 separates good from bad registrations): the first tables.
2. The confidence model of `registration._quality`: a logistic fit of P(good | checks),
   "good" meaning an RMS ground-truth correspondence error below ``GOOD_ERROR`` (0.15) of
   the subject's RMS radius. Its coefficients are printed at the end, ready to paste into
   `_quality.py`, with the held-out quality of the fit (leave one data set out).

Registrations measured, each as the tree runs them (`registration._tree`): from every
start the pose option offers (the pose as given: CPD on the normalised shapes as they
are; the similarity's rotated pose when affine ICP finds one; the turn rigid ICP finds,
when `_rigid_start` offers it; a mirrored pose under ``pose="affine"``), each registered
twice: one-way with CPD's one start, as direct CPD and the static tree register
("direct"), and as the dynamic tree's edges are (CPD also from the held start, the
registration made symmetric: "edge"). On

- chained smooth deformations of real glyphs (the 永 designs of ../shared/data, edges and
  skeletons; `registration.synthetic.deformation_chains`), root and mid-chain models;
- the same with the subject turned by 90 degrees (a pose the pose as given cannot reach:
  what a wrong pose looks like after CPD);
- with the Noto CJK fonts installed, the characters 書水心東龍 rendered and chained as
  bench_groundtruth.py's glyph-other family (two fonts, edges) at a seed that bench does
  not run, upright and with the subject turned by an angle drawn from +-180 degrees (as
  its glyph-turned family);
- the Chui & Rangarajan fish and Chinese-character deformation series;
- generated chained families (always, also without ../shared).

The model in ``registration/_quality.py`` is scored on the same registrations beside
the refit, so the two can be compared before its coefficients are replaced.

    .venv/bin/python bench/calibrate_thresholds.py [--quick]
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from ranking import auc
from scipy.optimize import minimize

from registration import CPDOptions, LocalProcessExecutor, normalise
from registration._icp import pairwise_affine_icp, prepare_shape
from registration._points import mean_spacing2 as _spacing2
from registration._pose import PoseSpec
from registration._quality import _FEATURES, _INTERCEPT, _MEAN, _SCALE, _WEIGHTS, GOOD_ERROR
from registration._tree._tasks import (
    HELD_START_MIN_POINTS,
    SYMMETRIC_LINK_MIN_POINTS,
    _register_from,
    _RegTask,
    _rigid_start,
    _Start,
)
from registration.synthetic import chained_family, deformation_chains

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GLYPHS = DATA / "glyphs_yong"

Pair = tuple[str, np.ndarray, np.ndarray, np.ndarray]  # set, model, subject, truth


def pairs_chui(kind: str, trials: int) -> Iterator[Pair]:
    for lvl in range(1, 6):
        f = DATA / "chui_rangarajan" / f"{kind}_def_{lvl}.npz"
        if not f.exists():
            return
        d = np.load(f)
        gt = d["gt_index_into_X"]  # Y row i is the image of X row gt[i]
        for t in range(trials):
            truth = np.empty_like(d["X"][t])
            truth[gt] = d["Y_clean"][t]
            yield f"chui-{kind}", d["X"][t], d["Y"][t], truth


def pairs_generated(seeds: int) -> Iterator[Pair]:
    for seed in range(seeds):
        fam = chained_family(n_chains=2, chain_length=6, n_points=200, step=0.35, seed=seed)
        for k in range(1, len(fam.shapes)):
            yield "generated", fam.shapes[0], fam.shapes[k], fam.root_images[k]


def _rotate(p: np.ndarray, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    c = p.mean(axis=0)
    return (p - c) @ R.T + c


def pairs_glyphs(kind: str, designs: int, seeds: int, turned: bool) -> Iterator[Pair]:
    if not GLYPHS.exists():
        return
    ids = sorted(p.name[: -len(f"_{kind}.txt")] for p in (GLYPHS / "points").glob(f"*_{kind}.txt"))
    # designs spread over the list, away from the ones bench_groundtruth uses first
    picks = [ids[(7 + 23 * k) % len(ids)] for k in range(designs)]
    for did, seed in itertools.product(picks, range(seeds)):
        fam = deformation_chains(np.loadtxt(GLYPHS / "points" / f"{did}_{kind}.txt"), seed=seed)
        # models: the undeformed shape and a mid-chain one
        for root in (0, 3):
            truths = fam.root_images(root)
            for k in range(len(fam.shapes)):
                if k == root or (turned and k % 3):
                    continue
                y, tr = fam.shapes[k], truths[k]
                label = f"glyph-{kind}"
                if turned:
                    y, tr = _rotate(y, 90.0), _rotate(tr, 90.0)
                    label += "-turned"
                yield label, fam.shapes[root], y, tr


def pairs_rendered(turned: bool) -> Iterator[Pair]:
    """bench_groundtruth.py's glyph-other characters (書水心東龍, two Noto CJK fonts,
    edges) chained at seed 2, which that bench does not run (it runs seeds 0 and 1), root
    and mid-chain models; `turned`: every third subject turned by an angle drawn from
    +-180 degrees (as its glyph-turned family). Nothing without the fonts."""
    import bench_groundtruth as bg

    rng = np.random.default_rng(7)
    for char, font in itertools.product(bg.OTHER_CHARACTERS, bg.OTHER_FONTS.values()):
        if not font.exists() or not bg.has_glyph(char, font):
            continue
        fam = deformation_chains(bg.glyph_points(char, font), seed=2)
        for root in (0, 3):
            truths = fam.root_images(root)
            for k in range(len(fam.shapes)):
                if k == root or (turned and k % 3):
                    continue
                y, tr, label = fam.shapes[k], truths[k], "glyph-other"
                if turned:
                    deg = float(rng.uniform(-180.0, 180.0))
                    y, tr, label = _rotate(y, deg), _rotate(tr, deg), label + "-turned"
                yield label, fam.shapes[root], y, tr


def measure(item: Pair) -> list[tuple[object, ...]]:
    """Every registration the tree could make of this pair: (set, start, variant, D, e,
    h^2, GT error, min Jacobian, D ratio, features...). The variants: "direct" (one way,
    CPD's one start) and, where the shapes are large enough for either, "edge" (the
    dynamic tree's: the held start beside, made symmetric)."""
    name, x, y, truth = item
    xn, _ = normalise(x)
    yn, ny = normalise(y)
    h2 = _spacing2(yn)
    truth_n = ny.apply(truth)
    variants = [("direct", False)]
    if min(len(xn), len(yn)) >= min(HELD_START_MIN_POINTS, SYMMETRIC_LINK_MIN_POINTS):
        variants.append(("edge", True))
    rows = []
    for mode in ("rotation", "affine"):
        spec = PoseSpec.resolve(mode, None)
        (r,) = pairwise_affine_icp({0: prepare_shape(xn), 1: prepare_shape(yn)}, [(0, 1)],
                                   pose=spec, tol=1e-3)
        # every pose the option offers, also those `_starts` would not register
        starts = [_Start("as given")] if mode == "rotation" else []
        if not np.allclose(r.A, r.A_given):
            starts.append(_Start("rotated", r.A, r.t))
        if mode == "affine" and np.linalg.det(r.A) > 0:
            continue  # only the mirrored poses are new under "affine"
        labels = [st.label for st in starts]
        if mode == "rotation":
            turn = _rigid_start(xn, yn, starts)
            if turn is not None:
                starts.append(turn)
                labels.append("rigid")
        for (variant, edge), (st, label) in itertools.product(
                variants, zip(starts, labels, strict=True)):
            task = _RegTask(subject=1, member=0, layer=2, similarity=r.D, q=xn, y=yn,
                            starts=(), cpd=CPDOptions(), prealign=True, pose=spec,
                            spacing2=h2, symmetric=edge, held=edge)
            out = _register_from(task, st)
            diff = out.warped - truth_n
            ce = float(np.sqrt((diff**2).sum(axis=1).mean()))
            rows.append((name, f"{mode}:{label}", variant, r.D, out.error, h2, ce,
                         out.min_jacobian, r.D / max(r.D_given, 1e-300),
                         *out.quality.features()))
    return rows


def _logistic_fit(X: np.ndarray, y: np.ndarray, l2: float = 1e-2) -> np.ndarray:
    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        z = w[0] + X @ w[1:]
        p = 1.0 / (1.0 + np.exp(-np.clip(z, -50, 50)))
        eps = 1e-12
        f = -np.mean(y * np.log(p + eps) + (1 - y) * np.log(1 - p + eps)) + l2 * np.sum(w[1:] ** 2)
        g = np.concatenate([[np.mean(p - y)], X.T @ (p - y) / len(y) + 2 * l2 * w[1:]])
        return float(f), g

    res = minimize(loss, np.zeros(X.shape[1] + 1), jac=True, method="L-BFGS-B")
    return np.asarray(res.x)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer pairs (a smoke run)")
    args = ap.parse_args()
    q = args.quick
    items: list[Pair] = []
    items += list(pairs_chui("fish", 3 if q else 8)) + list(pairs_chui("chinese", 3 if q else 8))
    for kind in ("edge", "skel"):
        items += list(pairs_glyphs(kind, 1 if q else 3, 1, turned=False))
        items += list(pairs_glyphs(kind, 1 if q else 2, 1, turned=True))
    if not GLYPHS.exists():
        print(f"NOTE: {DATA} is missing: generated pairs only")
    rendered = [*pairs_rendered(turned=False), *pairs_rendered(turned=True)]
    if not rendered:
        print("NOTE: the Noto CJK fonts are missing: no rendered glyphs")
    items += rendered[::4] if q else rendered
    items += list(pairs_generated(2 if q else 6))
    with LocalProcessExecutor() as ex:
        rows = [r for _, rr in ex.map_unordered(measure, items) for r in rr]
    sets = np.array([r[0] for r in rows])
    starts = np.array([r[1] for r in rows])
    variants = np.array([r[2] for r in rows])
    num = np.array([r[3:] for r in rows], dtype=np.float64)
    D, e, h2, ce, minjac = num[:, 0], num[:, 1], num[:, 2], num[:, 3], num[:, 4]
    d_ratio = num[:, 5]
    feats = num[:, 6:]
    good = (ce < GOOD_ERROR).astype(float)
    print(f"{len(items)} pairs, {len(rows)} registrations; good = RMS correspondence error "
          f"< {GOOD_ERROR} of the subject's RMS radius\n")

    print("Per set, start and variant: registrations, good %, median correspondence error,"
          " median e/h^2, and D of the best pose over D of the pose as given (range, median)")
    for s_name in sorted(set(sets)):
        for st, var in sorted(set(zip(starts[sets == s_name], variants[sets == s_name],
                                      strict=True))):
            m = (sets == s_name) & (starts == st) & (variants == var)
            dr = d_ratio[m]
            print(f"  {s_name:20s} {st:18s} {var:6s} n={m.sum():4d}"
                  f" good={100 * good[m].mean():5.1f}%"
                  f" ce={np.median(ce[m]):.3f} e/h2={np.median(e[m] / h2[m]):.2f}"
                  f" D/D_given {dr.min():.2f}-{dr.max():.2f} ({np.median(dr):.2f})")

    print("\nCPD success by affine-ICP distance D (pose as given and plain excluded):")
    # CPD from the pose as given (no affine step), one way
    sel = (starts == "rotation:as given") & (variants == "direct")
    for lo, hi in itertools.pairwise([0, 0.002, 0.005, 0.01, 0.02, 0.04, 0.08, np.inf]):
        m = sel & (D >= lo) & (D < hi)
        if m.any():
            print(f"  D in [{lo:g}, {hi:g}): {m.sum():5d} pairs, good {100 * good[m].mean():5.1f}%,"
                  f" median corr. err. {np.median(ce[m]):.4f}")

    print("\nHow well each check alone separates good from bad (AUC; 0.5 = no better than chance):")
    usable = minjac > 0
    for k, f in enumerate(_FEATURES):
        sign = -1.0 if f in ("log_error_ratio", "distortion", "anisotropy", "cpd_rotation") else 1
        print(f"  {f:16s} AUC {auc(sign * feats[usable, k], good[usable]):.3f}")

    # the confidence model: standardised features, logistic fit; held out by data set
    Xs = feats[usable]
    ys = good[usable]
    groups = sets[usable]
    mean, scale = Xs.mean(axis=0), Xs.std(axis=0) + 1e-12
    Z = (Xs - mean) / scale
    def logistic(w: np.ndarray, Zs: np.ndarray) -> np.ndarray:
        return np.asarray(1.0 / (1.0 + np.exp(-np.clip(w[0] + Zs @ w[1:], -50, 50))))

    # the model as it is in registration/_quality.py, on these registrations
    now = np.array([_INTERCEPT, *_WEIGHTS])
    p_now = logistic(now, (Xs - np.asarray(_MEAN)) / np.asarray(_SCALE))
    print("\nConfidence model, leave one data set out (fit on the others, scored on it), beside"
          " the model in _quality.py:")
    for g in sorted(set(groups)):
        tr, te = groups != g, groups == g
        p = logistic(_logistic_fit(Z[tr], ys[tr]), Z[te])
        took = p >= 0.5
        acc = 100 * ys[te][took].mean() if took.any() else float("nan")
        rej = 100 * ys[te][~took].mean() if (~took).any() else float("nan")
        print(f"  {g:22s} n={te.sum():4d} AUC {auc(p, ys[te]):.3f}"
              f" (now {auc(p_now[te], ys[te]):.3f})  accepted (p>=0.5) good {acc:5.1f}% of"
              f" {took.sum()}, rejected good {rej:5.1f}% of {(~took).sum()}")
    w = _logistic_fit(Z, ys)
    p = logistic(w, Z)
    print(f"\nall sets: AUC {auc(p, ys):.3f} (now {auc(p_now, ys):.3f})")
    for lo, hi_ in itertools.pairwise([0, 0.2, 0.5, 0.8, 0.95, 1.0001]):
        m, m_now = (p >= lo) & (p < hi_), (p_now >= lo) & (p_now < hi_)
        print(f"  confidence [{lo:.2f}, {hi_:.2f}): refit {m.sum():5d} registrations, good"
              f" {100 * ys[m].mean() if m.any() else float('nan'):5.1f}%;"
              f" now {m_now.sum():5d}, good"
              f" {100 * ys[m_now].mean() if m_now.any() else float('nan'):5.1f}%")
    print("\nPaste into registration/_quality.py:")
    print(f"_INTERCEPT = {w[0]:.4f}")
    print(f"_WEIGHTS = ({', '.join(f'{v:.4f}' for v in w[1:])})")
    print(f"_MEAN = ({', '.join(f'{v:.4f}' for v in mean)})")
    print(f"_SCALE = ({', '.join(f'{v:.4f}' for v in scale)})")


if __name__ == "__main__":
    main()

"""Measure how CPD's success depends on D (eq. 9) and how e (eq. 10) separates good from
bad registrations, on data with ground-truth correspondences. This is the evidence behind
the automatic thresholds of `build_dynamic_tree`.

Pairs: the Chui & Rangarajan fish and Chinese-character deformation series (model to
targets of deformation levels 1-5), when ../shared/data is present, and pairs at growing
chain distance in generated chained families (always). For every pair: affine-ICP D, CPD
(after the affine pre-alignment, as the tree does it), e, the subject's point spacing h
(RMS nearest-neighbour distance within the subject, normalised), the minimum Jacobian
determinant, and the RMS ground-truth correspondence error (relative to RMS radius).

    .venv/bin/python bench/calibrate_thresholds.py
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from registration import LocalProcessExecutor, normalise
from registration._icp import affine_icp
from registration._tree import CPDOptions, _register_task, _RegTask
from registration.synthetic import chained_family

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GOOD = 0.05  # a registration is "good" when its RMS correspondence error < 5% of radius


def spacing2(p: np.ndarray) -> float:
    d, _ = cKDTree(p).query(p, k=2)
    return float(np.mean(d[:, 1] ** 2))


def pairs_chui(kind: str, trials: int):
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


def pairs_generated(seeds: int, resample: bool):
    label = "generated-resampled" if resample else "generated-same-sampling"
    for seed in range(seeds):
        fam = chained_family(n_chains=2, chain_length=6, n_points=200, step=0.35, seed=seed,
                             resample=resample)
        for k in range(1, len(fam.shapes)):
            yield label, fam.shapes[0], fam.shapes[k], fam.root_images[k]


def measure(item):
    name, x, y, truth = item
    xn, _ = normalise(x)
    yn, ny = normalise(y)
    icp = affine_icp(xn, yn)
    out = _register_task(_RegTask(subject=1, member=0, layer=2, similarity=icp.distance,
                                  q=xn, y=yn, A0=icp.A, t0=icp.t, cpd=CPDOptions(),
                                  prealign=True))
    diff = out.warped - ny.apply(truth)
    ce = float(np.sqrt((diff**2).sum(axis=1).mean()))
    return name, icp.distance, out.error, spacing2(yn), out.min_jacobian, ce


def main() -> None:
    items = list(pairs_chui("fish", 20)) + list(pairs_chui("chinese", 20))
    if not items:
        print(f"NOTE: {DATA / 'chui_rangarajan'} is missing: generated pairs only")
    items += list(pairs_generated(6, True)) + list(pairs_generated(6, False))
    with LocalProcessExecutor() as ex:
        rows = [r for _, r in ex.map_unordered(measure, items)]
    names = sorted({r[0] for r in rows})
    arr = {n: np.array([r[1:] for r in rows if r[0] == n]) for n in names}
    allr = np.array([r[1:] for r in rows])
    print(f"{len(rows)} pairs; 'good' = RMS correspondence error < {GOOD}\n")
    print("CPD success by affine-ICP distance D (all sets):")
    print(f"{'D bin':>20s} {'pairs':>6s} {'good %':>7s} {'median corr.err':>16s}")
    edges = [0, 0.002, 0.005, 0.01, 0.02, 0.04, 0.08, np.inf]
    for lo, hi in itertools.pairwise(edges):
        m = (allr[:, 0] >= lo) & (allr[:, 0] < hi)
        if m.any():
            print(f"{f'[{lo:g}, {hi:g})':>20s} {m.sum():6d} {100 * np.mean(allr[m, 4] < GOOD):7.1f}"
                  f" {np.median(allr[m, 4]):16.4f}")
    print("\nSeparation of good and bad registrations by e / h^2 (h: subject's point spacing):")
    print(f"{'e/h^2 bin':>20s} {'pairs':>6s} {'good %':>7s} {'folded %':>9s}")
    ratio = allr[:, 1] / allr[:, 2]
    edges = [0, 0.5, 1, 2, 4, 8, 16, 32, np.inf]
    for lo, hi in itertools.pairwise(edges):
        m = (ratio >= lo) & (ratio < hi)
        if m.any():
            print(f"{f'[{lo:g}, {hi:g})':>20s} {m.sum():6d} {100 * np.mean(allr[m, 4] < GOOD):7.1f}"
                  f" {100 * np.mean(allr[m, 3] <= 0):9.1f}")
    print("\nPer set: median D, e, h^2 and share good")
    for n in names:
        a = arr[n]
        print(f"{n:16s} pairs={len(a):4d} D={np.median(a[:, 0]):.4g} e={np.median(a[:, 1]):.4g}"
              f" h2={np.median(a[:, 2]):.4g} good={100 * np.mean(a[:, 4] < GOOD):.0f}%")


if __name__ == "__main__":
    main()

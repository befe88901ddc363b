"""Single links: the root registered onto subjects one or two generation steps away, by CPD
alone and by CPD followed by a second CPD (the polish's finish, bench/RESULTS.md 7.12).

The families and their ground truth are those of ``bench_groundtruth.py`` (root 0, the
first seed of each; the 永 designs both seeds). Each scheme is a chain of CPD runs
separated by ``>``: ``BETA:LAMBDA`` runs CPD from the root model (the first from the
root's own pose, a later one started where the previous left the points,
``cpd_nonrigid(init_warped=...)``: its field still root -> subject), ``BETA:LAMBDA:s``
runs it from the previous one's points instead (its field penalised from there, as the
polish's stages are). Later runs start at sigma^2 = max(e / 2, h^2) and are accelerated.
Printed per family: the mean ground-truth error of each scheme, its ratio to the first
scheme's, the geometric mean of the per-subject ratios and the share of subjects made
more than 10 % worse.

    .venv/bin/python bench/bench_single_link.py --families edge skel mpeg7 \\
        --schemes 2:3 "2:3>1:6" "2:3>1:3:s"
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_groundtruth as bg

from registration import cpd_nonrigid
from registration._error import registration_error
from registration._points import mean_spacing2, normalise

FAMILIES = ("edge", "skel", "mpeg7", "outline", "outline-random", "outline-arc", "glyph-other",
            "generated", "fish", "chinese")


def run_scheme(scheme: str, model: np.ndarray, subject: np.ndarray) -> np.ndarray:
    """The model's points on the subject after the scheme's CPD runs (normalised coords)."""
    warped: np.ndarray | None = None
    for part in scheme.split(">"):
        beta, lmbda, *flag = part.split(":")
        if warped is None:
            res = cpd_nonrigid(model, subject, beta=float(beta), lmbda=float(lmbda))
        else:
            s2 = max(0.5 * registration_error(warped, subject), mean_spacing2(subject))
            if flag == ["s"]:
                res = cpd_nonrigid(warped, subject, beta=float(beta), lmbda=float(lmbda),
                                   sigma2=s2, accelerate=True)
            else:
                res = cpd_nonrigid(model, subject, beta=float(beta), lmbda=float(lmbda),
                                   sigma2=s2, init_warped=warped, accelerate=True)
        warped = np.asarray(res.warped, dtype=np.float64)
    assert warped is not None
    return warped


def cases_of(family: str, sources: dict) -> list[bg.Case]:
    if family in ("edge", "skel"):
        if not (bg.GLYPHS / "index.csv").exists():
            return []
        return bg.glyph_cases(family, bg.pick_designs(None, 3), [0, 1], False)
    if family in ("mpeg7", *bg.OUTLINE_SAMPLINGS):
        return bg.outline_cases(family, [0], sources)
    if family == "glyph-other":
        return bg.other_glyph_cases([0])
    if family == "generated":
        return bg.generated_cases([0, 1])
    if all((bg.CHUI / f"{family}_def_{lvl}.npz").exists() for lvl in range(1, 6)):
        return bg.chui_cases(family, [0, 1, 2])
    return []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--families", nargs="*", default=list(FAMILIES), choices=FAMILIES)
    ap.add_argument("--schemes", nargs="+", default=["2:3", "2:3>1:6", "2:3>1:3",
                                                     "2:3>1.5:6", "2:3>1:3:s"])
    ap.add_argument("--max-distance", type=int, default=2,
                    help="subjects at most this many generation steps from the root")
    args = ap.parse_args()
    if not bg.DATA.is_dir():
        print(f"NOTE: {bg.DATA} is missing: only the generated family runs")
    sources = bg.outline_sources() if bg.DATA.is_dir() else {}
    base = args.schemes[0]
    for family in args.families:
        cases = cases_of(family, sources)
        if not cases:
            print(f"{family:14s} (no data)")
            continue
        errors: dict[str, list[float]] = {s: [] for s in args.schemes}
        for case in cases:
            model, _ = normalise(case.shapes[case.root])
            for k, shape in enumerate(case.shapes):
                if k == case.root or case.distance[k] > args.max_distance:
                    continue
                subject, norm = normalise(shape)
                for scheme in args.schemes:
                    warped = norm.invert(run_scheme(scheme, model, subject))
                    gt = bg.gt_error(warped, case.truth[k], shape)
                    assert gt is not None
                    errors[scheme].append(gt)
        ref = np.array(errors[base])
        for scheme in args.schemes:
            v = np.array(errors[scheme])
            r = v / np.maximum(ref, 1e-12)
            print(f"{family:14s} {scheme:16s} {v.mean():.4f}  x{v.mean() / ref.mean():.3f}  "
                  f"geometric x{np.exp(np.log(np.maximum(r, 1e-12)).mean()):.3f}  "
                  f"worse by >10 %: {np.mean(r > 1.1):.2f}  (n={len(v)})", flush=True)


if __name__ == "__main__":
    main()

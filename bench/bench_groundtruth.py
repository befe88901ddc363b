"""Ground-truth correspondence error of plain CPD, direct CPD and the dynamic tree, defaults only.

Each method is called with its DEFAULT options (the point of this benchmark is to judge
the defaults); only the root changes:

- plain CPD: ``register_direct(shapes, root=r, prealign=False)``, the paper's baseline;
  every ratio is taken against it;
- direct CPD: ``register_direct(shapes, root=r)``;
- dynamic tree: ``build_dynamic_tree(shapes, root=r)``.

The error of a subject k is the RMS distance between ``res.subject(k).warped`` (the root
model warped onto k, in k's coordinates, in the order of the root's points) and the true
images of the root's points on k, divided by k's RMS radius
(:func:`registration.synthetic.correspondence_error`). A subject a method leaves
unattached (``warped is None``) is counted separately and left out of that method's
mean; a penalised mean, where it counts as error 1.0, is printed beside it.

Families (collections with exact ground truth):

- ``yong-edge`` / ``yong-skel``: the character 永 (``../shared/data/glyphs_yong``), edge
  or skeleton points of a few font designs, deformed by
  :func:`registration.synthetic.deformation_chains` with its defaults (4 chains x 6 warp
  steps, 400 points, step 0.12); roots: shape 0 (undeformed) and chain 1 step 3;
- ``chui-fish`` / ``chui-chinese``: the Chui & Rangarajan deformation series
  (``../shared/data/chui_rangarajan``): per trial, the model X (root) and that trial's
  targets of deformation levels 1-5;
- ``chui-noise`` / ``chui-outlier`` / ``chui-occlusion``: the same benchmark's other
  series, fish and Chinese character together (per trial, the model and that trial's
  targets of every level): each target a new affine and warp of the model, with noise on
  its points (levels 1-6), up to twice as many outliers as points scattered over its box
  (1-5), or up to half of its points cut away (1-6). The truth is each target's clean
  image of a model point; occluded points have none, outliers are nobody's. Degraded
  shapes rather than deformed ones: e (eq. 10) counts every point both ways, so it
  rewards a registration that covers outliers or squeezes the model into what is left
  (bench/RESULTS.md 7.58); CPD's own mixture has an outlier term. ``chui-rot`` (only when
  named, with the turned families: no plain-CPD baseline): the series turned by up to
  180 degrees.
- ``generated``: :func:`registration.synthetic.chained_family` with its defaults (root 0).
- ``mpeg7`` / ``outline`` / ``outline-random`` / ``outline-arc``: shape classes no default
  was tuned on,
  deformed as the glyphs (root 0, the first seed only): the first instance of each MPEG-7
  class (400 points a shape, random subsets as the glyphs), and the first lmfree2d contour
  of each class (100 points), three Momocs hearts (80) and three North Sea fishes (120),
  their outlines densified 20x so that each shape samples its own points off them: evenly
  from a random start in the undeformed outline's spacing, which the warps stretch
  (``outline``), as random subsets (``outline-random``), or evenly along each deformed
  outline's own length (``outline-arc``, as an outline digitised anew on every shape: its
  sampling says nothing of the warp, bench/RESULTS.md 7.22).
- ``glyph-other``: five other characters (書水心東龍) rendered from the Noto CJK fonts
  when this machine has them (sans regular, serif bold), their edge pixels chained as the
  永 glyphs' (root 0, every seed: the first alone held 4 of the far-half misses where the
  second adds 5, bench/RESULTS.md 7.35): glyph sets no default was tuned on.
  ``--characters`` and ``--fonts`` run other ones (bench/RESULTS.md 7.28: twelve simpler
  characters in the two other Noto fonts).
- ``dense-edge`` / ``dense-skel``: the same characters rendered twice as large, their edge
  and skeleton pixels (3000-6000) chained at 1200 points a shape: above the default
  working resolution, so the tree is decided on 400-point subsamples and registered again
  at the stored resolution (the path of full-size uploads; bench/RESULTS.md 7.30). The 永
  skeletons have only 490-801 pixels: at 400 points two shapes share half or more of
  their points, and at 1200 every shape is all of them, which no real pair of instances
  does.
- ``small-step``: the 永 edges of the same designs and the first three glyph-other
  characters in the same fonts, chained with warp steps half the default (0.06): a
  collection of near-identical instances (prints of one type), where the tree has least
  to gain over plain CPD (root 0, seed 0).
- ``one-type``: the same sources as ``small-step``, each root with 12 subjects, every one
  a single warp of 0.04 of the size from the root (two thirds of small-step's step), drawn
  independently (seeds 0-1): prints of one type or block, a star rather than a chain, so
  none is far.
- ``one-type-dense``: the same prints of 書水心 drawn twice as large, at 1200 points a
  print: full-size scans, decided at the working resolution and registered again at the
  stored one (bench/RESULTS.md 7.54).
- ``glyph-latin``: Latin letters and digits (agR&5QOCDGSe0) from the same Noto fonts,
  chained as glyph-other (root 0, seed 0): glyphs of a few smooth closed contours, round
  ones among them, where the points barely show where a point lies along a contour
  (bench/RESULTS.md 7.39). ``--latin`` runs other ones; ``--fonts dejavu-sans,dejavu-serif``
  the same letters in DejaVu, a second type family (bench/RESULTS.md 7.40).
- ``glyph-stroke``: glyphs of one straight stroke (一丨I-1l) from the same Noto fonts,
  their skeletons and edges chained as glyph-other (root 0, the first two seeds): nearly
  symmetric under a half turn, so a registration can come out end for end at a low e
  (bench/RESULTS.md 7.42-7.43: seed 0 alone hid four of the failures seed 1 showed).

- ``glyph-turned`` (only when named in ``--only``): glyph-other's chains (seed 0) with
  every subject turned about its centroid by an angle drawn uniformly from +-180 degrees,
  the truth turned with it: instances at any angle, whose poses the pre-alignment has to
  find (bench/RESULTS.md 7.45). Plain CPD searches no pose, so it is no baseline there:
  the family is kept out of the targets, and its own lines compare the tree with direct
  CPD by the mean error and the subjects registered wrong (error above
  ``GROSS_ERROR``).

- ``ink-spread`` (only when named in ``--only``): glyph-other's characters and fonts,
  each printed with 0-6 px of extra ink about the outline, one print a step (root: the
  lightest), 400 random edge pixels a print; the true image of a root point is the
  heavier print's edge pixel nearest it (extra ink moves the outline along its normal).
  Not a deformation: the two sides of a stroke move apart. Kept out of the default run
  (bench/RESULTS.md 7.51).

"far" subjects are those more than half the family's chain length away from the root
along the generation (warp steps; for the Chui series, deformation levels): steps 4-6 of
a glyph chain for root 0. For the mid-chain root the distance is counted along the
generation tree (same chain: |step - 3|; other chains: 3 + step).

    .venv/bin/python bench/bench_groundtruth.py [--quick] [--seeds 2] [--designs ID,...]
        [--trials 3] [--characters 書水心東龍] [--fonts sans-regular,serif-bold]
        [--json PATH]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from ranking import auc, spearman
from scipy.spatial import cKDTree

from registration import CollectionResult, build_dynamic_tree, register_direct
from registration._points import normalise
from registration.synthetic import chained_family, correspondence_error, deformation_chains

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GLYPHS = DATA / "glyphs_yong"
CHUI = DATA / "chui_rangarajan"
PENALTY = 1.0
METHODS = ("plain", "direct", "tree")
MIRROR_CHECK = 0.5  # subjects with a GT error above this get a pose diagnosis


@dataclass
class Case:
    """One registration problem: a collection, a root and the ground truth for that root."""

    kind: str  # family kind, e.g. "yong-edge"
    label: str  # e.g. "yong-edge arphic-... seed 0"
    seed: int
    shapes: list[np.ndarray]
    names: list[str]
    root: int
    truth: list[np.ndarray]  # per shape, (n_root, 2); NaN rows: no true image
    depth: list[int]  # generation depth from the family's undeformed shape
    distance: list[int]  # generation distance from the root
    far_from: int  # subjects with distance >= far_from are "far"
    results: dict[str, CollectionResult] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- data


def _chain_distance(depth: list[int], chain: list[int], root: int) -> list[int]:
    """Warp steps between each shape and the root along the generation tree (a star of
    chains joined at shape 0)."""
    return [abs(depth[k] - depth[root]) if chain[k] == chain[root] else depth[k] + depth[root]
            for k in range(len(depth))]


def glyph_ids() -> list[str]:
    with (GLYPHS / "index.csv").open(newline="") as fh:
        return [row["id"] for row in csv.DictReader(fh)]


def pick_designs(spec: str | None, count: int) -> list[str]:
    """Design ids from ``--designs`` (ids or row numbers of index.csv), else `count`
    spread evenly over index.csv."""
    ids = glyph_ids()
    if spec:
        out = []
        for tok in (t.strip() for t in spec.split(",") if t.strip()):
            if tok.isdigit():
                out.append(ids[int(tok)])
            elif tok in ids:
                out.append(tok)
            else:
                raise SystemExit(f"unknown design {tok!r}: not an id or row number of index.csv")
        return out
    pos = np.unique(np.round(np.linspace(0, len(ids) - 1, count)).astype(int))
    return [ids[p] for p in pos]


def glyph_cases(kind: str, designs: list[str], seeds: list[int], mid_root: bool) -> list[Case]:
    cases = []
    for design in designs:
        dense = np.loadtxt(GLYPHS / "points" / f"{design}_{kind}.txt")
        for seed in seeds:
            fam = deformation_chains(dense, seed=seed)
            n = len(fam.shapes[0])
            if seed == seeds[0] and n > 0.5 * len(dense):
                # a sample of most of the file's points: two shapes share most of theirs,
                # which favours every method (bench/RESULTS.md 7.30; dense-edge /
                # dense-skel do not)
                print(f"NOTE: yong-{kind} {design}: {n} of its {len(dense)} points a shape, "
                      f"so two shapes share {n / len(dense):.0%} of their points on average")
            roots = [0]
            if mid_root:
                roots.append(next(k for k in range(len(fam.shapes))
                                  if fam.chain[k] == 0 and fam.depth[k] == 3))
            chain_length = max(fam.depth)
            for r in roots:
                cases.append(Case(
                    kind=f"yong-{kind}", label=f"yong-{kind} {design} seed {seed}", seed=seed,
                    shapes=fam.shapes, names=fam.names, root=r, truth=fam.root_images(r),
                    depth=fam.depth, distance=_chain_distance(fam.depth, fam.chain, r),
                    far_from=chain_length // 2 + 1,
                ))
    return cases


#: The Chui & Rangarajan series besides ``def``, and their levels: each level's target is a
#: new deformation of the model (an affine and a warp) with the series' degradation.
CHUI_SERIES = {"def": 5, "noise": 6, "outlier": 5, "occlusion": 6, "rot": 6}


def chui_cases(kind: str, trials: list[int], series: str = "def") -> list[Case]:
    """Per trial, the model X (the root) and that trial's targets of every level of
    `series`. The truth of model row ``gt[j]`` (the row of that level's ``X``, which the
    occlusion series lists in another order at each level) is row j of the clean target:
    ``Y_clean`` has ``Y``'s rows in the deformation, noise and occlusion series (occluded
    model points have no image: NaN), and only the inlier rows of ``Y``, in order, in the
    outlier series (rows with ``gt == -1`` are the outliers)."""
    levels = range(1, CHUI_SERIES[series] + 1)
    files = [CHUI / f"{kind}_{series}_{lvl}.npz" for lvl in levels]
    data = [np.load(f) for f in files]
    family = f"chui-{kind}" if series == "def" else f"chui-{series}"
    cases = []
    for t in trials:
        model = np.asarray(data[0]["X"][t], dtype=np.float64)
        shapes, names, truth = [model], ["model"], [model.copy()]
        rows = {tuple(p): i for i, p in enumerate(model)}
        for lvl, d in zip(levels, data, strict=True):
            name = files[lvl - 1].name
            # the occlusion series lists the model's rows in another order at each level
            order = np.array([rows.get(tuple(p), -1) for p in d["X"][t]])
            if len(rows) != len(model) or (order < 0).any() or len(set(order)) != len(model):
                raise SystemExit(f"{name}: trial {t} has a different model X")
            y, y_clean, gt = d["Y"][t], d["Y_clean"][t], d["gt_index_into_X"]
            inl = gt >= 0
            if gt.shape[0] != y.shape[0]:
                raise SystemExit(f"{name}: gt_index_into_X has {gt.shape[0]} rows, Y {y.shape[0]}")
            if y_clean.shape == y.shape:
                clean = y_clean[inl]
            elif y_clean.shape[0] == int(inl.sum()):
                clean = y_clean
                if series != "noise" and not np.allclose(y[inl], clean):
                    raise SystemExit(f"{name}: Y_clean is not Y's inlier rows")
            else:
                raise SystemExit(f"{name}: Y_clean has {y_clean.shape[0]} rows; Y has "
                                 f"{y.shape[0]}, {int(inl.sum())} of them inliers")
            image = np.full_like(model, np.nan)
            if len(np.unique(gt[inl])) != int(inl.sum()):
                raise SystemExit(f"{name}: a model point has two images")
            image[order[gt[inl]]] = clean
            shapes.append(np.asarray(y, dtype=np.float64))
            names.append(f"{series}{lvl}")
            truth.append(image)
        depth = list(range(len(shapes)))
        cases.append(Case(
            kind=family, label=f"{family} {kind} trial {t}" if series != "def"
            else f"chui-{kind} trial {t}", seed=t, shapes=shapes, names=names, root=0,
            # a degraded series' levels are no distance from the root: no far half
            truth=truth, depth=depth, distance=depth,
            far_from=3 if series == "def" else len(shapes),
        ))
    return cases


def _densify(contour: np.ndarray, per: int = 20) -> np.ndarray:
    """A closed contour with `per` points along each of its segments (linear), so that
    each deformed shape can sample its own points off the outline."""
    c = np.asarray(contour, dtype=np.float64)
    t = np.linspace(0.0, 1.0, per, endpoint=False)[None, :, None]
    return (c[:, None, :] * (1 - t) + np.roll(c, -1, axis=0)[:, None, :] * t).reshape(-1, 2)


def outline_sources() -> dict[str, list[tuple[str, np.ndarray, int]]]:
    """Dense outlines of the shape classes that no default was tuned on, with the points a
    shape of that class has: ``mpeg7`` (instance 1 of each class, 400 points), ``outline``
    (lmfree2d contours, shape 1 of each class, 100 points; Momocs hearts, 80, and North
    Sea fishes, 120: the first three of each)."""
    out: dict[str, list[tuple[str, np.ndarray, int]]] = {"mpeg7": [], "outline": []}
    mpeg7 = DATA / "mpeg7"
    if mpeg7.is_dir():
        for cls in sorted(p.name for p in mpeg7.iterdir() if (p / f"{p.name}-1.npy").exists()):
            out["mpeg7"].append((cls, np.load(mpeg7 / cls / f"{cls}-1.npy"), 400))
    lmfree = DATA / "lmfree2d"
    if lmfree.is_dir():
        for cls in sorted(p.name for p in lmfree.iterdir() if (p / "contours.csv").exists()):
            with (lmfree / cls / "contours.csv").open(newline="") as fh:
                pts = [(float(r["X"]), float(r["Y"])) for r in csv.DictReader(fh)
                       if r["Shape"] == "1"]
            out["outline"].append((f"lmfree2d-{cls}", _densify(np.array(pts)), 100))
    for name, n in (("hearts", 80), ("nsfishes", 120)):
        path = DATA / "momocs" / f"{name}.npz"
        if path.exists():
            with np.load(path) as data:
                for key in list(data.keys())[:3]:
                    out["outline"].append((f"{name}-{key}", _densify(data[key]), n))
    return out


#: The outline families and how each samples its shapes' points
#: (:func:`registration.synthetic.deformation_chains`' ``sampling``).
OUTLINE_SAMPLINGS = {"outline": "even", "outline-random": "random", "outline-arc": "arclength"}


def outline_source(kind: str) -> str:
    """The :func:`outline_sources` key a family `kind` draws its dense outlines from."""
    return "outline" if kind in OUTLINE_SAMPLINGS else kind


def outline_cases(kind: str, seeds: list[int],
                  sources: dict[str, list[tuple[str, np.ndarray, int]]] | None = None
                  ) -> list[Case]:
    """`deformation_chains` (its defaults but the points per shape) of each outline of
    `kind` (see :func:`outline_sources`), root 0, sampled as :data:`OUTLINE_SAMPLINGS`
    says: ``outline`` every n-th dense point from a random start (even in the undeformed
    outline's spacing, stretched by the warps); ``outline-random`` random subsets (as the
    glyph and MPEG-7 families do: gaps and clusters at 80-120 points that real outline data
    does not have); ``outline-arc`` evenly along each deformed outline's own length, as an
    outline digitised anew on every shape. `sources`: those of
    :func:`outline_sources`, read again when not given."""
    cases = []
    source = outline_source(kind)
    sampling = OUTLINE_SAMPLINGS.get(kind, "random")
    for name, dense, n in (sources or outline_sources())[source]:
        for seed in seeds:
            fam = deformation_chains(dense, n_points=n, seed=seed, sampling=sampling)
            cases.append(Case(
                kind=kind, label=f"{kind} {name} seed {seed}", seed=seed,
                shapes=fam.shapes, names=fam.names, root=0, truth=fam.root_images(0),
                depth=fam.depth, distance=fam.depth, far_from=max(fam.depth) // 2 + 1,
            ))
    return cases


#: Characters other than 永 for the ``glyph-other`` family, and the CJK fonts they are
#: rendered from when this machine has them (Debian's fonts-noto-cjk, which .ci/run
#: installs).
OTHER_CHARACTERS = "書水心東龍"
_NOTO = Path("/usr/share/fonts/opentype/noto")
OTHER_FONTS = {
    "sans-regular": _NOTO / "NotoSansCJK-Regular.ttc",
    "serif-bold": _NOTO / "NotoSerifCJK-Bold.ttc",
}
CJK_FONTS = {
    **OTHER_FONTS,
    "sans-bold": _NOTO / "NotoSansCJK-Bold.ttc",
    "serif-regular": _NOTO / "NotoSerifCJK-Regular.ttc",
}
_DEJAVU = Path("/usr/share/fonts/truetype/dejavu")
#: Latin-only fonts (Debian's fonts-dejavu-core): a second type family for ``glyph-latin``.
#: They carry no CJK characters; a character a font lacks is skipped (`has_glyph`).
LATIN_FONTS = {
    "dejavu-sans": _DEJAVU / "DejaVuSans.ttf",
    "dejavu-serif": _DEJAVU / "DejaVuSerif.ttf",
}
#: Every font ``--fonts`` can name (:data:`OTHER_FONTS` are the default).
FONTS = {**CJK_FONTS, **LATIN_FONTS}


#: Points a shape of the ``dense-edge`` / ``dense-skel`` families: above the library's
#: default working resolution (400), so the tree is decided on subsamples and registered
#: again at the stored resolution, as for full-size uploads.
DENSE_POINTS = 1200
#: The dense families' characters are rendered this many times larger than glyph-other's
#: (512 px: 5000-6000 edge pixels and 3000-3300 skeleton pixels for 書), so that 1200 points
#: are a sample of each deformed glyph and no two shapes share most of their points.
DENSE_SCALE = 2


def glyph_points(char: str, font: Path, mode: str = "edges", scale: int = 1,
                 ink: int = 0) -> np.ndarray:
    """The edge (Canny) or skeleton pixels of `char` rendered at 256 x `scale` px (the
    library's image route, as the 永 set's points were made); `ink` px of extra ink
    about the outline (PIL's stroke width: a heavier print of the same glyph)."""
    from PIL import Image, ImageDraw, ImageFont

    from registration.images import points_from_image

    img = Image.new("L", (300 * scale, 300 * scale), 255)
    ImageDraw.Draw(img).text((22 * scale, 0), char,
                             font=ImageFont.truetype(str(font), 256 * scale), fill=0,
                             stroke_width=ink, stroke_fill=0)
    return points_from_image(img, mode=mode)


#: A code point no font draws (plane 16's last, private use): what a font renders for a
#: character it lacks.
_NO_GLYPH = "\U0010fffd"


def has_glyph(char: str, font: Path) -> bool:
    """Whether `font` draws `char` rather than its missing-glyph box (or nothing)."""
    from PIL import ImageFont

    f = ImageFont.truetype(str(font), 64)
    mask = f.getmask(char)
    if mask.getbbox() is None:
        return False
    missing = f.getmask(_NO_GLYPH)
    return bool(mask.size != missing.size or bytes(mask) != bytes(missing))


def _rendered_glyph_cases(seeds: list[int], characters: str, fonts: dict[str, Path] | None,
                          families: tuple[tuple[str, str, int, int | None], ...]
                          ) -> list[Case]:
    """The `characters` in the `fonts` (default :data:`OTHER_FONTS`) found here, chained as
    the 永 glyphs' (root 0), once per family of `families`: (kind, image mode, render scale,
    points a shape; None: :func:`~registration.synthetic.deformation_chains`' default).
    A character a font lacks (:func:`has_glyph`) is skipped, with a note."""
    cases = []
    for char, font_name, font in _drawn(characters, fonts):
        for kind, mode, scale, n_points in families:
            dense = glyph_points(char, font, mode, scale)
            points = {} if n_points is None else {"n_points": n_points}
            for seed in seeds:
                fam = deformation_chains(dense, seed=seed, **points)
                cases.append(Case(
                    kind=kind, label=f"{kind} {char} {font_name} seed {seed}",
                    seed=seed, shapes=fam.shapes, names=fam.names, root=0,
                    truth=fam.root_images(0), depth=fam.depth, distance=fam.depth,
                    far_from=max(fam.depth) // 2 + 1,
                ))
    return cases


def _drawn(characters: str, fonts: dict[str, Path] | None
           ) -> Iterator[tuple[str, str, Path]]:
    """(character, font name, font) for each of the `characters` in each of the `fonts`
    (default :data:`OTHER_FONTS`) installed here that draws it; one it lacks is skipped,
    with a note."""
    for char in characters:
        for font_name, font in (OTHER_FONTS if fonts is None else fonts).items():
            if not font.exists():
                continue
            if not has_glyph(char, font):
                print(f"NOTE: {font_name} has no glyph for {char!r}: skipping it there")
                continue
            yield char, font_name, font


#: Latin glyphs for the ``glyph-latin`` family: letters of one contour and of several,
#: with and without corners, and the round O, Q, 0 (bench/RESULTS.md 7.39).
LATIN_CHARACTERS = "agR&5QOCDGSe0"


def latin_glyph_cases(seeds: list[int], characters: str = LATIN_CHARACTERS,
                      fonts: dict[str, Path] | None = None) -> list[Case]:
    """``glyph-latin``: the Latin `characters` (default :data:`LATIN_CHARACTERS`) in the
    `fonts` (default :data:`OTHER_FONTS`) found here, their edges chained as the 永
    glyphs' (root 0)."""
    return _rendered_glyph_cases(seeds, characters, fonts,
                                 (("glyph-latin", "edges", 1, None),))


#: Glyphs of one straight stroke for the ``glyph-stroke`` family (bench/RESULTS.md 7.42).
STROKE_CHARACTERS = "一丨I-1l"


def stroke_glyph_cases(seeds: list[int], characters: str = STROKE_CHARACTERS,
                       fonts: dict[str, Path] | None = None) -> list[Case]:
    """``glyph-stroke``: the one-stroke `characters` (default :data:`STROKE_CHARACTERS`)
    in the `fonts` (default :data:`OTHER_FONTS`) found here, their skeletons and edges
    chained as the 永 glyphs' (root 0). A character whose skeleton has fewer than three
    points (a dot) is skipped, with a note."""
    cases = []
    for char in characters:
        for mode in ("skeleton", "edges"):
            try:
                made = _rendered_glyph_cases(seeds, char, fonts,
                                             (("glyph-stroke", mode, 1, None),))
            except ValueError as exc:  # too few points to chain
                print(f"NOTE: glyph-stroke: no {mode} chain of {char!r}: {exc}")
                continue
            for case in made:
                case.label = case.label.replace("glyph-stroke ", f"glyph-stroke {mode} ", 1)
            cases += made
    return cases


#: Families whose subjects lie at any angle: no plain-CPD baseline, kept out of the targets.
TURNED_KINDS = frozenset({"glyph-turned", "chui-rot"})
#: A subject registered wrong (the wrong pose: a turn, a mirror, a slide by a stroke): its
#: RMS ground-truth error above this fraction of its RMS radius.
GROSS_ERROR = 0.5


def turned_glyph_cases(seeds: list[int], characters: str = OTHER_CHARACTERS,
                       fonts: dict[str, Path] | None = None) -> list[Case]:
    """``glyph-turned``: glyph-other's chains with every subject turned about its centroid
    by an angle drawn uniformly from +-180 degrees (seeded by the chain's seed), the truth
    turned with it."""
    cases = _rendered_glyph_cases(seeds, characters, fonts,
                                  (("glyph-turned", "edges", 1, None),))
    for case in cases:
        rng = np.random.default_rng([case.seed, 7])
        for k in range(len(case.shapes)):
            if k == case.root:
                continue
            a = math.radians(rng.uniform(-180.0, 180.0))
            turn = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            c = case.shapes[k].mean(axis=0)
            case.shapes[k] = (case.shapes[k] - c) @ turn.T + c
            case.truth[k] = (case.truth[k] - c) @ turn.T + c
    return cases


def turned_summary(cases: list[Case], rows_by_case: list[list[dict[str, Any]]]) -> None:
    """The turned families' own lines: per run, each method's mean ground-truth error
    and its subjects registered wrong (error above ``GROSS_ERROR``; unattached ones
    counted apart)."""
    print(f"\nturned collections (no plain-CPD baseline: mean GT error, and subjects with "
          f"GT error > {GROSS_ERROR} or unattached):")
    totals = {m: [0, 0, 0] for m in METHODS}
    for case, rows in zip(cases, rows_by_case, strict=True):
        cells = []
        for m in METHODS:
            errs = [r[m]["gt"] for r in rows if r[m]["gt"] is not None]
            gross = sum(e > GROSS_ERROR for e in errs)
            totals[m][0] += gross
            totals[m][1] += len(rows) - len(errs)
            totals[m][2] += len(rows)
            cells.append(f"{m} {f4(_mean(errs))} {gross:2d}+{len(rows) - len(errs)}")
        print(f"  {case.label:40s} " + "   ".join(cells))
    print("  ALL" + " " * 38 + "   ".join(
        f"{m} wrong {g} + unattached {u} of {n}" for m, (g, u, n) in totals.items()))


#: Extra ink of the ``ink-spread`` family's prints, px about the outline at 256 px (the
#: strokes of the Noto fonts' regular weights are about 20 px wide there).
INK_WIDTHS = (0, 1, 2, 3, 4, 5, 6)
#: A root point whose nearest edge pixel of a heavier print lies further than this (px)
#: from that print's ink width off it has no true image there (strokes merged, a counter
#: closed up; up to 15 % of 書's points at 6 px, 0-2 % at 1-3 px).
INK_TRUTH_TOLERANCE = 1.5


def ink_spread_cases(seeds: list[int], characters: str = OTHER_CHARACTERS,
                     fonts: dict[str, Path] | None = None, n_points: int = 400) -> list[Case]:
    """``ink-spread``: each character printed with more and more ink, one print a step
    (:data:`INK_WIDTHS`; root: the lightest), their edge pixels sampled at random, 400 a
    print (seeded by `seeds`). Extra ink moves the outline along its normal, so the true
    image of a root point on a heavier print is that print's edge pixel nearest it (the
    sampled subject lies on the same pixels); see :data:`INK_TRUTH_TOLERANCE` for the
    points without one.

    Not a deformation: the two sides of a stroke move apart, which no coherent field (CPD's)
    follows, and the prints of one glyph differ by little else. The tree gains nothing over
    plain CPD here and loses where its polish fits the samples (bench/RESULTS.md 7.51)."""
    cases = []
    for char, font_name, font in _drawn(characters, fonts):
        dense = [glyph_points(char, font, ink=w) for w in INK_WIDTHS]
        for seed in seeds:
            rng = np.random.default_rng([seed, 11])
            shapes = [d[rng.choice(len(d), min(n_points, len(d)), replace=False)]
                      for d in dense]
            truth = []
            for w, d in zip(INK_WIDTHS, dense, strict=True):
                dist, j = cKDTree(d).query(shapes[0])
                t = d[j].astype(np.float64)
                t[np.abs(dist - w) > INK_TRUTH_TOLERANCE] = np.nan
                truth.append(t)
            steps = list(range(len(INK_WIDTHS)))
            cases.append(Case(
                kind="ink-spread", label=f"ink-spread {char} {font_name} seed {seed}",
                seed=seed, shapes=shapes, names=[f"ink{w}" for w in INK_WIDTHS], root=0,
                truth=truth, depth=steps, distance=steps, far_from=max(steps) // 2 + 1,
            ))
    return cases


def other_glyph_cases(seeds: list[int], characters: str = OTHER_CHARACTERS,
                      fonts: dict[str, Path] | None = None) -> list[Case]:
    """``glyph-other``: the `characters` (default :data:`OTHER_CHARACTERS`) in the `fonts`
    (default :data:`OTHER_FONTS`) found here, their edges chained as the 永 glyphs' (root
    0): glyph sets no default was tuned on."""
    return _rendered_glyph_cases(seeds, characters, fonts,
                                 (("glyph-other", "edges", 1, None),))


def dense_glyph_cases(seeds: list[int], characters: str = OTHER_CHARACTERS,
                      fonts: dict[str, Path] | None = None) -> list[Case]:
    """``dense-edge`` / ``dense-skel``: glyph-other's characters rendered at
    :data:`DENSE_SCALE` times the size, their edge and skeleton pixels chained as the 永
    glyphs' at :data:`DENSE_POINTS` points a shape (root 0): the library's coarse-to-fine
    path, which every other family (at most 400 points a shape) leaves out."""
    return _rendered_glyph_cases(seeds, characters, fonts,
                                 (("dense-edge", "edges", DENSE_SCALE, DENSE_POINTS),
                                  ("dense-skel", "skeleton", DENSE_SCALE, DENSE_POINTS)))


#: The ``small-step`` family's warp step: half of :func:`~registration.synthetic.
#: deformation_chains`' default (0.12 of the RMS radius a step).
SMALL_STEP = 0.06


def _small_sources(designs: list[str], characters: str, fonts: dict[str, Path]
                   ) -> list[tuple[str, np.ndarray]]:
    """The dense shapes of the near-identical families: the 永 edges of `designs` and
    `characters` drawn in `fonts`, each with its name."""
    sources: list[tuple[str, np.ndarray]] = []
    for design in designs:
        path = GLYPHS / "points" / f"{design}_edge.txt"
        if path.exists():
            sources.append((f"永 {design}", np.loadtxt(path)))
    for char, font_name, font in _drawn(characters, fonts):
        sources.append((f"{char} {font_name}", glyph_points(char, font)))
    return sources


def small_step_cases(designs: list[str], characters: str,
                     fonts: dict[str, Path]) -> list[Case]:
    """``small-step``: the 永 edges of `designs` and glyph-other's `characters` in `fonts`,
    chained as the glyph families (seed 0, root 0) but with warp steps of
    :data:`SMALL_STEP`: collections of near-identical instances, as prints of one type or
    block are, where plain CPD from the root is already near what one registration of two
    random samples can reach and the polish's stages and finish mostly fit the samples'
    noise (bench/RESULTS.md 7.34)."""
    cases = []
    for name, dense in _small_sources(designs, characters, fonts):
        fam = deformation_chains(dense, seed=0, step=SMALL_STEP)
        cases.append(Case(
            kind="small-step", label=f"small-step {name} seed 0", seed=0, shapes=fam.shapes,
            names=fam.names, root=0, truth=fam.root_images(0), depth=fam.depth,
            distance=fam.depth, far_from=max(fam.depth) // 2 + 1,
        ))
    return cases


#: The ``one-type`` family: subjects a collection, and each one's warp from the root (RMS
#: displacement over the RMS radius, and the largest turn in degrees).
ONE_TYPE_SUBJECTS = 12
ONE_TYPE_STEP = 0.04
ONE_TYPE_ROTATION = 1.0


def one_type_cases(designs: list[str], characters: str, fonts: dict[str, Path],
                   seeds: list[int]) -> list[Case]:
    """``one-type``: prints of one type or block, the archive application's collections.
    Every subject is one small warp of the root's shape (:data:`ONE_TYPE_STEP`), drawn
    independently of the others: a star, not a chain, so no subject is far from the root
    and every one sits one step from it (root 0, the sources of ``small-step``). Plain CPD
    from the root is one registration across the smallest difference there is; the tree
    can only match it or fit the samples' noise (bench/RESULTS.md 7.53)."""
    return _star_cases("one-type", _small_sources(designs, characters, fonts), seeds)


def dense_one_type_cases(characters: str, fonts: dict[str, Path],
                         seeds: list[int]) -> list[Case]:
    """``one-type-dense``: ``one-type``'s prints at full size, the `characters` drawn in
    `fonts` at :data:`DENSE_SCALE` times the size and sampled at :data:`DENSE_POINTS`
    points a print, so that the tree is decided on 400-point subsamples and registered
    again at the stored resolution: the path of uploaded scans (bench/RESULTS.md 7.54)."""
    sources = [(f"{char} {font_name}", glyph_points(char, font, scale=DENSE_SCALE))
               for char, font_name, font in _drawn(characters, fonts)]
    return _star_cases("one-type-dense", sources, seeds, DENSE_POINTS)


def _star_cases(kind: str, sources: list[tuple[str, np.ndarray]], seeds: list[int],
                n_points: int = 400) -> list[Case]:
    """A collection of ``ONE_TYPE_SUBJECTS`` prints of each source per seed, each one
    small warp of the root's shape drawn independently, `n_points` points a shape."""
    cases = []
    for name, dense in sources:
        for seed in seeds:
            fam = deformation_chains(dense, n_chains=ONE_TYPE_SUBJECTS, chain_length=1,
                                     step=ONE_TYPE_STEP, rotation_deg=ONE_TYPE_ROTATION,
                                     seed=seed, n_points=n_points)
            cases.append(Case(
                kind=kind, label=f"{kind} {name} seed {seed}", seed=seed,
                shapes=fam.shapes, names=fam.names, root=0, truth=fam.root_images(0),
                depth=fam.depth, distance=fam.depth, far_from=2,  # none is far
            ))
    return cases


def generated_cases(seeds: list[int]) -> list[Case]:
    cases = []
    for seed in seeds:
        fam = chained_family(seed=seed)
        chain_length = max(fam.depth)
        cases.append(Case(
            kind="generated", label=f"generated chained_family seed {seed}", seed=seed,
            shapes=fam.shapes, names=fam.names, root=0, truth=fam.root_images,
            depth=fam.depth, distance=fam.depth, far_from=chain_length // 2 + 1,
        ))
    return cases


# ----------------------------------------------------------------------------- scoring


def gt_error(warped: np.ndarray | None, truth: np.ndarray, subject: np.ndarray) -> float | None:
    if warped is None:
        return None
    has = np.isfinite(truth).all(axis=1)
    return correspondence_error(warped[has], truth[has], subject)


def error_along(warped: np.ndarray | None, truth: np.ndarray, subject: np.ndarray,
                neighbours: int = 8) -> float | None:
    """The part of :func:`gt_error` that lies along the subject's outline: the RMS of each
    error vector's component along the outline's direction at the true image (the
    principal direction of the subject's `neighbours` points nearest to it), over the
    subject's RMS radius. A registration that slid along the outline errs along it, where
    neither e (eq. 10) nor the data term of CPD sees anything; one off the outline errs
    across it. At corners and junctions the direction is ill-defined, so read the share
    pooled over many subjects."""
    if warped is None:
        return None
    has = np.isfinite(truth).all(axis=1)
    y = np.asarray(subject, dtype=np.float64)
    t = truth[has]
    k = min(neighbours, len(y))
    _, idx = cKDTree(y).query(t, k)
    nb = y[idx] - y[idx].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    along = np.einsum("ni,ni->n", warped[has] - t, vecs[:, :, 1])
    return float(np.sqrt(np.mean(along * along))) / normalise(y)[1].scale  # as gt_error


def pose_diagnosis(warped: np.ndarray, truth: np.ndarray) -> str:
    """Best orthogonal map (Procrustes) from the true images to the warped model: a
    reflection or a large rotation means the method found a mirrored/rotated match."""
    has = np.isfinite(truth).all(axis=1)
    a = truth[has] - truth[has].mean(axis=0)
    b = warped[has] - warped[has].mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    r = u @ vt  # a @ r ~ b
    mirrored = np.linalg.det(r) < 0
    if mirrored:
        r = r @ np.diag([1.0, -1.0])
    angle = math.degrees(math.atan2(r[0, 1], r[0, 0]))
    scale = float(np.linalg.norm(b)) / max(float(np.linalg.norm(a)), 1e-12)
    return f"{'MIRRORED ' if mirrored else ''}rotation {angle:+.0f} deg, size ratio {scale:.2f}"


def per_subject(case: Case) -> list[dict[str, Any]]:
    rows = []
    for k in range(len(case.shapes)):
        if k == case.root:
            continue
        row: dict[str, Any] = {
            "index": k, "name": case.names[k], "depth": case.depth[k],
            "distance": case.distance[k], "far": case.distance[k] >= case.far_from,
        }
        for m in METHODS:
            s = case.results[m].subject(k)
            row[m] = {
                "gt": gt_error(s.warped, case.truth[k], case.shapes[k]),
                "along": error_along(s.warped, case.truth[k], case.shapes[k]),
                "e": s.error, "layer": s.layer, "parent": s.parent, "attached": s.attached,
                # newer library versions attach low-confidence leaves and give a confidence
                "leaf": bool(getattr(s, "leaf", False)),
                "confidence": getattr(s, "confidence", None),
                # how far apart the symmetric finish's two registrations are (None without
                # one; bench/RESULTS.md 7.38)
                "disagreement": getattr(s, "disagreement", None),
                # the dynamic tree's edges: which CPD start the subject's edge kept and the
                # e of each (bench/RESULTS.md 7.36); None where the edge ran one start
                "edge_start": (getattr(s, "quality", None) or {}).get("edge_start"),
                "edge_start_errors": (getattr(s, "quality", None) or {}).get("edge_start_errors"),
            }
        rows.append(row)
    return rows


def _mean(v: list[float]) -> float:
    return float(np.mean(v)) if v else float("nan")


def _p95(v: list[float]) -> float:
    return float(np.percentile(v, 95)) if v else float("nan")


def group_stats(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per method: mean (attached), penalised mean, p95, counts; ratios against plain."""
    out: dict[str, Any] = {"n": len(rows)}
    for m in METHODS:
        att = [r[m]["gt"] for r in rows if r[m]["gt"] is not None]
        pen = [r[m]["gt"] if r[m]["gt"] is not None else PENALTY for r in rows]
        out[m] = {"mean": _mean(att), "pen": _mean(pen), "p95": _p95(att),
                  "attached": len(att), "unattached": len(rows) - len(att)}
    plain_pen = out["plain"]["pen"]
    for m in [m for m in METHODS if m != "plain"]:
        same = [r["plain"]["gt"] for r in rows
                if r[m]["gt"] is not None and r["plain"]["gt"] is not None]
        out[f"{m}/plain"] = out[m]["pen"] / plain_pen if plain_pen > 0 else float("nan")
        out[f"{m}/plain same"] = (out[m]["mean"] / _mean(same)
                                  if same and _mean(same) > 0 else float("nan"))
    return out


def e_stats(case: Case) -> dict[str, Any]:
    """e (eq. 10) at tree layer >= 3, the tree's and plain CPD's on the same subjects."""
    tree, plain = case.results["tree"], case.results["plain"]
    deep = [s.index for s in tree.subjects
            if s.attached and s.layer is not None and s.layer >= 3]
    pe = [e for i in deep if (e := plain.subject(i).error) is not None]
    st = tree.summary()["layer_ge_3"]
    return {"n": st["count"], "tree_mean": st["mean"], "tree_p95": st["p95"],
            "plain_mean": _mean(pe) if pe else None, "plain_p95": _p95(pe) if pe else None}


# ----------------------------------------------------------------------------- output


def f4(v: float | None) -> str:
    return "   n/a" if v is None or not np.isfinite(v) else f"{v:6.4f}"


def f2(v: float | None) -> str:
    return "  n/a" if v is None or not np.isfinite(v) else f"{v:5.2f}"


def header(first: str = "subjects", width: int = 9) -> str:
    return (f"{first:{width}s} {'n':>3s} | {'plain':>6s} {'direct':>6s} {'tree':>6s} "
            f"{'tree*':>6s} {'unatt':>5s} | {'p95 pl':>6s} {'p95 dir':>7s} {'p95 tr':>6s} | "
            f"{'tr/pl':>5s} {'tr/pl=':>6s} {'dir/pl':>6s}")


def stats_line(name: str, st: dict[str, Any], width: int = 9) -> str:
    if st["n"] == 0:
        return f"{name:{width}s} {0:3d} | (none)"
    return (f"{name:{width}s} {st['n']:3d} | {f4(st['plain']['mean'])} "
            f"{f4(st['direct']['mean'])} "
            f"{f4(st['tree']['mean'])} {f4(st['tree']['pen'])} "
            f"{st['tree']['unattached']:5d} | {f4(st['plain']['p95'])} "
            f" {f4(st['direct']['p95'])} {f4(st['tree']['p95'])} | "
            f"{f2(st['tree/plain'])}  {f2(st['tree/plain same'])}  {f2(st['direct/plain'])}")


def report_case(case: Case, rows: list[dict[str, Any]]) -> dict[str, Any]:
    root = case.names[case.root]
    all_st = group_stats(rows)
    far_rows = [r for r in rows if r["far"]]
    far_st = group_stats(far_rows)
    es = e_stats(case)
    secs = "  ".join(f"{m} {case.seconds[m]:.1f}s" for m in METHODS)
    print(f"\n--- {case.label}, root {case.root} ({root}): {len(case.shapes)} shapes; {secs}")
    print(header())
    print(stats_line("all", all_st))
    far_note = (f"far: distance from the root >= {case.far_from} generation steps"
                + ("" if case.depth[case.root] == 0
                   else " (counted along the generation tree through shape 0)"))
    print(stats_line("far", far_st) + f"   [{far_note}]")
    if "variant" in METHODS:
        print(f"  variant*/plain all {f2(all_st['variant/plain'])}, "
              f"far {f2(far_st['variant/plain'])}"
              f" (tree*/plain {f2(all_st['tree/plain'])}, {f2(far_st['tree/plain'])}); "
              f"variant {case.seconds['variant']:.1f}s")
    unatt = {m: [r["name"] for r in rows if not r[m]["attached"]] for m in METHODS}
    for m, names in unatt.items():
        if names:
            print(f"  {m}: unattached {', '.join(names)}")
    leaves = [r for r in rows if r["tree"]["leaf"]]
    if leaves:
        gts = [r["tree"]["gt"] for r in leaves if r["tree"]["gt"] is not None]
        print(f"  tree: {len(leaves)} low-confidence leaves (attached, counted in the means; "
              f"mean GT error {_mean(gts):.4f}): " + ", ".join(r["name"] for r in leaves))
    print(f"  e (eq. 10) at tree layer >= 3 ({es['n']} subjects): tree mean/p95 "
          f"{f4(es['tree_mean'])}/{f4(es['tree_p95'])}, plain CPD on the same subjects "
          f"{f4(es['plain_mean'])}/{f4(es['plain_p95'])}")
    by_layer: dict[int, list[float]] = {}
    for r in rows:
        if r["tree"]["layer"] is not None:
            by_layer.setdefault(r["tree"]["layer"], []).append(r["tree"]["gt"])
    print("  tree layers (count: mean GT error): " + ", ".join(
        f"L{k} {len(v)}: {np.mean(v):.4f}" for k, v in sorted(by_layer.items())))
    for r in rows:
        for m in METHODS:
            gt = r[m]["gt"]
            if gt is not None and gt > MIRROR_CHECK:
                s = case.results[m].subject(r["index"])
                assert s.warped is not None
                print(f"  ! {m} on {r['name']} (depth {r['depth']}): GT error {gt:.3f}, "
                      f"e {s.error:.4g}, layer {s.layer}: "
                      f"{pose_diagnosis(s.warped, case.truth[r['index']])}")
    return {"all": all_st, "far": far_st, "e": es}


def summary(cases: list[Case], reports: list[dict[str, Any]],
            rows_by_case: list[list[dict[str, Any]]]) -> None:
    turned = [i for i, c in enumerate(cases) if c.kind in TURNED_KINDS]
    if turned:
        turned_summary([cases[i] for i in turned], [rows_by_case[i] for i in turned])
        keep = [i for i in range(len(cases)) if i not in turned]
        cases = [cases[i] for i in keep]
        reports = [reports[i] for i in keep]
        rows_by_case = [rows_by_case[i] for i in keep]
        if not cases:
            return
    print("\n" + "=" * 100)
    print("SUMMARY: mean ground-truth correspondence error (RMS / subject's RMS radius), "
          "pooled over the runs of each family")
    print("tree = attached subjects only; tree* = penalised, an unattached subject counts as "
          f"error {PENALTY}; tr/pl uses tree*, tr/pl= compares the attached subjects with "
          "plain on the same subjects")
    print("far = subjects more than half a chain from the root along the generation "
          "(glyph chains: steps 4-6 from root 0)")
    kinds = list(dict.fromkeys(c.kind for c in cases))
    print(f"\n{'family':13s} {'runs':>4s} " + header("part", 4)
          + f" | {'worst tr/pl':>11s} {'worst dir/pl':>12s}")
    verdicts: list[tuple[str, bool, str]] = []
    pooled_all: list[dict[str, Any]] = []
    pooled_far: list[dict[str, Any]] = []
    worst_t_all, worst_d_all = 0.0, 0.0
    for kind in [*kinds, "ALL"]:
        idx = [i for i, c in enumerate(cases) if kind in (c.kind, "ALL")]
        rows = [r for i in idx for r in rows_by_case[i]]
        far = [r for r in rows if r["far"]]
        worst_t = max(reports[i]["all"]["tree/plain"] for i in idx)
        worst_d = max(reports[i]["all"]["direct/plain"] for i in idx)
        for part, group in (("all", rows), ("far", far)):
            st = group_stats(group)
            extra = f" | {f2(worst_t):>11s} {f2(worst_d):>12s}" if part == "all" else ""
            print(f"{kind:13s} {len(idx):4d} {stats_line(part, st, 4)}{extra}")
            if kind == "ALL":
                (pooled_all if part == "all" else pooled_far).append(st)
            else:
                if part == "far" and st["n"]:
                    verdicts.append((f"{kind}: tree* <= 0.6x plain on the far half",
                                     st["tree/plain"] <= 0.6, f2(st["tree/plain"]).strip()))
                if part == "all":
                    verdicts.append((f"{kind}: tree* <= 0.85x plain over all subjects",
                                     st["tree/plain"] <= 0.85, f2(st["tree/plain"]).strip()))
        if kind != "ALL":
            worst_t_all, worst_d_all = max(worst_t_all, worst_t), max(worst_d_all, worst_d)
    # the glyph chains' target holds run by run: the 永 sets it was set on, and the glyph
    # sets no rule was measured on (glyph-other, glyph-latin; bench/RESULTS.md 7.28, 7.39)
    far_over: list[tuple[str, int, float]] = []
    for name, is_kind in (("永", lambda k: k.startswith("yong")),
                          ("other-glyph", lambda k: k == "glyph-other"),
                          ("Latin-glyph", lambda k: k == "glyph-latin"),
                          ("stroke-glyph", lambda k: k == "glyph-stroke"),
                          ("dense-glyph", lambda k: k.startswith("dense"))):
        far_runs = [(c.label, c.root, r["far"]["tree/plain"]) for c, r in
                    zip(cases, reports, strict=True) if is_kind(c.kind) and r["far"]["n"]]
        over = [x for x in far_runs if not x[2] <= 0.6]
        far_over += over
        if far_runs:
            passed = f"{len(far_runs) - len(over)} of {len(far_runs)} runs"
            roots = sorted({root for _, root, _ in far_runs})
            if len(roots) > 1:  # the ratio depends on the root (bench/RESULTS.md 7.37)
                passed += " (" + ", ".join(
                    f"root {root}: {sum(v <= 0.6 for _, r, v in far_runs if r == root)} of "
                    f"{sum(r == root for _, r, _ in far_runs)}" for root in roots) + ")"
            verdicts.append((f"every {name} run: tree* <= 0.6x plain on its far half",
                             not over, passed))
    verdicts.append(("every run: tree* <= 1.05x plain", worst_t_all <= 1.05,
                     f"worst {worst_t_all:.2f}"))
    verdicts.append(("every run: direct <= 1.05x plain", worst_d_all <= 1.05,
                     f"worst {worst_d_all:.2f}"))
    over_t = [(c.label, c.root, r["all"]["tree/plain"]) for c, r in zip(cases, reports,
              strict=True) if r["all"]["tree/plain"] > 1.05]
    over_d = [(c.label, c.root, r["all"]["direct/plain"]) for c, r in zip(cases, reports,
              strict=True) if r["all"]["direct/plain"] > 1.05]
    st_all, st_far = pooled_all[0], pooled_far[0]
    if st_far["n"]:  # none when only families without far subjects ran (one-type)
        verdicts.append(("ALL: tree* <= 0.6x plain on the far half",
                         st_far["tree/plain"] <= 0.6, f2(st_far["tree/plain"]).strip()))
    verdicts.append(("ALL: tree* <= 0.85x plain over all subjects",
                     st_all["tree/plain"] <= 0.85, f2(st_all["tree/plain"]).strip()))
    print("\nTargets (tree* = penalised for unattached subjects):")
    for text, ok, val in verdicts:
        print(f"  [{'PASS' if ok else 'FAIL'}] {text}: {val}")
    for label, root, v in far_over:
        print(f"    far half: tree*/plain {v:.2f} on {label}, root {root}")
    for label, root, v in over_t:
        print(f"    tree*/plain {v:.2f} on {label}, root {root}")
    for label, root, v in over_d:
        print(f"    direct/plain {v:.2f} on {label}, root {root}")
    print("\ne (eq. 10) at tree layer >= 3 (tree vs plain CPD on the same subjects), pooled "
          "per family:")
    for kind in kinds:
        t_e, p_e = [], []
        for c in cases:
            if c.kind != kind:
                continue
            tree, plain = c.results["tree"], c.results["plain"]
            for s in tree.subjects:
                if s.attached and s.layer is not None and s.layer >= 3 and s.error is not None:
                    pe = plain.subject(s.index).error
                    if pe is not None:
                        t_e.append(s.error)
                        p_e.append(pe)
        print(f"  {kind:13s} n={len(t_e):3d}  tree mean/p95 {f4(_mean(t_e))}/{f4(_p95(t_e))}"
              f"   plain mean/p95 {f4(_mean(p_e))}/{f4(_p95(p_e))}")
    print("\nwhere the error lies: share of the squared GT error along the subject's outline "
          "(a slide, which e cannot see; the rest lies across it), all subjects / far half:")
    for kind in kinds:
        rows = [r for i, c in enumerate(cases) if c.kind == kind for r in rows_by_case[i]]
        cells = []
        for m in METHODS:
            parts = []
            for group in (rows, [r for r in rows if r["far"]]):
                pairs = [(r[m]["gt"], r[m]["along"]) for r in group if r[m]["gt"] is not None]
                total = sum(g * g for g, _ in pairs)
                parts.append(f2(sum(a * a for _, a in pairs) / total if total > 0 else None))
            cells.append(f"{m} {parts[0].strip()} / {parts[1].strip()}")
        print(f"  {kind:13s} " + "   ".join(cells))
    print("\nwhich subjects the tree's own signs single out, '1 - confidence' and "
          "'disagreement' (bench/RESULTS.md 7.38):\nthe AUC of each for the fifth of the "
          "subjects the tree registered worst (1.0 ranks them all first,\n0.5 is chance) "
          "and Spearman's rank correlation rho with the GT error, pooled over the family's\n"
          "subjects, and within each run (as a user sorts one job), averaged over the runs:")
    for kind in kinds:
        per_run = []
        for i, c in enumerate(cases):
            if c.kind != kind:
                continue
            rows = [r["tree"] for r in rows_by_case[i]]
            rows = [r for r in rows if r["gt"] is not None and r["confidence"] is not None
                    and r.get("disagreement") is not None]
            if rows:
                per_run.append((np.array([r["gt"] for r in rows]),
                                1 - np.array([r["confidence"] for r in rows]),
                                np.array([r["disagreement"] for r in rows])))
        if sum(len(g) for g, _, _ in per_run) < 10:
            print(f"  {kind:13s} too few subjects with both signs")
            continue
        gt, unsure, spread = (np.concatenate(x) for x in zip(*per_run, strict=True))
        worst = gt > np.percentile(gt, 80)
        cells = [f"{name} AUC {auc(score, worst):.2f} rho {spearman(score, gt):+.2f}"
                 for name, score in (("1-conf", unsure), ("disagr.", spread))]
        runs = [(g, u, d) for g, u, d in per_run if len(g) >= 8]
        if runs:
            for name, k in (("1-conf", 1), ("disagr.", 2)):
                a = np.nanmean([auc(r[k], r[0] > np.percentile(r[0], 80)) for r in runs])
                rho = np.nanmean([spearman(r[k], r[0]) for r in runs])
                cells.append(f"per run {name} {a:.2f} {rho:+.2f}")
        ratio = float(np.median(gt / np.maximum(spread, 1e-12)))
        print(f"  {kind:13s} n={len(gt):4d}  " + "  ".join(cells)
              + f"  GT/disagr. {ratio:.2f}")
    print("\ntree subjects attached as low-confidence leaves (counted as attached above):")
    for kind in kinds:
        rows = [r for i, c in enumerate(cases) if c.kind == kind for r in rows_by_case[i]]
        leaf = [r["tree"]["gt"] for r in rows if r["tree"]["leaf"] and r["tree"]["gt"] is not None]
        rest = [r["tree"]["gt"] for r in rows
                if not r["tree"]["leaf"] and r["tree"]["gt"] is not None]
        print(f"  {kind:13s} {len(leaf):3d} of {len(rows):3d}; mean GT error leaves "
              f"{f4(_mean(leaf))}, accepted subjects {f4(_mean(rest))}")
    print("\nwall time (s), summed over runs:")
    for kind in kinds:
        secs = {m: sum(c.seconds[m] for c in cases if c.kind == kind) for m in METHODS}
        print(f"  {kind:13s} " + "  ".join(f"{m} {secs[m]:7.1f}" for m in METHODS))
    tot = {m: sum(c.seconds[m] for c in cases) for m in METHODS}
    print(f"  {'ALL':13s} " + "  ".join(f"{m} {tot[m]:7.1f}" for m in METHODS))


# ----------------------------------------------------------------------------- main


def library_fingerprint() -> str:
    """A short hash of the library's source (every module of its subpackages, and the
    compiled E-step's C source), so runs of a changing library can be told apart."""
    import hashlib

    import registration

    root = Path(registration.__file__).parent
    h = hashlib.sha1()
    for f in sorted([*root.rglob("*.py"), *root.rglob("*.c")]):
        h.update(f.relative_to(root).as_posix().encode() + f.read_bytes())
    return h.hexdigest()[:12]


RUNNERS: dict[str, Callable[[list[np.ndarray], int], CollectionResult]] = {
    # DEFAULT options only: the benchmark judges the defaults
    "plain": lambda shapes, r: register_direct(shapes, root=r, prealign=False),
    "direct": lambda shapes, r: register_direct(shapes, root=r),
    "tree": lambda shapes, r: build_dynamic_tree(shapes, root=r),
}


def variant_summary(cases: list[Case], reports: list[dict[str, Any]],
                    rows_by_case: list[list[dict[str, Any]]], spec: str) -> None:
    """The tree with the options of ``--compare`` beside the default tree, same runs."""
    print(f"\nTREE VARIANT ({spec}) beside the default tree, both against plain CPD "
          "(penalised means, pooled; worst = largest per-run ratio over all subjects)")
    print(f"{'family':13s} {'runs':>4s} {'tree/pl all':>11s} {'far':>6s} {'worst':>6s} | "
          f"{'variant/pl all':>14s} {'far':>6s} {'worst':>6s}")
    kinds = list(dict.fromkeys(c.kind for c in cases))
    for kind in [*kinds, "ALL"]:
        idx = [i for i, c in enumerate(cases) if kind in (c.kind, "ALL")]
        rows = [r for i in idx for r in rows_by_case[i]]
        st_all = group_stats(rows)
        st_far = group_stats([r for r in rows if r["far"]])
        cols = []
        for m in ("tree", "variant"):
            worst = max(reports[i]["all"][f"{m}/plain"] for i in idx)
            cols.append(f"{f2(st_all[f'{m}/plain']):>11s} {f2(st_far[f'{m}/plain']):>6s} "
                        f"{f2(worst):>6s}")
        print(f"{kind:13s} {len(idx):4d} {cols[0]} | {cols[1]:>28s}")


def main() -> None:
    global METHODS, DATA, GLYPHS, CHUI
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="1 design, 1 seed, 1 Chui trial, root 0 only")
    ap.add_argument("--seeds", type=int, default=2, help="seeds per design (default 2)")
    ap.add_argument("--designs", default=None,
                    help="comma-separated glyph ids or row numbers of index.csv "
                    "(default: 3 spread over index.csv)")
    ap.add_argument("--trials", type=int, default=3,
                    help="Chui & Rangarajan trials per series (default 3)")
    ap.add_argument("--only", nargs="*", default=None,
                    help="family kinds to run (yong-edge yong-skel chui-fish chui-chinese "
                    "chui-noise chui-outlier chui-occlusion generated mpeg7 outline "
                    "outline-random outline-arc glyph-other dense-edge dense-skel small-step "
                    "one-type one-type-dense glyph-latin glyph-stroke; "
                    "glyph-turned, chui-rot and ink-spread run only when named)")
    ap.add_argument("--compare", default=None, metavar="KEY=VALUE,...",
                    help="also run the dynamic tree with these options (e.g. polish=False) "
                    "as method 'variant' and print it beside the default tree")
    ap.add_argument("--data", type=Path, default=None,
                    help=f"the shared data directory (default {DATA})")
    ap.add_argument("--characters", default=OTHER_CHARACTERS,
                    help="the glyph-other and dense families' characters (default "
                    f"{OTHER_CHARACTERS})")
    ap.add_argument("--fonts", default=",".join(OTHER_FONTS),
                    help="the glyph-other, dense and glyph-latin families' fonts, "
                    f"comma-separated, of {', '.join(FONTS)} (default "
                    f"{','.join(OTHER_FONTS)}; the DejaVu fonts draw Latin glyphs only)")
    ap.add_argument("--latin", default=LATIN_CHARACTERS,
                    help=f"the glyph-latin family's characters (default {LATIN_CHARACTERS})")
    ap.add_argument("--json", type=Path, default=None, help="dump every per-subject number")
    args = ap.parse_args()
    fonts = [f.strip() for f in args.fonts.split(",") if f.strip()]
    unknown = [f for f in fonts if f not in FONTS]
    if args.seeds < 1 or args.trials < 1:
        ap.error(f"--seeds and --trials take a count of at least 1; got --seeds {args.seeds} "
                 f"--trials {args.trials}")
    if unknown or not fonts or not args.characters or not args.latin:
        ap.error(f"--fonts takes names of {', '.join(FONTS)}, and --characters and --latin "
                 f"at least one character each; got --fonts {args.fonts!r} --characters "
                 f"{args.characters!r} --latin {args.latin!r}")
    seeds = list(range(1 if args.quick else args.seeds))
    trials = list(range(1 if args.quick else args.trials))
    mid_root = not args.quick
    if args.data is not None:
        DATA, GLYPHS, CHUI = args.data, args.data / "glyphs_yong", args.data / "chui_rangarajan"
    if args.compare:
        kw = {k.strip(): _literal(v) for k, v in
              (item.split("=", 1) for item in args.compare.split(",") if item.strip())}
        RUNNERS["variant"] = lambda shapes, r: build_dynamic_tree(shapes, root=r, **kw)
        METHODS = (*METHODS, "variant")

    cases: list[Case] = []
    if not DATA.is_dir():
        print(f"NOTE: {DATA} is missing: skipping the 永 glyph and Chui & Rangarajan families "
              "(the generated family still runs)")
    designs: list[str] = []
    if (GLYPHS / "index.csv").exists():
        designs = pick_designs(args.designs, 1 if args.quick else 3)
        print(f"永 designs: {', '.join(designs)}; seeds {seeds}")
        for kind in ("edge", "skel"):
            cases += glyph_cases(kind, designs, seeds, mid_root)
    elif DATA.is_dir():
        print(f"NOTE: {GLYPHS} is missing: skipping the 永 glyph families")
    if all((CHUI / f"{k}_def_{lvl}.npz").exists() for k in ("fish", "chinese")
           for lvl in range(1, 6)):
        for kind in ("fish", "chinese"):
            cases += chui_cases(kind, trials)
    elif DATA.is_dir():
        print(f"NOTE: {CHUI} lacks the def series: skipping the Chui & Rangarajan families")
    for series, levels in CHUI_SERIES.items():
        if series == "def" or (series == "rot" and not (args.only and "chui-rot" in args.only)):
            continue  # chui-rot only when named
        if all((CHUI / f"{k}_{series}_{lvl}.npz").exists() for k in ("fish", "chinese")
               for lvl in range(1, levels + 1)):
            for kind in ("fish", "chinese"):
                cases += chui_cases(kind, trials, series)
        elif DATA.is_dir():
            print(f"NOTE: {CHUI} lacks the {series} series: skipping chui-{series}")
    cases += generated_cases(seeds)
    if not args.quick or (args.only and {"mpeg7", *OUTLINE_SAMPLINGS} & set(args.only)):
        sources = outline_sources()
        for kind in ("mpeg7", *OUTLINE_SAMPLINGS):
            if sources[outline_source(kind)]:
                cases += outline_cases(kind, seeds[:1], sources)
            elif DATA.is_dir() and kind in ("mpeg7", "outline"):
                print(f"NOTE: no {kind} shapes under {DATA}: skipping that family")
    if not args.quick or (args.only and "glyph-other" in args.only):
        others = other_glyph_cases(seeds, args.characters,
                                   {f: FONTS[f] for f in fonts})
        if not others:
            print(f"NOTE: no font of {', '.join(fonts)} is installed with a glyph of "
                  f"{args.characters}: skipping the glyph-other family")
        cases += others
    if not args.quick or (args.only and {"dense-edge", "dense-skel"} & set(args.only)):
        cases += dense_glyph_cases(seeds[:1], args.characters,
                                   {f: FONTS[f] for f in fonts})
    if not args.quick or (args.only and "small-step" in args.only):
        cases += small_step_cases(designs, args.characters[:3],
                                  {f: FONTS[f] for f in fonts})
    if not args.quick or (args.only and "one-type" in args.only):
        cases += one_type_cases(designs, args.characters[:3], {f: FONTS[f] for f in fonts},
                                seeds)
    if not args.quick or (args.only and "one-type-dense" in args.only):
        cases += dense_one_type_cases(args.characters[:3], {f: FONTS[f] for f in fonts},
                                      seeds)
    if not args.quick or (args.only and "glyph-latin" in args.only):
        cases += latin_glyph_cases(seeds[:1], args.latin, {f: FONTS[f] for f in fonts})
    if not args.quick or (args.only and "glyph-stroke" in args.only):
        cases += stroke_glyph_cases(seeds[:2], STROKE_CHARACTERS, {f: FONTS[f] for f in fonts})
    if args.only and "glyph-turned" in args.only:  # only when named
        cases += turned_glyph_cases(seeds[:1], args.characters, {f: FONTS[f] for f in fonts})
    if args.only and "ink-spread" in args.only:  # only when named
        cases += ink_spread_cases(seeds, args.characters, {f: FONTS[f] for f in fonts})
    if args.only:
        cases = [c for c in cases if c.kind in args.only]
    print(f"{len(cases)} runs x 3 methods, default options (the library picks its executor); "
          f"library fingerprint {library_fingerprint()}")

    reports, rows_by_case = [], []
    for case in cases:
        for m in METHODS:
            t0 = time.perf_counter()
            case.results[m] = RUNNERS[m](case.shapes, case.root)
            case.seconds[m] = time.perf_counter() - t0
        rows = per_subject(case)
        rows_by_case.append(rows)
        reports.append(report_case(case, rows))
    summary(cases, reports, rows_by_case)
    if args.compare:
        variant_summary(cases, reports, rows_by_case, args.compare)

    if args.json is not None:
        doc = [{"family": c.kind, "label": c.label, "seed": c.seed, "root": c.root,
                "root_name": c.names[c.root], "far_from": c.far_from, "seconds": c.seconds,
                "tree_thresholds": c.results["tree"].thresholds, "report": rep,
                "subjects": rows}
               for c, rep, rows in zip(cases, reports, rows_by_case, strict=True)]
        args.json.write_text(json.dumps(_clean(doc), indent=1, allow_nan=False))
        print(f"\nper-subject numbers written to {args.json}")


def _literal(text: str) -> Any:
    """An option value of ``--compare``: a Python literal (True, 3, 0.5) or a string."""
    import ast

    try:
        return ast.literal_eval(text.strip())
    except (ValueError, SyntaxError):
        return text.strip()


def _clean(o: Any) -> Any:
    """JSON-ready: numpy scalars and arrays to Python, NaN and infinity to None."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, float | np.floating):
        return float(o) if math.isfinite(o) else None
    return o


if __name__ == "__main__":
    main()

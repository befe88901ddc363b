"""Coarse to fine (`working_points`): the tree decided on subsampled shapes, its results at
the stored resolution."""

import json

import numpy as np
import pytest

from registration import (
    CPDOptions,
    SerialExecutor,
    build_dynamic_tree,
    build_static_tree,
    register_direct,
    registration_error,
)
from registration._points import normalise
from registration._tree import _polish, _resolution
from registration._tree._resolution import (
    DEFAULT_WORKING_POINTS,
    _edge_from_polished_parent,
    farthest_point_indices,
)
from registration.synthetic import (
    base_outline,
    chained_family,
    correspondence_error,
    deformation_chains,
)

FAST_CPD = CPDOptions(max_iter=60)
WORKING = 60


@pytest.fixture(scope="module")
def family():
    # 240 points a shape, decided at 60: every shape is subsampled
    return deformation_chains(base_outline(1500), n_chains=2, chain_length=3, n_points=240,
                              seed=0)


@pytest.fixture(scope="module")
def runs(family):
    kw = {"cpd": FAST_CPD, "executor": SerialExecutor(), "names": family.names}
    events: list[tuple[str, int, int]] = []
    with pytest.MonkeyPatch.context() as mp:
        # the stored stage alone (each coarse edge replayed), without the polish there,
        # whose edges registered again from the parent replace most of those chains
        mp.setattr(_resolution, "_polish_stored", _without_stored_polish)
        replay = build_dynamic_tree(family.shapes, 0, working_points=WORKING, **kw)
    return {
        "c2f": build_dynamic_tree(family.shapes, 0, working_points=WORKING,
                                  compare_direct=True, **kw,
                                  progress=lambda *e: events.append(e)),
        "full": build_dynamic_tree(family.shapes, 0, working_points=None, **kw),
        "c2f events": events,
        "replay": replay,
    }


def _without_stored_polish(full, subjects, *args):
    return subjects


def _check_stored_resolution(res, family):
    n_root = len(family.shapes[0])
    root_pts = family.shapes[0]
    for s in [*res.subjects, *(res.direct or [])]:
        assert s.attached
        y = family.shapes[s.index]
        assert s.warped.shape == (n_root, 2)
        assert s.correspondence.shape == (n_root,) and s.probability.shape == (n_root,)
        assert 0 <= s.correspondence.min() and s.correspondence.max() < len(y)
        # indices into the full subject, not into its 60-point subsample
        assert s.correspondence.max() >= WORKING
        # e is that of the stored shapes
        yn, norm = normalise(y)
        assert s.error == pytest.approx(registration_error(norm.apply(s.warped), yn), rel=1e-9)
        # the transform reproduces the warped model from the full root
        np.testing.assert_allclose(s.transform.apply(root_pts), s.warped, atol=1e-8 * norm.scale)
        assert s.transform.path[0] == 0 and s.transform.path[-1] == s.index
        assert s.quality["working_error"] > 0 and 0 <= s.confidence <= 1
        assert np.isfinite(s.quality["stored_min_jacobian"])


def _stored_polish(s):
    """What the polish at the stored resolution recorded for `s` ({} when it kept nothing)."""
    return (s.quality or {}).get("stored_polish") or {}


def _polished_again_from_parent(s):
    """Whether the stored polish registered `s`'s edge again from its parent as polished
    there (its chain then extends the parent's whole chain)."""
    return bool((_stored_polish(s).get("from_parent") or {}).get("kept"))


def _before_stored_polish(s):
    """`s`'s chain as the stored-resolution CPD left it (not for a subject
    :func:`_polished_again_from_parent`): without the stored polish's steps."""
    assert not _polished_again_from_parent(s)
    steps = s.transform.steps
    return steps[:len(steps) - _stored_polish(s).get("steps", 0)]


def test_results_are_at_the_stored_resolution(runs, family):
    res = runs["c2f"]
    assert res.options["working_points"] == WORKING
    _check_stored_resolution(res, family)
    json.dumps(res.to_dict())
    # each stored polish that took the edge again from the parent as polished there: the
    # chain extends the parent's whole chain (the root's: no steps), but for the parent's
    # step towards plain CPD, taken once every subject was polished
    again = [s for s in res.subjects if _polished_again_from_parent(s)]
    assert again
    for s in again:
        if s.parent != 0:
            parent = res.subject(s.parent)
            along = bool((_stored_polish(parent).get("along_plain") or {}).get("kept"))
            assert (s.transform.shared_steps(parent.transform)
                    == len(parent.transform.steps) - along)


def test_the_stored_stage_replays_each_coarse_edge(runs, family):
    """Without the polish there, one stored-resolution CPD per subject, after its
    parent's chain as built: the edge (its coarse steps), a polished subject's coarse
    polish steps, then the stored resolution's."""
    res = runs["replay"]
    _check_stored_resolution(res, family)
    n_root = len(family.shapes[0])
    assert any((s.quality or {}).get("polish") for s in res.subjects), \
        "nothing polished: the family is too shallow to test the polish here"
    assert not any(_stored_polish(s) for s in res.subjects)
    for s in res.subjects:
        parent_res = res.subject(s.parent) if s.parent else None
        parent = () if parent_res is None else parent_res.transform.steps
        steps = s.transform.steps
        # the parent's chain as its children were built on it: without its polish and
        # the stored-resolution step that follows it
        parent_polish = (parent_res.quality or {}).get("polish") if parent_res else None
        shared = len(parent) - (parent_polish["steps"] + 1 if parent_polish else 0)
        assert steps[:shared] == parent[:shared]
        assert len(steps[-1].control_points) == n_root  # the stored-resolution CPD
        # then a polished parent's own stored-resolution step of its edge (its children's
        # start), at least the edge's CPD, the polish's stages and the stored resolution's
        polish = (s.quality or {}).get("polish")
        assert len(steps) >= (shared + (1 if parent_polish else 0) + 2
                              + (polish.get("steps", 1) if polish else 0))


def test_the_tree_is_polished_again_at_the_stored_resolution(runs, family):
    """After its stored-resolution CPD each tree subject is polished again on the stored
    points (the polish's stages, its edge from the parent as polished there, the finish
    and the symmetric finish): recorded in ``quality["stored_polish"]`` as the working
    resolution's in ``quality["polish"]``, and its chain without those steps is where the
    stored CPD left the model. Direct CPD's registrations are not polished there."""
    res = runs["c2f"]
    polished = [s for s in res.subjects if _stored_polish(s)]
    assert polished
    for s in polished:
        info = _stored_polish(s)
        assert "polished again at the stored resolution" in s.reason
        assert info["error_before"] > 0 and info["steps"] >= 1
        assert info["error"] == s.error  # the e reached on the stored points
        assert "finish" in info and "symmetric" in info  # tried, kept or not
        assert "consensus" not in info  # no partner at the stored resolution
        if _polished_again_from_parent(s):
            continue
        chain = type(s.transform)(source=s.transform.source, target=s.transform.target,
                                  steps=_before_stored_polish(s), path=s.transform.path)
        yn, norm = normalise(family.shapes[s.index])
        e = registration_error(norm.apply(chain.apply(family.shapes[0])), yn)
        assert e == pytest.approx(info["error_before"], rel=1e-9)
    for s in res.direct or []:
        assert "stored_polish" not in (s.quality or {})


def test_without_the_polish_nothing_is_polished_at_the_stored_resolution(family):
    res = build_dynamic_tree(family.shapes, 0, working_points=WORKING, cpd=FAST_CPD,
                             executor=SerialExecutor(), polish=False)
    _check_stored_resolution(res, family)
    assert not any("stored_polish" in (s.quality or {}) or "polish" in (s.quality or {})
                   for s in res.subjects)


def test_static_tree_and_direct_are_not_polished(family):
    kw = {"cpd": FAST_CPD, "executor": SerialExecutor(), "working_points": WORKING}
    for fn in (build_static_tree, register_direct):
        res = fn(family.shapes, 0, **kw)
        assert not any("stored_polish" in (s.quality or {}) for s in res.subjects)


def test_stored_resolution_stages_count_subjects(runs):
    """``full resolution`` counts the tree's attached subjects (a polished one once, its
    edge and polish step in one task), ``polish full resolution`` those the working
    resolution polished (a single edge whose polish it did not keep is not polished
    again) and ``direct full resolution`` direct's, each from 0 up to its total, after
    every stage decided at the working resolution."""
    res, events = runs["c2f"], runs["c2f events"]
    assert any((s.quality or {}).get("polish") for s in res.subjects)
    stages = list(dict.fromkeys(stage for stage, _, _ in events))
    assert stages[-3:] == ["full resolution", "polish full resolution",
                           "direct full resolution"]
    for stage, results in (("full resolution", res.subjects),
                           ("polish full resolution", res.subjects),
                           ("direct full resolution", res.direct)):
        seen = [(d, t) for s, d, t in events if s == stage]
        attached = sum(1 for s in results if s.attached and not (
            stage == "polish full resolution" and "polish_not_kept" in (s.quality or {})))
        assert {t for _, t in seen} == {attached}
        assert [d for d, _ in seen] == sorted(d for d, _ in seen)
        assert seen[0][0] == 0 and seen[-1][0] == attached


def test_coarse_to_fine_matches_a_full_resolution_run(runs, family):
    c2f, full = runs["c2f"], runs["full"]
    assert full.options["working_points"] is None
    e_c = np.array([s.error for s in c2f.subjects])
    e_f = np.array([s.error for s in full.subjects])
    assert e_c.mean() <= 1.3 * e_f.mean()

    truth = family.root_images(0)

    def gt(res):
        return np.mean([correspondence_error(s.warped, truth[s.index], family.shapes[s.index])
                        for s in res.subjects])

    # measured 0.0513 (coarse to fine) vs 0.0321 (full resolution) here, 1.60x (with the
    # uniform mixture 0.0526 vs 0.0363, 1.45x: the full-resolution tree's random 240-point
    # samples take the sampling weights, the coarse decisions' even 60 do not): this
    # family (random 240-point samples decided at 60, 60 EM iterations) is the one place
    # where session 36's polish at the stored resolution lost (0.0404 with the stored
    # finishes alone, 0.0432 with the polish but its edges again only under a moved
    # parent); over seeds 0-3 the ratio runs 0.98-1.60 (uniform 0.88-1.45), the means
    # 0.0646 and 0.0549 (uniform 0.0632 and 0.0539; 0.0525 with the stored finishes). At
    # 1200 points a shape it gains on every family measured (bench/RESULTS.md 7.31). The
    # loss is this family's 4x coarser decisions: decided at 80 (3x, the default's 1200
    # -> 400) the same seeds give 0.0536 against 0.0535, evenly sampled at 60 0.0257
    # against 0.0284, 720 points decided at 240 0.0366 against 0.0368 (default CPD
    # options, uniform mixture; bench/RESULTS.md 7.32, 7.33)
    assert gt(c2f) <= 1.7 * gt(full)


def test_stored_resolution_fits_its_field_with_control_points(monkeypatch, runs, family):
    """Above ``FINE_CONTROL_POINTS`` (here 120 of 240) each stored-resolution CPD fits its
    field with the root's farthest-point subsample and moves every stored point: the
    results are as complete as with every point, and as close to the truth."""
    monkeypatch.setattr(_resolution, "FINE_CONTROL_POINTS", 120)
    res = build_dynamic_tree(family.shapes, 0, working_points=WORKING, cpd=FAST_CPD,
                             executor=SerialExecutor(), names=family.names)
    _check_stored_resolution(res, family)
    for s in res.subjects:
        assert len(s.transform.steps[-1].control_points) == 120  # the stored-resolution CPD
    truth = family.root_images(0)

    def gt(r):
        return np.mean([correspondence_error(s.warped, truth[s.index], family.shapes[s.index])
                        for s in r.subjects])

    # measured 0.0417 against 0.0526 here (0.79x); over seeds 0-3 of this family 0.76x
    # to 1.07x (session 35, before the polish at the stored resolution: 0.84x to 1.05x).
    # Decided at 80 points instead of 60, 0.0534 against 0.0380 (1.40x): the stored
    # polish's CPDs lose with fewer centroids (default 500 on the 永 glyphs: 1.07x the
    # every-point error, bench/RESULTS.md 7.32)
    assert gt(res) <= 1.15 * gt(runs["c2f"])


def test_control_points_are_never_fewer_than_the_working_points(monkeypatch, family):
    monkeypatch.setattr(_resolution, "FINE_CONTROL_POINTS", 50)
    monkeypatch.setattr(_resolution, "POLISH_STAGE_CONTROL_POINTS", 50)
    res = build_dynamic_tree(family.shapes, 0, working_points=WORKING, cpd=FAST_CPD,
                             executor=SerialExecutor())
    assert {len(s.transform.steps[-1].control_points) for s in res.subjects} == {WORKING}


def test_the_stored_polish_stages_fit_their_own_control_points(monkeypatch, family):
    """The polish's stages at the stored resolution fit their fields with
    ``POLISH_STAGE_CONTROL_POINTS`` of the root's points, its other CPDs with
    ``FINE_CONTROL_POINTS``; the working resolution's stages with every point."""
    monkeypatch.setattr(_resolution, "FINE_CONTROL_POINTS", 60)
    monkeypatch.setattr(_resolution, "POLISH_STAGE_CONTROL_POINTS", 120)
    stages: list[int | None] = []
    stages_of = _polish._stages

    def spy(*args, **kwargs):
        control = args[7] if len(args) > 7 else kwargs.get("control")
        stages.append(None if control is None else len(control))
        return stages_of(*args, **kwargs)

    monkeypatch.setattr(_polish, "_stages", spy)
    res = build_dynamic_tree(family.shapes, 0, working_points=WORKING, cpd=FAST_CPD,
                             executor=SerialExecutor())
    assert set(stages) == {None, 120}
    # the polish's steps and its other CPDs keep the stored stage's 60
    assert {len(s.transform.steps[-1].control_points) for s in res.subjects} <= {60, 120}


def test_static_tree_and_direct_are_at_the_stored_resolution(family):
    kw = {"cpd": FAST_CPD, "executor": SerialExecutor(), "working_points": WORKING}
    for fn in (build_static_tree, register_direct):
        res = fn(family.shapes, 0, **kw)
        assert res.options["working_points"] == WORKING
        _check_stored_resolution(res, family)


def test_small_shapes_are_not_touched():
    fam = chained_family(n_chains=1, chain_length=3, n_points=80, seed=2)
    kw = {"cpd": FAST_CPD, "executor": SerialExecutor()}
    a = build_dynamic_tree(fam.shapes, 0, **kw)  # default working_points: 400 > 80
    b = build_dynamic_tree(fam.shapes, 0, working_points=None, **kw)
    c = build_dynamic_tree(fam.shapes, 0, working_points=0, **kw)
    assert a.options["working_points"] == DEFAULT_WORKING_POINTS
    assert c.options["working_points"] is None
    for sa, sb, sc in zip(a.subjects, b.subjects, c.subjects, strict=True):
        assert sa.error == sb.error == sc.error
        np.testing.assert_array_equal(sa.warped, sb.warped)
        np.testing.assert_array_equal(sa.correspondence, sb.correspondence)
        assert "working_error" not in sa.quality


def test_a_mix_of_small_and_large_shapes(family):
    shapes = list(family.shapes[:4])
    shapes[2] = shapes[2][::5]  # 48 points: below the working resolution, used as is
    res = register_direct(shapes, 0, cpd=FAST_CPD, executor=SerialExecutor(),
                          working_points=WORKING)
    s = res.subject(2)
    assert s.warped.shape == (len(shapes[0]), 2) and s.correspondence.max() < 48


@pytest.mark.parametrize("bad", [-1, 5, 2.5, True, "400"])
def test_bad_working_points_raise(family, bad):
    with pytest.raises(ValueError, match="working_points"):
        register_direct(family.shapes[:3], 0, working_points=bad)


def test_farthest_point_subsample_is_deterministic_and_even():
    rng = np.random.default_rng(0)
    # a dense cluster and a sparse line: the subsample covers both
    pts = np.concatenate([rng.normal(0, 0.01, size=(900, 2)),
                          np.column_stack([np.linspace(1, 2, 100), np.zeros(100)])])
    idx = farthest_point_indices(pts, 50)
    assert len(idx) == 50 and len(np.unique(idx)) == 50 and np.all(np.diff(idx) > 0)
    np.testing.assert_array_equal(idx, farthest_point_indices(pts, 50))
    assert np.sum(idx >= 900) > 25  # most of it on the line, not in the cluster
    # without ties (random points) the choice does not depend on the order of the points
    scatter = rng.uniform(size=(500, 2))
    perm = rng.permutation(len(scatter))
    assert set(perm[farthest_point_indices(scatter[perm], 50)]) == set(
        farthest_point_indices(scatter, 50))
    np.testing.assert_array_equal(farthest_point_indices(pts[:10], 50), np.arange(10))


@pytest.mark.parametrize("from_parent_min_layer", [3, 99])
def test_children_of_a_polished_subject_start_from_its_registration_as_built(
        from_parent_min_layer, monkeypatch):
    """A polished subject's children were built, at the working resolution, on its chained
    registration, not on the polished one, unless the polish registered a child's edge
    again from the polished parent. At the stored resolution the first start from the
    parent's edge's own stored-resolution CPD (one more task for such a parent), so a
    polish that lowers e but moves correspondences the wrong way stays with that subject;
    the second from the parent's final stored-resolution registration, its whole chain.
    (The stored stage alone: the polish there registers every edge again.)"""
    from registration._tree import _polish

    # 99: no edge registered again from a polished parent (every child built on the chain)
    monkeypatch.setattr(_polish, "POLISH_FROM_PARENT_MIN_LAYER", from_parent_min_layer)
    monkeypatch.setattr(_resolution, "_polish_stored", _without_stored_polish)
    fam = deformation_chains(base_outline(1500), n_chains=2, chain_length=4, n_points=240,
                             seed=0, step=0.3)
    events: list[tuple[str, int, int]] = []
    res = build_dynamic_tree(fam.shapes, 0, working_points=WORKING, cpd=FAST_CPD,
                             executor=SerialExecutor(), progress=lambda *e: events.append(e))
    _check_stored_resolution(res, fam)
    n_root = len(fam.shapes[0])
    polished_parents = [s for s in res.subjects if (s.quality or {}).get("polish")
                        and any(c.parent == s.index for c in res.subjects)]
    assert polished_parents, "no polished subject with children: pick another family"
    kinds = set()
    for p in polished_parents:
        final = p.transform.steps
        built = final[:len(final) - p.quality["polish"]["steps"] - 1]
        for c in (c for c in res.subjects if c.parent == p.index):
            steps = c.transform.steps
            if _edge_from_polished_parent(c):
                kinds.add("final")
                assert steps[:len(final)] == final
                continue
            kinds.add("built")
            assert steps[:len(built)] == built
            # then the parent's own stored-resolution step of its edge, not its polish
            step = steps[len(built)]
            assert len(step.control_points) == n_root
            assert step is not final[-1]
    assert kinds == ({"built"} if from_parent_min_layer == 99 else {"final"}), kinds
    counts = [(d, t) for s, d, t in events if s == "full resolution"]
    attached = sum(1 for s in res.subjects if s.attached)
    assert counts[-1] == (attached, attached)
    assert [d for d, _ in counts] == sorted(d for d, _ in counts)


def test_the_stored_polish_records_the_e_of_the_stored_points(monkeypatch, family):
    """The quality checks measure shapes above ``QUALITY_POINTS`` on subsamples; the
    stored polish's record still gives the e the subject's registration reached."""
    from registration import _quality

    monkeypatch.setattr(_quality, "QUALITY_POINTS", 100)  # below the family's 240 points
    res = build_dynamic_tree(family.shapes, 0, working_points=WORKING, cpd=FAST_CPD,
                             executor=SerialExecutor())
    polished = [s for s in res.subjects if _stored_polish(s)]
    assert polished
    for s in polished:
        assert _stored_polish(s)["error"] == s.error

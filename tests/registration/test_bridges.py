"""The automatic similarity rule reaches every subject from the root (issue 9 item 3).

A collection of tight groups (an archive with several impressions of each design) has a
4-nearest graph that falls apart into its groups; the rule then bridges the groups with
the subjects' bottleneck D from the root, and leaves a connected collection unchanged.
"""

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order

import registration._tree._rules as rules
from registration import CPDOptions, SerialExecutor, build_dynamic_tree, build_static_tree
from registration._pose import PoseSpec
from registration._tree._collection import _Collection, _TreeStart
from registration.synthetic import chained_family

FAST_CPD = CPDOptions(max_iter=60)


def clustered(groups: int, copies: int, n_points: int, seed: int) -> list[np.ndarray]:
    """`groups` designs one deformation step apart along a chain, each printed `copies`
    times: near-identical copies (jitter 0.3% of the size, a slight turn), so every
    shape's 4 nearest are copies of its own design. Design-major order: shape 0 is a
    copy of the first design."""
    fam = chained_family(n_chains=1, chain_length=groups - 1, n_points=n_points, step=0.3,
                         pose=False, seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for centre in fam.shapes:
        size = float(np.sqrt(np.mean((centre - centre.mean(0)) ** 2)))
        for _ in range(copies):
            a = np.deg2rad(rng.uniform(-3.0, 3.0))
            rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            out.append(centre @ rot.T + 0.003 * size * rng.normal(size=centre.shape))
    return out


@pytest.fixture
def no_bridges(monkeypatch):
    """The rule as it was before the bridges."""
    monkeypatch.setattr(rules, "_bridge_limits", lambda *a, **k: {})


def _reached(start: _TreeStart) -> set[int]:
    n = start.coll.n
    adj = np.zeros((n, n), dtype=bool)
    for s in range(n):
        # the pairs the tree may use: all, or the allowed candidates (root's row included)
        members = range(n) if start.sources is None else start.sources.get(s, [])
        for m in members:
            if m != s and start.rule.similar(start.sim, m, s):
                adj[m, s] = True
    order = breadth_first_order(csr_matrix(adj), start.coll.root, directed=True,
                                return_predecessors=False)
    return {int(k) for k in order}


def _start(shapes):
    coll = _Collection.prepare(shapes, 0, None)
    return _TreeStart.prepare(coll, None, None, PoseSpec.resolve(None, None), SerialExecutor(),
                              None)


def test_tight_groups_are_bridged_and_attached_in_the_tree():
    shapes = clustered(groups=5, copies=6, n_points=40, seed=3)
    kw = dict(cpd=FAST_CPD, executor=SerialExecutor(), refine=False, polish=False)
    after = build_dynamic_tree(shapes, 0, **kw)
    in_tree = [s for s in after.subjects if s.parent is not None and not s.leaf]
    assert after.thresholds["bridged"] > 0
    assert "bridged" in after.thresholds["similarity_rule"]
    assert len(in_tree) == len(shapes) - 1
    # the bridges open the nearest pairs between designs, not everything: most edges
    # still join two copies of the same design
    same = sum(1 for s in in_tree if s.parent // 6 == s.index // 6)
    assert same >= len(in_tree) // 2
    static = build_static_tree(shapes, 0, cpd=FAST_CPD, executor=SerialExecutor())
    assert all(s.parent is not None for s in static.subjects)


def test_a_bridged_tree_gives_every_subject_its_depth_as_layer(monkeypatch):
    # after a stall the tree grows from every member, not only the last round's: a subject
    # that joins in a late round from a shallow member sits one layer below that member
    # (before, it took the round's number: layer 22 under a layer-2 parent, 40 glyph images)
    import registration._tree._methods as methods

    shapes = clustered(groups=4, copies=5, n_points=30, seed=3)
    late = 3  # a copy of the root's design, refused until the fifth round of growth
    rounds: list[str] = []
    run_tasks, rejection = methods._run_tasks, methods._rejection

    def counting(tasks, executor, progress, stage):
        rounds.append(stage)
        return run_tasks(tasks, executor, progress, stage)

    def refusing(out, *args, **kwargs):
        if out.subject == late and len(rounds) < 4:
            return "refused by the test"
        return rejection(out, *args, **kwargs)

    monkeypatch.setattr(methods, "_run_tasks", counting)
    monkeypatch.setattr(methods, "_rejection", refusing)
    reported: list[str] = []
    res = build_dynamic_tree(shapes, 0, cpd=FAST_CPD, executor=SerialExecutor(),
                             polish=False, refine=False,
                             progress=lambda stage, done, total: reported.append(stage))
    layers = {0: 1} | {s.index: s.layer for s in res.subjects}
    attached = [s for s in res.subjects if s.parent is not None]
    assert len(attached) == len(shapes) - 1
    s_late = res.subject(late)
    joined = next(a for a in s_late.attempts if a.accepted)
    assert not s_late.leaf and rounds.index("round 4") >= 3, (s_late, rounds)
    for s in attached:
        assert s.layer == len(s.path) == layers[s.parent] + 1, (s.index, s.layer, s.path)
        accepted = [a for a in s.attempts if a.accepted]
        assert [(a.member, a.layer) for a in accepted] == [(s.parent, s.layer)]
    # it joined in round 5 or later, from a member less than four layers deep
    assert joined.layer == s_late.layer < 5, s_late
    assert f"(layer {layers[s_late.parent]})" in (s_late.reason or "")
    # progress names the rounds of growth (s_late joined in round 4 or later, at layer 4
    # or above), not layers
    grown = [s for s in dict.fromkeys(reported) if "round" in s or "layer" in s]
    assert grown == [f"round {k}" for k in range(1, len(grown) + 1)] == rounds, grown


def test_without_bridges_the_same_groups_stay_outside_the_tree(no_bridges):
    shapes = clustered(groups=5, copies=6, n_points=40, seed=3)
    start = _start(shapes)
    assert start.rule.bridged == {}
    assert len(_reached(start)) <= 6  # the root's own design
    before = build_dynamic_tree(shapes, 0, cpd=FAST_CPD, executor=SerialExecutor(),
                                refine=False, polish=False)
    in_tree = [s for s in before.subjects if s.parent is not None and not s.leaf]
    assert len(in_tree) <= 5
    assert before.thresholds["bridged"] == 0


def test_every_subject_is_reachable_with_pruned_candidates():
    # > 64 shapes: D is only computed for the descriptor's candidate pairs (and the root's
    # row); the bridges use those pairs alone
    shapes = clustered(groups=14, copies=5, n_points=30, seed=5)
    start = _start(shapes)
    assert start.allowed is not None
    assert start.rule.bridged
    assert _reached(start) == set(range(len(shapes)))
    for s, limit in start.rule.bridged.items():
        assert start.rule.into[s] == limit
        assert np.isfinite(limit) and limit > 0


def test_a_connected_family_gets_exactly_the_result_it_had(monkeypatch):
    fam = chained_family(n_chains=2, chain_length=4, n_points=60, step=0.3, seed=2)
    kw = dict(names=fam.names, cpd=FAST_CPD, executor=SerialExecutor())
    after = build_dynamic_tree(fam.shapes, 0, **kw)
    assert after.thresholds["bridged"] == 0
    monkeypatch.setattr(rules, "_bridge_limits", lambda *a, **k: {})
    before = build_dynamic_tree(fam.shapes, 0, **kw)
    a, b = after.to_dict(), before.to_dict()
    a["thresholds"].pop("similarity_rule"), b["thresholds"].pop("similarity_rule")
    assert a == b


def test_an_explicit_threshold_is_never_bridged():
    shapes = clustered(groups=3, copies=5, n_points=30, seed=1)
    coll = _Collection.prepare(shapes, 0, None)
    start = _TreeStart.prepare(coll, 1e-6, None, PoseSpec.resolve(None, None), SerialExecutor(),
                               None)
    assert start.rule.bridged == {}
    assert "bridged" not in rules._similarity_report(start.rule)


def test_a_stalled_tree_opens_the_next_nearest_bridges():
    # the pairs into the other designs were tried and rejected: the rule opens the
    # nearest untried pairs from the tree's members, until none are left
    shapes = clustered(groups=3, copies=5, n_points=30, seed=1)
    start = _start(shapes)
    rule, sim = start.rule, start.sim
    members, waiting = set(range(5)), set(range(5, 15))
    tried: set[tuple[int, int]] = set()
    raised = 0
    while True:
        opened = {(m, s) for m in members for s in waiting
                  if (m, s) not in tried and rule.similar(sim, m, s)}
        if opened:
            untried = [sim.D[m, s] for m in members for s in waiting
                       if (m, s) not in tried and (m, s) not in opened]
            # the nearest untried pair is among those opened
            assert not untried or min(sim.D[p] for p in opened) <= min(untried)
            tried |= opened
        elif rule.bridge(sim, members, waiting, tried):
            raised += 1
        else:
            break
    assert raised >= 1
    assert tried == {(m, s) for m in members for s in waiting}


def test_bridging_stops_at_its_budget(monkeypatch):
    # the copies of the root's design attach; every registration into another design is
    # refused (an error threshold between the two): the stalled tree bridges again and
    # again, but only while it has run fewer than the budget's registrations
    import registration._tree._methods as methods

    shapes = clustered(groups=3, copies=5, n_points=30, seed=2)
    counted: list[int] = []
    run_tasks = methods._run_tasks

    def counting(tasks, *args, **kwargs):
        counted.append(len(tasks))
        return run_tasks(tasks, *args, **kwargs)

    monkeypatch.setattr(methods, "_run_tasks", counting)

    def runs(budget: int) -> int:
        monkeypatch.setattr(methods, "BRIDGE_TASKS_PER_SUBJECT", budget)
        counted.clear()
        res = build_dynamic_tree(shapes, 0, cpd=FAST_CPD, error_threshold=1e-4,
                                 polish=False, refine=False, executor=SerialExecutor())
        in_tree = {s.index for s in res.subjects if s.layer is not None and not s.leaf}
        assert in_tree == {1, 2, 3, 4}, in_tree  # the root's own design only
        return sum(counted)

    subjects = len(shapes) - 1
    small, large = runs(1), runs(100)
    assert small < large  # measured 14 vs 54 (every pair into the other designs tried)
    # the budget is checked between layers: one layer's registrations may overrun it
    assert small <= 1 * subjects + subjects * 3

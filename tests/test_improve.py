"""Shortcuts (`planning.improve.shortcut`): stretches of a solved path replaced by one
extremal each, the rest of the path re-attached (`interior_shortcuts`), and its tail by one
extremal to the goal (`goal_shortcuts`), added to the same tree as new leaves; the tree
stays a tree whose every edge re-simulates, the cost only falls, and the same plan gives the
same result."""

from __future__ import annotations

import numpy as np
import pytest
from tests.swingup import (
    assert_grown_by_leaves,
    assert_path_resimulates,
    first_solution,
    swingup_planner,
    tree_edges,
    tree_snapshot,
)

from rrtcolearn.evaluate import edge_trajectory, resimulate
from rrtcolearn.planning.improve import shortcut
from rrtcolearn.planning.termination import TerminationCondition


@pytest.mark.parametrize("u_max", [None, 2.0])
def test_the_tree_stays_a_tree_of_exact_edges(paper_model, u_max):
    planner = swingup_planner(paper_model, u_max)
    p = first_solution(planner, 3)
    first_cost, first_nodes = p.path_cost, p.tree.n_nodes
    q = shortcut(planner, p)
    t = q.tree
    assert q.solved and q.extra["shortcuts"]["added"] >= 1
    assert q.path_cost < first_cost
    # only leaves were added, below earlier nodes: every node reaches the root
    assert t.n_nodes == first_nodes + q.extra["shortcuts"]["added"] + \
        q.extra["interior"]["added"] + q.extra["pieces"]["added"] + q.extra["pieces"]["pieces"]
    assert t.parents[0] == -1 and all(t.parents[k] < k for k in range(1, t.n_nodes))
    assert q.path_nodes == t.path_to(q.path_nodes[-1])
    # every edge of the tree re-simulates from its parent to its node at its cost
    w, dt = q.time_weight, q.dt
    for e in tree_edges(q):
        r = edge_trajectory(paper_model.system, e, w, dt)
        assert np.abs(r.states[-1] - e["to"]).max() < 1e-9
        assert r.cost == pytest.approx(e["cost"], rel=1e-9, abs=1e-12)
    # costs to come: the path's cost is the sum of its edges', as re-simulated
    r = resimulate(paper_model.system, q)
    assert r["path_cost"] == pytest.approx(q.path_cost, rel=1e-9)
    assert q.final_goal_distance <= 0.1
    if u_max is not None:
        assert r["max_abs_u"] <= u_max + 1e-12 and q.max_abs_u <= u_max


def test_never_dearer_and_deterministic(paper_model):
    planner = swingup_planner(paper_model)
    for seed in (1, 4):
        a = shortcut(planner, first_solution(planner, seed))
        b = shortcut(planner, first_solution(planner, seed))
        assert a.to_dict()["path"] == b.to_dict()["path"]
        assert a.path_cost <= first_solution(planner, seed).path_cost


def test_an_unsolved_plan_is_returned_as_it_is(paper_model):
    planner = swingup_planner(paper_model)
    p = planner.solve(TerminationCondition(None, 3), 0)
    assert not p.solved and shortcut(planner, p) is p


def test_stop_is_obeyed(paper_model):
    planner = swingup_planner(paper_model)
    p = first_solution(planner, 3)
    cost, nodes = p.path_cost, p.tree.n_nodes
    q = shortcut(planner, p, stop=lambda: True)
    assert q.path_cost == cost and q.tree.n_nodes == nodes


def test_shortcuts_keep_clear_of_obstacles(paper_model):
    """A tail that would cross an obstacle is cut there and rejected: the shortcut path
    re-simulated from the start stays free, within the limits, and reaches the goal."""
    from rrtcolearn.evaluate import replay

    block = {"type": "box", "low": [-2.0, 0.3], "high": [-1.2, 2.5]}
    planner = swingup_planner(paper_model, obstacles=[block])
    problem = planner.problem
    cheaper = 0
    for seed in range(3):
        p = first_solution(planner, seed)
        first = p.path_cost
        q = shortcut(planner, p)
        r = replay(problem, q)
        assert r["valid"] and r["reaches_goal"] and q.path_cost <= first
        cheaper += q.path_cost < first
    assert cheaper  # the shortcuts did act, around the obstacle


# interior shortcuts (`planning.improve.interior_shortcuts`): seeds whose first paths the
# paper model's shortcuts make cheaper, and where the rest of the path is re-attached
INTERIOR_CASES = [(None, 4), (2.0, 3)]


@pytest.mark.parametrize(("u_max", "seed"), INTERIOR_CASES)
def test_interior_shortcut_resimulates_independently(paper_model, u_max, seed):
    """The improved path, re-simulated edge by edge by a plain RK4 of the pendulum's own
    equations (tests/conftest.py: no code shared with the planner) from the start, joins,
    ends where each edge says at the cost it says, keeps the input limit and ends in the
    goal ball; `check_plan` agrees."""
    from rrtcolearn.evaluate import check_plan
    from rrtcolearn.planning.improve import interior_shortcuts

    planner = swingup_planner(paper_model, u_max)
    p = first_solution(planner, seed)
    first = p.path_cost
    q = interior_shortcuts(planner, p)
    rec = q.extra["interior"]
    assert rec["kept"] >= 1 and q.path_cost < first
    # the rest of the path was re-attached behind a shortcut: more new nodes than shortcuts
    assert rec["added"] > rec["kept"]
    assert_path_resimulates(q, u_max)
    r = check_plan(paper_model.system, q, goal_fn=planner.problem.goal_distance)
    assert r["path_cost"] == pytest.approx(q.path_cost, rel=1e-9)
    assert "shooting" in q.duration_by


@pytest.mark.parametrize(("u_max", "seed"), INTERIOR_CASES)
def test_interior_shortcuts_keep_the_tree(paper_model, u_max, seed):
    """Only leaves are added: the nodes the solve made keep their states, parents and costs,
    and every node's cost to come is the sum of its path's edge costs (the path's end: the
    plan's cost)."""
    from rrtcolearn.planning.improve import interior_shortcuts

    planner = swingup_planner(paper_model, u_max)
    p = first_solution(planner, seed)
    before = tree_snapshot(p.tree)
    q = interior_shortcuts(planner, p)
    assert_grown_by_leaves(before, q, q.extra["interior"]["added"], paper_model.system)


def test_shortcut_never_dearer_and_deterministic(paper_model):
    """`shortcut` (goal, then interior shortcuts: the anytime hook) never returns a dearer
    path than it was given, and the same plan gives the same path, bit for bit."""
    planner = swingup_planner(paper_model, 2.0)
    for seed in range(4):
        first = first_solution(planner, seed).path_cost
        a = shortcut(planner, first_solution(planner, seed))
        b = shortcut(planner, first_solution(planner, seed))
        assert a.to_dict()["path"] == b.to_dict()["path"]
        assert a.extra["interior"] == b.extra["interior"]
        assert a.path_cost <= first


@pytest.mark.parametrize(("u_max", "seed"), INTERIOR_CASES)
def test_interior_shortcuts_are_deterministic(paper_model, u_max, seed):
    """The same plan gives the same interior shortcuts, bit for bit."""
    from rrtcolearn.planning.improve import interior_shortcuts

    planner = swingup_planner(paper_model, u_max)
    a = interior_shortcuts(planner, first_solution(planner, seed))
    b = interior_shortcuts(planner, first_solution(planner, seed))
    assert a.extra["interior"]["kept"] >= 1
    assert a.to_dict()["path"] == b.to_dict()["path"]
    assert a.extra["interior"] == b.extra["interior"]


@pytest.mark.parametrize("u_max", [None, 2.0])
def test_landed_shortcuts_resimulate_and_keep_the_tree(paper_model, u_max):
    """`landed_shortcuts` (stretches joined by one extremal over the same duration): on the
    first seed whose path it makes cheaper, the path re-simulated edge by edge by a plain
    RK4 of the pendulum's equations (tests/conftest.py) joins, costs what each edge says,
    keeps the input limit and ends in the goal ball; only leaves are added; the same plan
    gives the same path, bit for bit; and it is never dearer on any seed."""
    from rrtcolearn.planning.improve import landed_shortcuts

    planner = swingup_planner(paper_model, u_max)
    kept = None
    for seed in range(8):
        p = first_solution(planner, seed)
        first, before = p.path_cost, tree_snapshot(p.tree)
        q = landed_shortcuts(planner, p)
        assert q.path_cost <= first
        if q.extra["landed"]["kept"] and kept is None:
            kept = seed
            assert q.path_cost < first
            assert_grown_by_leaves(before, q, q.extra["landed"]["added"], paper_model.system)
            assert_path_resimulates(q, u_max)
            again = landed_shortcuts(planner, first_solution(planner, seed))
            assert again.to_dict()["path"] == q.to_dict()["path"]
            assert again.extra["landed"] == q.extra["landed"]
    assert kept is not None


class _CountingModel:
    """A model that counts the stretches it is asked about (rows of its queries)."""

    def __init__(self, model):
        self.model, self.rows, self.calls = model, 0, 0

    def query(self, X):
        self.rows += len(X)
        self.calls += 1
        return self.model.query(X)


def _long_path(planner, plan, edges):
    """``plan`` with its path replaced by a chain of ``edges`` one-step held inputs from the
    root (an LQR chain's shape), added to its tree."""
    from dataclasses import replace

    from rrtcolearn.integrate import propagate_draws
    from rrtcolearn.planning.contracts import Edge, add_edge

    tree, path, dt = plan.tree, [0], planner.settings.dt
    u = np.array([0.5])
    for _ in range(edges):
        x = tree.states[path[-1]]
        flat = propagate_draws(planner.problem.system, x, u[None], np.array([1]), dt,
                               *planner.propagator.box)[0]
        edge = Edge(np.vstack([x[None], flat[:1]]), 1, dt * (1.0 + 0.125), 0.5, False,
                    control=u.copy())
        path.append(add_edge(tree, path[-1], edge, dt))
    return replace(plan, path_nodes=path)


def test_a_long_paths_pairwise_search_obeys_stop(paper_model):
    """On a path of 3 000 edges the interior search asks the model about one block of
    stretches, then stops when ``stop()`` turns true (no stretch tried); without a stop it
    asks about pairs of at most PAIR_NODES evenly spaced nodes, not all 4.5 million."""
    from rrtcolearn.planning.improve import common, interior

    planner = swingup_planner(paper_model)
    first = first_solution(planner, 3)
    counting = _CountingModel(planner.model)
    planner.model = counting
    p = _long_path(planner, first, 3000)
    q = interior.interior_shortcuts(planner, p, stop=lambda: counting.calls > 0)
    assert counting.calls == 1 and counting.rows == interior.PAIR_BLOCK
    assert q.extra["interior"]["stretches"] == 0 and q.path_nodes == p.path_nodes
    counting.rows = counting.calls = 0
    come = np.concatenate([[0.0], np.cumsum(p.tree.costs[p.path_nodes[1:]])])
    interior._pairs(planner, p.tree, p.path_nodes, come, set())
    pairs = common.PAIR_NODES * (common.PAIR_NODES - 1) // 2
    assert 0 < counting.rows <= pairs and counting.calls == -(-counting.rows // interior.PAIR_BLOCK)
    assert common._stations(3000).size == common.PAIR_NODES
    assert np.array_equal(common._stations(40), np.arange(40))


@pytest.mark.parametrize("u_max", [None, 2.0])
def test_pieces_cut_the_path_and_resimulate(paper_model, u_max):
    """`interior._pieces` (`piece_shortcuts`' stations along the edges): the path cut into
    about 40 pieces passes through every state of the original path in order, costs the
    same (to rounding) and lasts the same, each piece re-simulated by the suite's plain RK4
    ends where it says at its cost and keeps the input limit, `check_plan` agrees (each
    piece's own largest |u|), and every new node names the path node whose edge it cuts."""
    from dataclasses import replace

    from rrtcolearn.evaluate import check_plan
    from rrtcolearn.planning.improve.interior import _pieces

    planner = swingup_planner(paper_model, u_max)
    p = first_solution(planner, 3)
    old = list(p.path_nodes)
    new, origin = _pieces(planner, p.tree, old, 40)
    t = p.tree
    assert len(old) < len(new) <= 40 + len(old)
    assert set(origin.values()) <= set(old[1:])
    # the original nodes' states appear in order along the new path
    at = [next(k for k in range(len(new)) if np.array_equal(t.states[new[k]], t.states[i]))
          for i in old]
    assert at == sorted(at) and at[-1] == len(new) - 1
    assert np.sum(t.costs[new[1:]]) == pytest.approx(p.path_cost, rel=1e-12)
    assert np.sum(t.durations[new[1:]]) == pytest.approx(p.path_duration, rel=1e-12)
    for node in old[1:]:  # each edge's pieces (or its copy) last as long as it
        assert sum(t.durations[k] for k in new[1:] if origin.get(k, k) == node) == \
            pytest.approx(t.durations[node], rel=1e-12)
    q = replace(p, path_nodes=new)
    assert_path_resimulates(q, u_max)
    r = check_plan(paper_model.system, q, goal_fn=planner.problem.goal_distance)
    assert r["path_cost"] == pytest.approx(p.path_cost, rel=1e-9)


def test_piece_shortcuts_keep_the_tree_and_never_cost_more(paper_model):
    """`piece_shortcuts` on the first paths of seeds 0-5 (|u| <= 2): never dearer; only
    leaves added (the pieces and the shortcuts' edges); where it shortens a path, the
    path re-simulates by the suite's plain RK4; the same plan gives the same path."""
    from rrtcolearn.planning.improve import piece_shortcuts

    planner = swingup_planner(paper_model, 2.0)
    gained = 0
    for seed in range(6):
        p = first_solution(planner, seed)
        first, before = p.path_cost, tree_snapshot(p.tree)
        q = piece_shortcuts(planner, p)
        rec = q.extra["pieces"]
        assert q.path_cost <= first
        assert_grown_by_leaves(before, q, rec["added"] + rec["pieces"], paper_model.system)
        again = piece_shortcuts(planner, first_solution(planner, seed))
        assert again.to_dict()["path"] == q.to_dict()["path"]
        if q.path_cost < first:
            gained += 1
            assert_path_resimulates(q, 2.0)
    assert gained >= 1


@pytest.mark.parametrize("verdict", [False, True])
def test_a_pieces_path_turned_down_leaves_the_path_before_them(paper_model, monkeypatch,
                                                                verdict):
    """`shortcut` asks ``accept`` about the pieces' pass's new path only: turned down, the
    plan is the one the pass was given (the other shortcuts' gains kept), recorded as not
    accepted; taken, the pass's. (The pass stands in here: on the pendulum the other
    shortcuts leave one extremal, nothing to cut.)"""
    from dataclasses import replace

    from rrtcolearn.planning import improve

    given, asked = [], []

    def stand_in(planner, plan, stop=None):
        given.append(plan)
        return replace(plan, extra={**plan.extra, "pieces": {"kept": 1}})

    monkeypatch.setattr(improve, "piece_shortcuts", stand_in)
    planner = swingup_planner(paper_model, 2.0)
    out = shortcut(planner, first_solution(planner, 1),
                   accept=lambda q: asked.append(q) or verdict)
    assert len(given) == 1 and len(asked) == 1 and asked[0] is not given[0]
    if verdict:
        assert out is asked[0] and out.extra["pieces"] == {"kept": 1}
    else:
        assert out is given[0] and out.extra["pieces"] == {"kept": 1, "not_accepted": True}


def test_grafted_adds_the_chain_as_leaves_below_the_cut():
    """`grafted`, every pass's way of keeping a chain: the path up to position a, then each
    edge a new leaf below the one before with its kind (None: the edge's default), and
    nothing in the tree before it changed."""
    from rrtcolearn.planning.contracts import Edge
    from rrtcolearn.planning.improve.common import grafted
    from rrtcolearn.planning.tree import PlannerData

    tree = PlannerData(np.zeros(2), n_params=1, capacity=2)
    path = [0]
    for i in range(3):  # a path of three held-input edges
        end = np.array([i + 1.0, 0.0])
        path.append(tree.add(end, path[-1], np.full(2, np.nan), np.full(1, np.nan), 0.1, 1.0,
                             np.stack([end - [1.0, 0.0], end]), 2.0, control=np.array([2.0])))
    before = {k: getattr(tree, k)[: tree.n_nodes].copy() for k in ("states", "parents", "costs")}
    chain = [(Edge(np.array([[1.0, 0.0, 0.5, 0.5, 0.0], [1.5, 1.0, 0.5, 0.5, 0.3]]), 10, 0.3,
                   0.5, False, np.array([0.7, 0.1]), np.array([0.5, 0.5])), "shooting"),
             (Edge(np.array([[1.5, 1.0], [3.0, 0.0]]), 20, 0.8, 1.0, True,
                   control=np.array([1.0])), None)]
    new = grafted(tree, path, 1, chain, 0.01)
    assert new[:2] == path[:2] and len(new) == 4 and new[2:] == [4, 5]
    assert tree.n_nodes == 6 and path == [0, 1, 2, 3]  # the old path untouched
    for k, v in before.items():
        assert np.array_equal(getattr(tree, k)[:4], v, equal_nan=True)
    assert tree.parents[4] == 1 and tree.parents[5] == 4
    assert np.array_equal(tree.states[4], [1.5, 1.0]) and np.array_equal(tree.states[5], [3.0, 0.0])
    assert tree.costs[4] == 0.3 and tree.costs[5] == 0.8
    assert tree.durations[4] == pytest.approx(0.1) and tree.durations[5] == pytest.approx(0.2)
    assert np.array_equal(tree.costates[4], [0.5, 0.5]) and tree.params[4, 0] == 0.7
    assert tree.made_by.get(4) == "shooting" and 5 not in tree.made_by
    assert np.array_equal(tree.controls[5], [1.0]) and np.isnan(tree.costates[5]).all()

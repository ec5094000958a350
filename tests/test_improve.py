"""Goal shortcuts (`planning.improve.shortcut`): a solved path's tail replaced by one extremal
to the goal, added to the same tree as a new leaf; the tree stays a tree whose every edge
re-simulates, the cost only falls, and the same plan gives the same result."""

from __future__ import annotations

import numpy as np
import pytest

from rrtcolearn import pipeline
from rrtcolearn.evaluate import edge_trajectory, resimulate
from rrtcolearn.planning.improve import shortcut
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

START, GOAL = np.array([-np.pi, 0.0]), np.array([0.0, 0.0])


def _planner(model, u_max=None):
    problem = pipeline.make_problem(model.system, model.config, START, GOAL, 0.1, u_max=u_max)
    return RRTCoLearn(problem, model.functions, model.planner_settings())


def _solve(planner, seed):
    return planner.solve(TerminationCondition(None, 3000), seed)


def _tree_edges(plan) -> list[dict]:
    """Every edge of the plan's tree (not only its path) in the plan-file form."""
    t = plan.tree
    out = []
    for k in range(1, t.n_nodes):
        extremal = not np.isnan(t.costates[k]).any()
        out.append({"from": t.states[t.parents[k]], "to": t.states[k],
                    "costate": t.costates[k] if extremal else None,
                    "control": None if extremal else t.controls[k],
                    "duration": t.durations[k], "cost": t.costs[k]})
    return out


@pytest.mark.parametrize("u_max", [None, 2.0])
def test_the_tree_stays_a_tree_of_exact_edges(paper_model, u_max):
    planner = _planner(paper_model, u_max)
    p = _solve(planner, 3)
    first_cost, first_nodes = p.path_cost, p.tree.n_nodes
    q = shortcut(planner, p)
    t = q.tree
    assert q.solved and q.extra["shortcuts"]["added"] >= 1
    assert q.path_cost < first_cost
    # only leaves were added, below earlier nodes: every node reaches the root
    assert t.n_nodes == first_nodes + q.extra["shortcuts"]["added"]
    assert t.parents[0] == -1 and all(t.parents[k] < k for k in range(1, t.n_nodes))
    assert q.path_nodes == t.path_to(q.path_nodes[-1])
    # every edge of the tree re-simulates from its parent to its node at its cost
    w, dt = q.time_weight, q.dt
    for e in _tree_edges(q):
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
    planner = _planner(paper_model)
    for seed in (1, 4):
        a = shortcut(planner, _solve(planner, seed))
        b = shortcut(planner, _solve(planner, seed))
        assert a.to_dict()["path"] == b.to_dict()["path"]
        assert a.path_cost <= _solve(planner, seed).path_cost


def test_an_unsolved_plan_is_returned_as_it_is(paper_model):
    planner = _planner(paper_model)
    p = planner.solve(TerminationCondition(None, 3), 0)
    assert not p.solved and shortcut(planner, p) is p


def test_stop_is_obeyed(paper_model):
    planner = _planner(paper_model)
    p = _solve(planner, 3)
    cost, nodes = p.path_cost, p.tree.n_nodes
    q = shortcut(planner, p, stop=lambda: True)
    assert q.path_cost == cost and q.tree.n_nodes == nodes


def test_shortcuts_keep_clear_of_obstacles(paper_model):
    """A tail that would cross an obstacle is cut there and rejected: the shortcut path
    re-simulated from the start stays free, within the limits, and reaches the goal."""
    from rrtcolearn.evaluate import replay

    block = {"type": "box", "low": [-2.0, 0.3], "high": [-1.2, 2.5]}
    problem = pipeline.make_problem(paper_model.system, paper_model.config, START, GOAL, 0.1,
                                    obstacles=[block])
    planner = RRTCoLearn(problem, paper_model.functions, paper_model.planner_settings())
    cheaper = 0
    for seed in range(3):
        p = _solve(planner, seed)
        first = p.path_cost
        q = shortcut(planner, p)
        r = replay(problem, q)
        assert r["valid"] and r["reaches_goal"] and q.path_cost <= first
        cheaper += q.path_cost < first
    assert cheaper  # the shortcuts did act, around the obstacle

"""The paper's swing-up query as the tests of improved paths ask it of a fitted pendulum model
(tests/test_improve.py, test_multiple_shooting.py, test_anytime.py, test_polish.py): the
planner and its first solution, a plan with plan-section options, and the checks that an
improved tree is still a tree of exact edges. The path checks re-simulate with the plain RK4
of tests/conftest.py (`pendulum_edge`: no code shared with the planner)."""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import pendulum_edge

from rrtcolearn import pipeline
from rrtcolearn.evaluate import edge_trajectory
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

START, GOAL = np.array([-np.pi, 0.0]), np.array([0.0, 0.0])
TOLERANCE = 0.1
FIRST_ITERATIONS = 3000  # the iteration budget of a first solution


def swingup_planner(model, u_max=None, **query) -> RRTCoLearn:
    """The model's planner on the swing-up query (`pipeline.make_problem`, given ``query``'s
    keywords, e.g. ``obstacles``), under ``u_max`` by truncation when given."""
    problem = pipeline.make_problem(model.system, model.config, START, GOAL, TOLERANCE,
                                    u_max=u_max, **query)
    return RRTCoLearn(problem, model.functions, model.planner_settings())


def first_solution(planner, seed):
    """The planner's plan within `FIRST_ITERATIONS` iterations."""
    return planner.solve(TerminationCondition(None, FIRST_ITERATIONS), seed)


def plan_swingup(model, seed, *, time_limit=None, max_iterations=None, **plan_options):
    """`pipeline.plan` of the swing-up with the model's configuration, its plan section
    changed by ``plan_options`` (e.g. ``anytime=True``) where any are given."""
    config = None if not plan_options else model.config.model_copy(update={
        "plan": model.config.plan.model_copy(update=plan_options)})
    return pipeline.plan(model, START, GOAL, TOLERANCE, seed, config=config,
                         time_limit=time_limit, max_iterations=max_iterations)


def tree_edges(plan) -> list[dict]:
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


def costs_to_come(tree) -> np.ndarray:
    """Every node's cost to come, summed edge by edge from the root (parents come first)."""
    come = np.zeros(tree.n_nodes)
    for k in range(1, tree.n_nodes):
        come[k] = come[tree.parents[k]] + tree.costs[k]
    return come


def tree_snapshot(tree) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Copies of the states, parents and edge costs of the tree's nodes, before a change."""
    m = tree.n_nodes
    return tree.states[:m].copy(), tree.parents[:m].copy(), tree.costs[:m].copy()


def assert_grown_by_leaves(before, q, added: int, system) -> None:
    """``q``'s tree is the one ``before`` (`tree_snapshot`) was taken of with ``added`` new
    nodes: the old nodes keep their states, parents and costs; every node hangs below an
    earlier one; the path is the tree's path to its end, whose cost to come summed edge by
    edge is the plan's cost; every new edge re-simulates from its parent to its node
    (`evaluate.edge_trajectory`)."""
    states, parents, costs = before
    m, t = len(states), q.tree
    assert t.n_nodes == m + added
    assert np.array_equal(t.states[:m], states) and np.array_equal(t.parents[:m], parents)
    assert np.array_equal(t.costs[:m], costs)
    assert t.parents[0] == -1 and all(0 <= t.parents[k] < k for k in range(1, t.n_nodes))
    assert q.path_nodes == t.path_to(q.path_nodes[-1])
    assert costs_to_come(t)[q.path_nodes[-1]] == pytest.approx(q.path_cost, rel=1e-12)
    for e in tree_edges(q)[m - 1 :]:
        r = edge_trajectory(system, e, q.time_weight, q.dt)
        assert np.abs(r.states[-1] - e["to"]).max() < 1e-9


def assert_path_resimulates(q, u_max=None) -> None:
    """``q``'s path re-simulated edge by edge by a plain RK4 of the pendulum's own equations
    from the start: each edge starts where the last ended, ends where it says at the cost it
    says, keeps |u| <= ``u_max``; the costs sum to the plan's, and the path ends in the goal
    ball."""
    x, cost = START, 0.0
    for e in q.edges():
        assert np.abs(np.asarray(e["from"]) - x).max() < 1e-12
        states, inputs, c = pendulum_edge(e, q.time_weight, q.dt)
        assert np.abs(states[-1] - e["to"]).max() < 1e-9
        assert c == pytest.approx(e["cost"], rel=1e-9, abs=1e-12)
        if u_max is not None:
            assert np.abs(inputs).max() <= u_max + 1e-9
        x, cost = states[-1], cost + c
    assert cost == pytest.approx(q.path_cost, rel=1e-9)
    assert np.linalg.norm(x - GOAL) <= TOLERANCE

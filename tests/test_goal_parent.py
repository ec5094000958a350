"""Choose-parent for the goal (`connections.cheaper_goal_edge`, ``plan.goal_parent_tries``):
once a solve reaches the goal it shoots at the goal from the nodes with the least
cost-to-come plus J and keeps the cheapest path. Checked against the same solve with it off
(the tree must be that tree plus the one goal edge) and against a hand RK4 of the pendulum's
state+costate ODEs and a hand formula for its Hamiltonian."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from tests.conftest import pendulum_edge
from tests.tree_cases import CASES, fit_model

from rrtcolearn import evaluate, pipeline
from rrtcolearn.cli.planning import plan_summary
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

_CASES = {c.name: c for c in CASES}
TOLERANCE = 0.1


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return fit_model(_CASES["pendulum"], tmp_path_factory.mktemp("goal_parent") / "pendulum")


def _planner(model, tries: int) -> RRTCoLearn:
    cfg = model.config
    problem = pipeline.make_problem(model.system, cfg, [-np.pi, 0.0], [0.0, 0.0], TOLERANCE)
    return RRTCoLearn(problem, model.functions,
                      replace(model.planner_settings(cfg), goal_parent_tries=tries))


def _hamiltonian(x: np.ndarray, lam: np.ndarray, w: float) -> float:
    """H* of theta'' = sin(theta) + u at cost w + u^2/2, u = -lambda_omega, by hand."""
    u = -lam[1]
    return w + 0.5 * u * u + lam[0] * x[1] + lam[1] * (np.sin(x[0]) + u)


def test_the_cheaper_goal_edge_is_the_only_change_and_replays_by_hand(model):
    on, off = _planner(model, 4), _planner(model, 0)
    w, dt = on.settings.time_weight, on.settings.dt
    improved = 0
    for seed in range(10):
        p = on.solve(TerminationCondition(None, 5000), seed)
        q = off.solve(TerminationCondition(None, 5000), seed)
        assert p.solved and q.solved
        assert "goal_parent" not in q.extra  # off: the paper's planner
        n = q.tree.n_nodes
        # the same tree, grown by the same iterations, and at most the one goal edge more
        assert p.iterations == q.iterations and p.tree.n_nodes in (n, n + 1)
        for a in ("states", "parents", "costs", "durations"):
            assert np.array_equal(getattr(p.tree, a)[:n], getattr(q.tree, a)[:n])
        record = p.extra["goal_parent"]
        assert record["cost_before"] == pytest.approx(q.path_cost, rel=1e-12)
        assert record["cost"] == pytest.approx(p.path_cost, rel=1e-12)
        assert 0 <= record["tries"] <= 4
        if p.tree.n_nodes == n:
            assert p.path_nodes == q.path_nodes
            continue
        improved += 1
        assert p.path_cost < q.path_cost
        assert f"{q.path_cost:.4g} -> {p.path_cost:.4g}" in plan_summary(p)["goal_parent"]
        assert p.path_nodes[-1] == n and p.path_nodes[:-1] == p.tree.path_to(p.path_nodes[-2])
        # the new goal edge, re-simulated by hand from its costate: it ends in the goal
        # region, at its recorded cost, and starts on H* = 0 (free final time)
        e = p.to_dict()["path"][-1]
        assert e["control"] is None and p.tree.kind(n) in ("learned", "shooting")
        states, _, cost = pendulum_edge(e, w, dt)
        gap = states[-1] - np.array([0.0, 0.0])
        gap[0] = np.mod(gap[0] + np.pi, 2 * np.pi) - np.pi
        assert np.linalg.norm(gap) <= TOLERANCE
        assert cost == pytest.approx(e["cost"], rel=1e-9)
        assert _hamiltonian(np.array(e["from"]), np.array(e["costate"]), w) == \
            pytest.approx(0.0, abs=1e-6)
        # the path's cost is its edges' sum, and the plan replays to it
        assert sum(x["cost"] for x in p.to_dict()["path"]) == pytest.approx(p.path_cost)
        assert evaluate.step_check(on.problem, p)["replays"]
    assert improved >= 3  # the pendulum: most first paths have a cheaper goal edge


def test_more_tries_never_cost_more(model):
    """The candidates are tried in one order and the cheapest path is kept: each allowance's
    path costs no more than a smaller one's, on the same tree."""
    costs = {}
    for tries in (0, 1, 4, 100):
        planner = _planner(model, tries)
        costs[tries] = [planner.solve(TerminationCondition(None, 5000), seed).path_cost
                        for seed in range(6)]
    for a, b in ((0, 1), (1, 4), (4, 100)):
        assert all(y <= x + 1e-12 for x, y in zip(costs[a], costs[b], strict=True))
    assert sum(costs[100]) < sum(costs[0])


def test_the_cheaper_goal_edge_keeps_out_of_an_obstacle(model):
    """A disc in (theta, omega) beside the swing-up's approach to the upright: every state of
    each new goal edge, re-simulated by hand, lies outside it."""
    centre, radius = np.array([-0.6, 1.0]), 0.4

    def outside(x: np.ndarray) -> np.ndarray:
        th = np.mod(x[:, 0] + np.pi, 2 * np.pi) - np.pi
        return (th - centre[0]) ** 2 + (x[:, 1] - centre[1]) ** 2 > radius**2

    cfg = model.config
    problem = pipeline.make_problem(model.system, cfg, [-np.pi, 0.0], [0.0, 0.0], TOLERANCE,
                                    is_valid=outside)
    planner = RRTCoLearn(problem, model.functions, model.planner_settings(cfg))
    w, dt = planner.settings.time_weight, planner.settings.dt
    improved = 0
    for seed in range(10):
        p = planner.solve(TerminationCondition(None, 5000), seed)
        record = p.extra["goal_parent"]
        if not p.solved or record["cost"] >= record["cost_before"]:
            continue
        improved += 1
        for e in p.to_dict()["path"]:
            states, _, _ = pendulum_edge(e, w, dt)
            assert outside(states).all()
    assert improved >= 2


def test_the_cheaper_goal_edge_keeps_within_a_torque_limit(model):
    """Under |u| <= 2 by truncation (edges whose input breaks it are rejected): every input
    of each improved path, re-simulated by hand, is within the limit. (At |u| <= 1 every
    shot of this unbounded model breaks the limit: 0 of 30 seeds improved.)"""
    cfg = model.config
    problem = pipeline.make_problem(model.system, cfg, [-np.pi, 0.0], [0.0, 0.0], TOLERANCE,
                                    u_max=2.0)
    planner = RRTCoLearn(problem, model.functions, model.planner_settings(cfg))
    w, dt = planner.settings.time_weight, planner.settings.dt
    improved = 0
    for seed in range(10):
        p = planner.solve(TerminationCondition(None, 5000), seed)
        record = p.extra.get("goal_parent")
        if not p.solved or record is None or record["cost"] >= record["cost_before"]:
            continue
        improved += 1
        for e in p.to_dict()["path"]:
            _, inputs, _ = pendulum_edge(e, w, dt)
            assert np.abs(inputs).max() <= 2.0 + 1e-9
    assert improved >= 2


def test_choose_parent_through_the_funnel_adds_a_cheaper_chain_that_resimulates(
        tmp_path_factory):
    """`FunnelConnection.cheaper`: once a solve with the goal funnel on has reached the goal,
    continuations from the nodes whose cost to come plus their funnel state's cost to go is
    least. On the small cart-pole tree case (it connects through the funnel at iteration
    331) it finds a cheaper path: the same tree as with choose-parent off, plus a chain of
    funnel edges, each re-simulated on the textbook cart-pole (`tests/references.py`:
    Pontryagin's equations on hand-written dynamics, a plain RK4) from where the previous
    one ended, into the goal region, at its recorded cost."""
    from tests import references
    from tests.references import rk4
    from tests.tree_cases import plan_case

    from rrtcolearn.planning import connections

    case = _CASES["cartpole"]
    model = fit_model(case, tmp_path_factory.mktemp("funnel_parent") / "cartpole")
    p = plan_case(case, model)
    q = plan_case(replace(case, plan=(*case.plan, "plan.goal_parent_tries=0")), model)
    assert p.solved and q.solved and p.iterations == q.iterations
    n = q.tree.n_nodes
    for a in ("states", "parents", "costs", "durations"):
        assert np.array_equal(getattr(p.tree, a)[:n], getattr(q.tree, a)[:n])
    record = p.extra["goal_parent"]
    assert 1 <= record["funnel_tries"] <= 4 * len(connections.PARENT_REACH)
    assert record["cost_before"] == pytest.approx(q.path_cost, rel=1e-12)
    assert record["cost"] == pytest.approx(p.path_cost, rel=1e-12)
    assert p.path_cost < q.path_cost  # measured: 1 581 -> 691
    new = [i for i in p.path_nodes if i >= n]
    assert new and new == list(range(n, p.tree.n_nodes))  # the chain ends the path
    assert all(p.tree.kind(i) == "funnel" for i in new)
    assert f"{record['funnel_tries']} through the goal funnel" in \
        plan_summary(p)["goal_parent"]
    settings = model.planner_settings(model.config)
    w, dt = settings.time_weight, settings.dt
    rhs = references.state_costate_rhs(references.cartpole, 1, w)
    path = p.to_dict()["path"]
    edges = path[len(path) - len(new):]
    at = np.array(edges[0]["from"])
    for e in edges:
        assert e["control"] is None
        np.testing.assert_array_equal(e["from"], at)
        end = rk4(rhs, np.r_[e["from"], e["costate"], 0.0], dt, round(e["duration"] / dt))[-1]
        np.testing.assert_allclose(end[:4], e["to"], atol=1e-4)
        assert end[-1] == pytest.approx(e["cost"], rel=1e-6)
        at = np.array(e["to"])
    assert p.final_goal_distance <= p.goal_tolerance
    assert sum(x["cost"] for x in path) == pytest.approx(p.path_cost)

"""RRT-CoLearn on the swing-up; plans are checked by re-simulating them independently."""

import itertools
import json

import numpy as np
import pytest
from tests.conftest import pendulum_edge

from rrtcolearn.pipeline import plan, write_plan
from rrtcolearn.planning.problem import ProblemError


def check_plan_file(d: dict) -> None:
    """Re-simulate every edge with an independent RK4 and check what the plan claims."""
    w, dt = d["time_weight"], d["dt"]
    saturated = d["u_max"] if d.get("limit_mode") == "saturate" else None
    edges = d["path"]
    assert edges, "a solved plan has edges"
    np.testing.assert_allclose(edges[0]["from"], d["start"])
    total = 0.0
    for a, b in itertools.pairwise(edges):
        assert a["to"] == b["from"]
    for e in edges:
        steps = round(e["duration"] / dt)
        assert steps * dt == pytest.approx(e["duration"])
        states, _, cost = pendulum_edge(e, w, dt, saturated)
        np.testing.assert_allclose(states[-1], e["to"], atol=1e-6)
        assert cost == pytest.approx(e["cost"], abs=1e-6)
        if e["control"] is None:
            # the costate satisfies H = 0 at the edge start, at u* (clipped when saturated)
            x, lam = np.array(e["from"]), np.array(e["costate"])
            u = np.clip(-lam[1], -(saturated or np.inf), saturated or np.inf)
            h = w + 0.5 * u**2 + lam[0] * x[1] + lam[1] * (np.sin(x[0]) + u)
            assert abs(h) < 1e-9
        else:  # a random-control edge: its input and nothing learned
            assert e["costate"] is None and e["params"] is None
        total += e["cost"]
    assert d["path_cost"] == pytest.approx(total)
    if d["solved"]:
        gap = np.linalg.norm(np.array(edges[-1]["to"]) - d["goal"])
        assert gap <= d["goal_tolerance"]
    tree = d["tree"]
    assert len(tree["states"]) == d["nodes"] == len(tree["parents"])
    assert tree["parents"][0] == -1


def test_seeded_swing_up_solves_and_resimulates(paper_model, tmp_path):
    p = plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=0, time_limit=None,
             max_iterations=3000)
    assert p.solved and p.status == "exact" and p.iterations < 3000
    write_plan(p, tmp_path / "plan.json")
    d = json.loads((tmp_path / "plan.json").read_text())
    for key in ("system", "start", "goal", "goal_tolerance", "time_weight", "solved", "status",
                "planning_time_s", "iterations", "nodes", "path_cost", "path", "tree"):
        assert key in d
    check_plan_file(d)


def test_same_seed_same_plan(paper_model):
    a = plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=5, time_limit=None,
             max_iterations=3000)
    b = plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=5, time_limit=None,
             max_iterations=3000)
    assert a.solved and a.to_dict()["path"] == b.to_dict()["path"]
    assert a.nodes == b.nodes


def test_iteration_limit_gives_the_closest_node_as_an_approximate_plan(paper_model):
    """Out of iterations before the goal: "approximate", the path to the tree's node closest
    to the goal, re-simulated independently."""
    p = plan(paper_model, [-np.pi, 0], [0, 0], 0.01, seed=1, time_limit=None,
             max_iterations=100)
    assert (p.solved, p.status, p.iterations) == (False, "approximate", 100)
    d = p.to_dict()
    assert len(d["path"]) >= 1 and d["nodes"] > 1
    closest = np.linalg.norm(np.array(d["tree"]["states"]), axis=1).min()  # goal (0, 0)
    assert d["final_goal_distance"] == pytest.approx(closest, abs=1e-12)
    assert d["final_goal_distance"] > 0.01
    np.testing.assert_allclose(np.linalg.norm(d["path"][-1]["to"]), closest, atol=1e-12)
    check_plan_file(d)


def test_a_budget_that_grows_no_node_is_a_timeout(paper_model):
    """Five iterations on this seed add no node: "timeout", the start alone, no path."""
    p = plan(paper_model, [-np.pi, 0], [0, 0], 0.01, seed=1, time_limit=None,
             max_iterations=5)
    assert (p.solved, p.status, p.iterations, p.nodes) == (False, "timeout", 5, 1)
    assert p.to_dict()["path"] == []
    assert p.to_dict()["final_goal_distance"] == pytest.approx(np.pi)


@pytest.mark.parametrize("start, goal, tol, message", [
    ([np.nan, 0], [0, 0], 0.1, "finite"),
    ([-np.pi, 0], [0, 10.0], 0.1, "outside the state box"),
    ([-np.pi], [0, 0], 0.1, "2 coordinates"),
    ([-np.pi, 0], [0, 0], 0.0, "positive"),
    ([-np.pi, 0], [0, 0], -1.0, "positive"),
    (["a", 0], [0, 0], 0.1, "numbers"),
])
def test_bad_queries_are_refused(paper_model, start, goal, tol, message):
    with pytest.raises(ProblemError, match=message):
        plan(paper_model, start, goal, tol)


@pytest.mark.parametrize("kwargs, message", [
    ({"seed": -1}, "seed must be a non-negative integer"),
    ({"seed": 1.5}, "seed must be a non-negative integer"),
    ({"time_limit": 0}, "time_limit must be a positive number"),
    ({"time_limit": -1.0}, "time_limit must be a positive number"),
    ({"time_limit": float("inf")}, "time_limit must be a positive number"),
    ({"max_iterations": 0}, "max_iterations must be a positive integer"),
    ({"max_iterations": 2.5}, "max_iterations must be a positive integer"),
])
def test_bad_seeds_and_limits_are_refused_as_on_the_command_line(paper_model, kwargs, message):
    """The library refuses what `rrtcolearn plan` refuses, with its reason (a negative seed
    was numpy's own error, a zero limit a plan that stopped before its first iteration)."""
    with pytest.raises(ProblemError, match=message):
        plan(paper_model, [-np.pi, 0], [0, 0], 0.1, **kwargs)


def test_concurrent_queries_on_one_model_match_sequential(paper_model):
    """No shared mutable state: threads planning on one model give the sequential plans."""
    from concurrent.futures import ThreadPoolExecutor

    def one(seed):
        p = plan(paper_model, [-np.pi, 0], [0, 0], 0.2, seed=seed, time_limit=None,
                 max_iterations=2000)
        return p.to_dict()["path"], p.nodes

    sequential = [one(s) for s in range(8)]
    with ThreadPoolExecutor(max_workers=4) as pool:
        threaded = list(pool.map(one, range(8)))
    assert threaded == sequential

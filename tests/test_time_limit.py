"""The time limits themselves: a wall-clock or CPU limit stops `solve`, and the anytime scheme
spends a time budget. The only tests that assert durations, each with a wide margin above
(a loaded machine stretches a run, never shortens it below its limit)."""

from __future__ import annotations

import time
from itertools import pairwise

import numpy as np
import pytest

from rrtcolearn import pipeline, planners
from rrtcolearn.anytime import solve_with_restarts
from rrtcolearn.evaluate import resimulate
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.termination import TerminationCondition

START, GOAL = [-np.pi, 0.0], [0.0, 0.0]
UNREACHABLE = 1e-9  # a goal tolerance no edge ends within: only a limit stops the planner
LIMIT = 1.0
MARGIN = 60.0  # stopping takes at most one iteration beyond the limit, and a start-up


def test_a_limit_reached_before_the_first_iteration_is_a_timeout(paper_model):
    """No node grown: status "timeout", the start alone; the iteration limit is far away."""
    p = pipeline.plan(paper_model, START, GOAL, 0.1, 0, time_limit=1e-9,
                      max_iterations=10**9)
    assert (p.solved, p.status, p.iterations, p.nodes) == (False, "timeout", 0, 1)


def test_a_wall_clock_limit_stops_a_growing_tree(paper_model):
    wall = time.perf_counter()
    p = pipeline.plan(paper_model, START, GOAL, UNREACHABLE, 0, time_limit=LIMIT,
                      max_iterations=None)
    wall = time.perf_counter() - wall
    assert not p.solved and p.status == "approximate" and p.iterations > 0
    assert LIMIT <= p.planning_time_s <= wall < LIMIT + MARGIN


def test_a_cpu_limit_stops_solve(paper_model, pendulum):
    problem = PlanningProblem.create(pendulum, START, GOAL, UNREACHABLE)
    planner = planners.make("rrtcolearn", model=paper_model)
    cpu = time.process_time()
    p = planner.solve(problem, TerminationCondition(time_limit=None, cpu_time_limit=LIMIT), 0)
    cpu = time.process_time() - cpu
    assert not p.solved and p.status == "approximate" and p.iterations > 0
    assert LIMIT <= cpu < LIMIT + MARGIN  # the process's CPU, which the limit counts


def test_the_anytime_scheme_spends_a_time_budget(paper_model):
    """With a time limit (no iteration limit) the restarts and shortcuts run until the limit;
    the first solution is the plain solve's (same seed), later ones only improve it."""
    cfg = paper_model.config.model_copy(update={"plan": paper_model.config.plan.model_copy(
        update={"anytime": True})})
    first = pipeline.plan(paper_model, START, GOAL, 0.1, 3, time_limit=None,
                          max_iterations=3000)
    wall = time.perf_counter()
    p = pipeline.plan(paper_model, START, GOAL, 0.1, 3, config=cfg, time_limit=LIMIT,
                      max_iterations=None)
    wall = time.perf_counter() - wall
    a = p.extra["anytime"]
    assert LIMIT <= wall < LIMIT + MARGIN
    assert p.solved and a["solves"] > 1 and a["scheme"] == "restarts+shortcut"
    costs = [c for _, c in a["progress"]]
    assert costs[0] == pytest.approx(first.path_cost, rel=1e-12)
    assert all(b < c for c, b in pairwise(costs)) and p.path_cost == costs[-1]
    r = resimulate(paper_model.system, p)
    assert r["max_gap"] < 1e-9 and r["path_cost"] == pytest.approx(p.path_cost, rel=1e-9)


def test_the_restart_baseline_spends_a_cpu_budget(pendulum):
    problem = PlanningProblem.create(pendulum, START, GOAL, 0.3, u_max=2.0)
    peer = planners.make("random-rrt", time_weight=1.0)

    def solve(termination, seed):
        return peer.solve(problem, termination, seed)

    cpu = time.process_time()
    p = solve_with_restarts(solve, TerminationCondition(time_limit=None, cpu_time_limit=LIMIT),
                            seed=1)
    cpu = time.process_time() - cpu
    a = p.extra["anytime"]
    assert LIMIT <= cpu < LIMIT + MARGIN
    assert p.solved and a["scheme"] == "restarts" and a["solves"] > 1
    assert p.path_cost == min(c for _, c in a["progress"])

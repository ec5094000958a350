"""The time limits themselves: a wall-clock or CPU limit stops `solve` (the anytime scheme's
time budgets: test_anytime.py). With those, the only tests that assert durations, each with a
wide margin above (a loaded machine stretches a run, never shortens it below its limit)."""

from __future__ import annotations

import time

import numpy as np

from rrtcolearn import pipeline, planners
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

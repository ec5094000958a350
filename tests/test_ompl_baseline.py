"""OMPL's control planners as baselines: solved swing-ups, re-simulated, seeded, obstacle-aware.

Every OMPL run goes through ``run_ompl_isolated`` (one fresh process each), so the pytest
process never creates an OMPL random generator; results are cached per module.
"""

import numpy as np
import pytest

from rrtcolearn.baselines.base import BaselineResult, ControlPath, path_metrics, simulate_controls
from rrtcolearn.baselines.ompl_planners import (
    _obstacle_free,
    ompl_available,
    run_ompl_isolated,
    solve_ompl,
)
from rrtcolearn.planning.problem import PlanningProblem, ProblemError

pytest.importorskip("ompl")  # the module above imports ompl lazily, so this import works

START = [-np.pi, 0.0]
GOAL = np.array([0.0, 0.0])
TOL = 0.1
BOX = {"type": "box", "low": [-2.0, 0.3], "high": [-1.2, 2.5]}
_cache: dict = {}


def run(planner: str, u_max: float, seed: int, box: bool = False) -> BaselineResult:
    """One isolated OMPL run, cached by its arguments."""
    key = (planner, u_max, seed, box)
    if key not in _cache:
        _cache[key] = run_ompl_isolated(planner, START, GOAL, TOL, u_max=u_max, seed=seed,
                                        time_limit=10.0, obstacles=[BOX] if box else [])
    return _cache[key]


def check_path(pendulum, r: BaselineResult, u_max: float) -> dict:
    """Re-simulate the returned path and check what the result claims about it."""
    assert isinstance(r.path, ControlPath)
    k = len(r.path.durations)
    assert k > 0 and r.path.controls.shape == (k, 1)
    np.testing.assert_array_equal(r.path.start, START)
    steps = r.path.durations / 0.02
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
    assert np.all((np.round(steps) >= 1) & (np.round(steps) <= 25))
    m = path_metrics(pendulum, r.path, 0.01, 1.0, GOAL, TOL)
    assert m["max_abs_u"] <= u_max
    assert m["final_goal_distance"] == pytest.approx(r.extra["final_goal_distance"])
    return m


def test_available():
    assert ompl_available()


@pytest.mark.parametrize("u_max", [1.0, 2.0])
@pytest.mark.parametrize("seed", [0, 1])
def test_rrt_solves_swing_up(pendulum, u_max, seed):
    r = run("RRT", u_max, seed)
    assert r.planner == "ompl-rrt"
    assert r.solved and r.status == "exact" and r.extra["ompl_claimed_exact"]
    assert r.wall_s < 10.0 and 0 < r.cpu_s < 10.0
    assert r.nodes > 1
    assert r.extra["seeded_before_first_rng"]
    m = check_path(pendulum, r, u_max)
    assert m["reaches_goal"] and m["final_goal_distance"] <= TOL
    # OMPL's own propagation and the independent re-simulation agree on the end state
    assert r.extra["resim_end_gap"] < 1e-9
    states = simulate_controls(pendulum, r.path, 0.01)
    assert np.all((states >= pendulum.state_low) & (states <= pendulum.state_high))


def test_same_seed_same_result():
    a = run("RRT", 1.0, 0)
    b = run_ompl_isolated("RRT", START, GOAL, TOL, u_max=1.0, seed=0, time_limit=10.0)
    np.testing.assert_array_equal(a.path.controls, b.path.controls)
    np.testing.assert_array_equal(a.path.durations, b.path.durations)
    assert a.nodes == b.nodes
    assert a.extra["final_goal_distance"] == b.extra["final_goal_distance"]
    # seeds 0 and 1 are distinct runs (OMPL alone would map seed 0 to 1)
    c = run("RRT", 1.0, 1)
    assert c.extra["ompl_seed"] != a.extra["ompl_seed"]
    assert c.nodes != a.nodes or not np.array_equal(c.path.durations, a.path.durations)


def test_box_obstacle_respected(pendulum):
    r = run("RRT", 2.0, 0, box=True)
    assert r.solved and r.status == "exact" and r.extra["resim_valid"]
    check_path(pendulum, r, 2.0)
    states = simulate_controls(pendulum, r.path, 0.01)
    wrapped = states + pendulum.wrap_shift(states)
    assert np.all((wrapped[:, 0] >= -1.5 * np.pi) & (wrapped[:, 0] < 0.5 * np.pi))
    inside = np.all((wrapped >= BOX["low"]) & (wrapped <= BOX["high"]), axis=1)
    assert not inside.any()


@pytest.mark.parametrize("planner", ["KPIECE1", "EST"])
def test_other_planners_return_valid_results(pendulum, planner):
    r = run(planner, 2.0, 0)
    assert isinstance(r, BaselineResult)
    assert r.planner == f"ompl-{planner.lower()}"
    assert r.status in ("exact", "approximate", "timeout")
    assert r.iterations == 0 and r.nodes >= 1 and r.cpu_s > 0
    assert r.solved == bool(r.extra["reaches_goal"] and r.extra["resim_valid"])
    if r.path is not None:
        m = check_path(pendulum, r, 2.0)
        assert m["reaches_goal"] == r.extra["reaches_goal"]


def test_fast_obstacle_test_matches_problem_validity(pendulum):
    obstacles = [BOX, {"type": "halfplane", "normal": [0.3, -1.0], "offset": 2.4}]
    problem = PlanningProblem.create(pendulum, START, GOAL, TOL, u_max=1.0,
                                     obstacles=obstacles)
    free = _obstacle_free(problem)
    rng = np.random.default_rng(0)
    x = rng.uniform(pendulum.state_low - 1.0, pendulum.state_high + 1.0, size=(4000, 2))
    x = np.concatenate([x, [[-2.0, 0.3], [-1.2, 2.5], [0.5 * np.pi, 0.0], [-1.5 * np.pi, 1.0]]])
    np.testing.assert_array_equal([free(a, b) for a, b in x], problem.validity(x))
    assert _obstacle_free(PlanningProblem.create(pendulum, START, GOAL, TOL)) is None


@pytest.mark.parametrize("kwargs, match", [
    ({"planner": "SST"}, "unknown OMPL planner"),
    ({"u_max": None}, "control bounds"),
    ({"propagation_step": 0.015}, "multiple of"),
    ({"min_steps": 5, "max_steps": 2}, "min_steps"),
])
def test_bad_arguments(kwargs, match):
    args = {"planner": "RRT", "u_max": 1.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        solve_ompl(args.pop("planner"), START, GOAL, TOL, **args)


def test_worker_errors_reach_the_caller():
    with pytest.raises(ProblemError, match="inside an obstacle"):
        run_ompl_isolated("RRT", START, [-1.5, 1.0], TOL, u_max=1.0, obstacles=[BOX])

"""The reference-optimum collocation (`baselines.collocation`), on the pendulum: fast."""

from __future__ import annotations

import casadi  # noqa: F401  (an extra: `make test` installs it; missing, the suite fails)
import numpy as np
import pytest

from rrtcolearn.baselines.collocation import (
    CollocationResult,
    optimal_cost,
    problem_optimum,
    sympy_to_casadi,
)
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.systems import make

START, GOAL = [-np.pi, 0.0], [0.0, 0.0]
SWING_UP = 5.41803  # 60 intervals (docs/collocation.md); baselines.direct gives the same
FAST = {"n_intervals": 20, "durations": (4.0,), "t_max": 15.0}


@pytest.fixture(scope="module")
def pendulum():
    return make("pendulum")


def test_sympy_to_casadi_matches_numpy():
    import casadi as ca
    import sympy

    a, b = sympy.symbols("a b", real=True)
    expr = (sympy.sin(a) * sympy.sqrt(1 + b**2) / (2 + sympy.cos(b)) + sympy.Abs(a) ** 3
            + sympy.atan2(b, 1 + a**2) + sympy.Piecewise((a, a > 0), (b, True))
            + sympy.Max(a, b, 0) + sympy.exp(-b) * sympy.pi)
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [sympy_to_casadi(expr, {a: x[0], b: x[1]})])
    g = sympy.lambdify((a, b), expr, "numpy")
    for va, vb in [(0.3, -1.2), (-0.7, 0.4), (1.5, 2.0)]:
        assert float(f([va, vb])) == pytest.approx(float(g(va, vb)), rel=1e-12)
    with pytest.raises(ValueError, match="cannot convert"):
        sympy_to_casadi(sympy.besselj(0, a), {a: x[0]})


def test_swing_up_optimum_is_re_simulated_and_converged(pendulum):
    res = optimal_cost(pendulum, START, GOAL, **FAST)
    assert isinstance(res, CollocationResult) and res.success
    # converged in N: within 1e-5 of the 60-interval optimum already at 20
    assert res.cost == pytest.approx(SWING_UP, rel=1e-5)
    assert res.duration == pytest.approx(3.529, abs=2e-3)
    # independent RK4 on the generated numpy dynamics reaches the goal
    assert res.resim_error < 1e-4 and res.interval_error < 1e-5
    assert res.resim_goal_distance < 1e-4 and res.held_error < 1e-3
    assert res.resim_cost == pytest.approx(res.cost, rel=1e-6)
    assert np.allclose(res.states[0], START) and res.controls.shape == (21, 1)
    assert res.times[-1] == pytest.approx(res.duration)
    # the unbounded optimum keeps |u| <= 2 on its own: the bound does not change it
    bounded = optimal_cost(pendulum, START, GOAL, u_max=2.0, **FAST)
    assert bounded.cost == pytest.approx(res.cost, rel=1e-6)
    assert np.abs(bounded.controls).max() <= 2.0 + 1e-7


def test_ball_goal_and_tighter_bound(pendulum):
    ball = optimal_cost(pendulum, START, GOAL, tolerance=0.1, **FAST)
    assert ball.success and ball.cost < SWING_UP
    assert ball.cost == pytest.approx(5.2054, abs=2e-3)
    assert ball.goal_distance == pytest.approx(0.1, abs=1e-6)
    # a binding bound costs more and is respected; the re-simulated path ends in the ball
    tight = optimal_cost(pendulum, START, GOAL, tolerance=0.1, u_max=0.5,
                         n_intervals=30, durations=(6.0, 10.0), t_max=20.0)
    assert tight.success and tight.cost > ball.cost
    # (IPOPT relaxes bounds by its bound_relax_factor, 1e-8 relative)
    assert np.abs(tight.controls).max() <= 0.5 + 1e-7
    assert np.abs(tight.mid_controls).max() <= 0.5 + 1e-7
    assert tight.resim_goal_distance < 0.1 + 1e-3


def test_wrapped_goal_is_reached_modulo_a_turn(pendulum):
    # the goal two turns away: with wrapping the optimum is the same swing-up
    res = optimal_cost(pendulum, START, [4 * np.pi, 0.0], **FAST)
    assert res.success and res.cost == pytest.approx(SWING_UP, rel=1e-5)
    end = res.states[-1, 0]
    assert abs(np.sin(end)) < 1e-6 and np.cos(end) > 0
    # without wrapping the far goal costs more
    far = optimal_cost(pendulum, START, [4 * np.pi, 0.0], wrap_goal=False,
                       state_low=[None, -20.0], state_high=[None, 20.0], **FAST)
    assert far.success and far.cost > res.cost + 1.0


def test_a_path_guess_warm_starts_a_finer_grid(pendulum):
    coarse = optimal_cost(pendulum, START, GOAL, **FAST)
    fine = optimal_cost(pendulum, START, GOAL, n_intervals=40, durations=(), path=coarse)
    assert fine.guess == "path" and fine.cost == pytest.approx(SWING_UP, rel=1e-5)
    assert fine.attempts[0]["iterations"] < 30
    # a (times, states, held controls) path, as a planner's re-simulated one
    t = coarse.times
    mids = 0.5 * (t[:-1] + t[1:])
    path = (t, coarse.states, coarse.control_at(mids))
    again = optimal_cost(pendulum, START, GOAL, n_intervals=20, durations=(), path=path)
    assert again.success and again.cost == pytest.approx(SWING_UP, rel=1e-5)
    # a re-simulated plan's rows (`evaluate.sample_path`) repeat the node where two edges
    # join, at one time, the later copy with the next edge's input: it guesses alike
    k = len(t) // 2
    twice = (np.insert(t, k, t[k]), np.insert(coarse.states, k, coarse.states[k], axis=0),
             np.insert(path[2], k, [[1e3]], axis=0))  # the earlier copy's input: dropped
    joined = optimal_cost(pendulum, START, GOAL, n_intervals=20, durations=(), path=twice)
    assert joined.success and joined.cost == pytest.approx(again.cost, rel=1e-9)
    assert joined.attempts[0]["iterations"] == again.attempts[0]["iterations"]
    with pytest.raises(ValueError, match="increasing"):
        optimal_cost(pendulum, START, GOAL, n_intervals=20, durations=(),
                     path=(t[::-1], coarse.states, path[2]))
    # the search-then-refine mode
    both = optimal_cost(pendulum, START, GOAL, n_intervals=30, search_intervals=10,
                        durations=(3.0, 6.0), t_max=15.0)
    assert both.success and both.n_intervals == 30
    assert {a["stage"] for a in both.attempts} == {"search", "refine"}
    assert both.cost == pytest.approx(SWING_UP, rel=1e-5)


def test_problem_optimum_and_task_space_goal(pendulum):
    import casadi as ca

    problem = PlanningProblem.create(pendulum, START, GOAL, 0.1, u_max=2.0)
    res = problem_optimum(problem, **FAST)
    assert res.success and res.cost == pytest.approx(5.2054, abs=2e-3)
    # a task-space goal: the pendulum's tip (sin theta, cos theta) within 0.1 of upright's
    def tip_distance(x):
        return ca.sqrt(ca.sin(x[0]) ** 2 + (ca.cos(x[0]) - 1) ** 2 + 1e-12)

    task = optimal_cost(pendulum, START, GOAL, tolerance=0.1, goal_distance=tip_distance,
                        **FAST)
    assert task.success and task.cost < res.cost  # the velocity is free at the goal
    assert task.goal_distance == pytest.approx(0.1, abs=1e-6)
    with_fn = PlanningProblem.create(
        pendulum, START, GOAL, 0.1,
        goal_fn=lambda x: np.hypot(np.sin(x[:, 0]), np.cos(x[:, 0]) - 1))
    with pytest.raises(ValueError, match="goal_distance"):
        problem_optimum(with_fn, **FAST)


@pytest.mark.parametrize("kwargs, match", [
    ({"tolerance": -1.0}, "tolerance"),
    ({"time_weight": 0.0}, "time_weight"),
    ({"u_max": -2.0}, "u_max"),
    ({"n_intervals": 1}, "n_intervals"),
    ({"durations": ()}, "duration"),
    ({"durations": (-1.0,)}, "durations"),
    ({"goal_distance": lambda x: x[0]}, "positive tolerance"),
    ({"goal_weights": [0.0, 0.0]}, "goal_weights"),
    ({"state_low": [None, 0.5]}, "start"),
    ({"path": ([0.0, 1.0], [[0.0, 0.0]], [[0.0]])}, "path states"),
])
def test_invalid_inputs_are_explained(pendulum, kwargs, match):
    with pytest.raises(ValueError, match=match):
        optimal_cost(pendulum, START, GOAL, **kwargs)


def test_non_symbolic_system_is_refused(pendulum):
    import dataclasses

    from rrtcolearn.systems.base import System

    plain = System(**{f.name: getattr(pendulum, f.name) for f in dataclasses.fields(System)})
    with pytest.raises(ValueError, match="SymbolicSystem"):
        optimal_cost(plain, START, GOAL)

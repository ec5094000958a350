"""The finite-horizon LQ law with the plan's own running cost (`lqr.GoalLQ`) and its tails in
the goal shortcuts (`improve.goal.lq_tail`), checked on the double integrator against the
closed form of its fixed-final-state cost (Webb and van den Berg 2013, written out here), a
plain RK4 written here, and the plan's step check."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

import rrtcolearn.planning.improve.goal as goal_module
from rrtcolearn.evaluate import step_check
from rrtcolearn.planning.improve import goal_shortcuts
from rrtcolearn.planning.lqr import GoalLQ, build_goal_lqr
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import PlannerSettings, RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make

DT, W = 0.01, 1.0
X0, GOAL = np.array([-1.0, 0.3]), np.array([1.0, 0.0])


def closed_form(x0, x1, T, w=W):
    """w T + the least effort (u^2 / 2 integrated) of q'' = u from x0 to x1 in time T."""
    dq, v0, v1 = x1[0] - x0[0], x0[1], x1[1]
    return w * T + 6 * dq**2 / T**3 - 6 * dq * (v0 + v1) / T**2 + 2 * (v0**2 + v0 * v1
                                                                         + v1**2) / T


def rk4_held(x, u, dt):
    """One RK4 step of q'' = u under the held input u."""
    f = lambda z: np.array([z[1], u])  # noqa: E731
    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


@pytest.fixture(scope="module")
def system():
    return make("double_integrator")


def _problem(system, tolerance=0.05, **kw):
    return PlanningProblem.create(system, X0, GOAL, tolerance, **kw)


def _law(system, problem):
    lqr = build_goal_lqr(problem, DT)
    return lqr, GoalLQ(lqr, np.eye(1), W)


def test_the_predicted_cost_is_the_closed_form(system):
    _, lq = _law(system, _problem(system))
    predicted = lq.predicted(X0, 400)
    for T in (1.0, 2.0, 4.0):
        want = closed_form(X0, GOAL, T)
        assert predicted[round(T / DT)] == pytest.approx(want, rel=0.01)
    assert np.isinf(predicted[0])


def test_a_run_reaches_the_goal_at_the_optimum_and_replays_by_hand(system):
    problem = _problem(system)
    _, lq = _law(system, problem)
    predicted = lq.predicted(X0, 600)
    j = int(np.argmin(predicted))
    grid = np.linspace(0.2, 6.0, 5801)  # the closed form's optimum, brute force
    best = min(closed_form(X0, GOAL, T) for T in grid)
    T_best = grid[np.argmin([closed_form(X0, GOAL, T) for T in grid])]
    assert j * DT == pytest.approx(T_best, abs=0.05)
    box = (np.full(2, -np.inf), np.full(2, np.inf))
    out = lq.run(X0, j, box, lambda s: np.linalg.norm(s - GOAL, axis=1) <= 0.05)
    assert out.reached
    x, cost = X0.copy(), 0.0
    for k, u in enumerate(out.inputs[:, 0]):
        x = rk4_held(x, u, DT)
        cost += (W + 0.5 * u**2) * DT
        np.testing.assert_allclose(x, out.states[k + 1], atol=1e-12)
    assert np.linalg.norm(x - GOAL) <= 0.05
    # it enters the region a little early, so a little cheaper than the full transfer
    assert 0.9 * best <= cost <= 1.01 * best


def test_the_compiled_run_is_the_time_varying_law(system):
    """`GoalLQ.run` compiled (`integrate.closed_loop_jit`, a gain per step) and in numpy (a
    System without the kernel) give the same run, whose input at step i is the law of the
    horizon j's table row j - i, recomputed here from the tables, clipped to the box."""
    import dataclasses

    problem = _problem(system, u_max=1.5)
    lqr, lq = _law(system, problem)
    plain = dataclasses.replace(problem, system=dataclasses.replace(system,
                                                                    closed_loop_jit=None))
    lq_plain = GoalLQ(dataclasses.replace(lqr, problem=plain), np.eye(1), W)
    box = (np.full(2, -np.inf), np.full(2, np.inf))
    never = lambda s: np.zeros(len(s), bool)  # noqa: E731
    j = 250
    a, b = lq.run(X0, j, box, never), lq_plain.run(X0, j, box, never)
    assert a.end == b.end == "timeout" and len(a.inputs) == j
    np.testing.assert_allclose(a.states, b.states, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.inputs, b.inputs, rtol=0, atol=1e-12)
    want = [np.clip(lqr.u_e - lq.K[j - i] @ (x - lqr.x_e) - lq.k[j - i], -1.5, 1.5)
            for i, x in enumerate(a.states[:-1])]
    np.testing.assert_allclose(a.inputs, want, rtol=0, atol=1e-12)
    assert np.abs(a.inputs).max() == pytest.approx(1.5)  # the box clipped some inputs
    with pytest.raises(ValueError, match="at least one step"):
        lq.run(X0, 0, box, never)


def _random_plan(system, seed=0):
    """A plan on random controls and the Bryson LQR connection alone (no learned
    functions), its inputs in |u| <= 2."""
    problem = _problem(system, tolerance=0.1, u_max=2.0)
    planner = RRTCoLearn(problem, None, PlannerSettings(control_edges=True, max_duration=0.5,
                                                        goal_lqr=True, dt=DT))
    plan = planner.solve(TerminationCondition(None, 3000), seed)
    assert plan.solved
    return planner, problem, plan


def test_goal_shortcuts_take_the_lq_tail_and_the_path_replays(system):
    planner, problem, plan = _random_plan(system)
    got = goal_shortcuts(planner, plan)
    assert got.extra["shortcuts"]["lq_tail"] == 1
    grid = np.linspace(0.2, 6.0, 5801)
    best = min(closed_form(X0, GOAL, T) for T in grid)
    assert got.path_cost < plan.path_cost
    assert got.path_cost <= 1.05 * best
    check = step_check(problem, got)
    assert check["resolved"] and check["replays"] and check["valid"]
    # every held-input edge of the path replays by hand to its recorded end and cost
    x = np.array(problem.start)
    total = 0.0
    for e in got.edges():
        assert e["control"] is not None  # random controls, LQR chains: held inputs only
        u = float(e["control"][0])
        for _ in range(round(e["duration"] / DT)):
            x = rk4_held(x, u, DT)
        total += (W + 0.5 * u**2) * e["duration"]
        np.testing.assert_allclose(x, e["to"], atol=1e-9)
    assert total == pytest.approx(got.path_cost, rel=1e-9)


def _never_resolved(monkeypatch) -> list[int]:
    """Every tail's end gap made infinite (never resolved); the horizons of the law's runs
    are appended to the list returned."""
    runs = []
    run = goal_module.GoalLQ.run

    def counted(self, *a, **k):
        runs.append(a[1])
        return run(self, *a, **k)
    monkeypatch.setattr(goal_module.GoalLQ, "run", counted)
    monkeypatch.setattr(goal_module, "state_gaps", lambda p, full, half: np.full(len(full),
                                                                                 np.inf))
    return runs


def test_a_tail_the_step_does_not_resolve_is_not_kept(system, monkeypatch):
    planner, _, plan = _random_plan(system)
    runs = _never_resolved(monkeypatch)
    got = goal_shortcuts(planner, plan)
    assert got.extra["shortcuts"]["lq_tail"] == 0
    assert 3 <= len(runs) <= goal_module.LQ_TRIES
    # each run after an unresolved one is shorter than LQ_SHORTER of it
    assert all(b <= goal_module.LQ_SHORTER * a + 1 for a, b in pairwise(runs))


def test_the_horizon_is_bisected_between_resolved_and_unresolved(system, monkeypatch):
    """Runs longer than ``longest`` steps made unresolved: after the first resolved run the
    horizons lie between the longest resolved and the shortest unresolved run, and the tail
    kept is resolved, longer and cheaper than that first resolved run's."""
    planner, _, plan = _random_plan(system)
    horizons, lengths = [], []
    run = goal_module.GoalLQ.run

    def counted(self, *a, **k):
        out = run(self, *a, **k)
        horizons.append(a[1])
        lengths.append(len(out.inputs))
        return out
    monkeypatch.setattr(goal_module.GoalLQ, "run", counted)
    longest = 120
    monkeypatch.setattr(goal_module, "state_gaps", lambda p, full, half: np.full(
        len(full), 0.0 if lengths[-1] <= longest else np.inf))
    got = goal_shortcuts(planner, plan)
    assert got.extra["shortcuts"]["lq_tail"] == 1
    first = next(i for i, n in enumerate(lengths) if n <= longest)
    assert first >= 1 and len(lengths) > first + 1  # the bisection ran
    for i in range(first + 1, len(lengths)):
        lo = max(h for h, n in zip(horizons[:i], lengths, strict=False) if n <= longest)
        hi = min(h for h, n in zip(horizons[:i], lengths, strict=False) if n > longest)
        assert lo < horizons[i] <= (lo + hi) // 2
    assert max(n for n in lengths if n <= longest) > lengths[first]
    monkeypatch.setattr(goal_module, "LQ_TRIES", first + 1)  # stopped at the first resolved
    assert got.path_cost < goal_shortcuts(planner, plan).path_cost


def test_a_tail_whose_half_step_replay_strays_midway_is_not_kept(system, monkeypatch):
    """The chain is judged at each of its steps, not at its end alone: the half step's
    replay moved away by twice the tolerance at one state in the middle (its end untouched)
    is not resolved."""
    planner, problem, plan = _random_plan(system)
    real = goal_module.propagate_controls

    def strays(*a, **k):
        traj = real(*a, **k).copy()
        traj[2 * (len(traj) // 4), 0] += 2 * problem.goal_tolerance  # a state at the step
        return traj
    monkeypatch.setattr(goal_module, "propagate_controls", strays)
    assert goal_shortcuts(planner, plan).extra["shortcuts"]["lq_tail"] == 0
    monkeypatch.setattr(goal_module, "propagate_controls", real)
    assert goal_shortcuts(planner, plan).extra["shortcuts"]["lq_tail"] == 1


def test_a_run_stops_trying_the_law_where_it_never_keeps_a_tail(system, monkeypatch):
    """`LQ_PATIENCE`: calls without a kept tail stop the law after LQ_PATIENCE calls; the
    record belongs to the run (a plain solve begins a new one)."""
    planner, _, plan = _random_plan(system)
    runs = _never_resolved(monkeypatch)
    per_call = []
    for _ in range(goal_module.LQ_PATIENCE + 2):
        before = len(runs)
        goal_shortcuts(planner, plan)
        per_call.append(len(runs) - before)
    assert all(per_call[:goal_module.LQ_PATIENCE]) and per_call[goal_module.LQ_PATIENCE:] == [0, 0]
    planner.solve(TerminationCondition(None, 3000), 0)  # a new run of the query
    before = len(runs)
    goal_shortcuts(planner, plan)
    assert len(runs) - before == per_call[0]

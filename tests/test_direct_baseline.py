"""The direct-method learning RRT (collocation with CasADi + IPOPT), checked independently."""

from __future__ import annotations

import numpy as np
import pytest
from tests import references

from rrtcolearn.baselines.direct import (
    casadi_available,
    dataset_points,
    execute,
    execute_controls,
    fit_direct_model,
    generate_direct_dataset,
    get_solver,
    load_direct_dataset,
    polish,
    save_direct_dataset,
    solve_direct_rrt,
)
from rrtcolearn.evaluate import replay
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems.pendulum import make_pendulum

START, GOAL = [-np.pi, 0.0], [0.0, 0.0]


@pytest.fixture(scope="module")
def dataset():
    return generate_direct_dataset(400, seed=3)


@pytest.fixture(scope="module")
def model(dataset):
    return fit_direct_model(dataset[0], intermediate=True)


def _quad_cost(sol, w: float, n: int = 200_001) -> float:
    """Integral of w + u^2/2 of the solution's own control function, by the trapezoidal rule."""
    t = np.linspace(0.0, sol.duration, n)
    v = w + 0.5 * sol.control_at(t) ** 2
    return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)))


def _fine_end(sol, steps: int = 20_000) -> np.ndarray:
    """End state of the collocation control integrated with a fine RK4 (exact T)."""
    t = sol.duration * (np.arange(steps) + 0.5) / steps
    return execute_controls(sol.x0, sol.control_at(t), sol.duration / steps)[-1]


def test_casadi_available():
    assert casadi_available()


@pytest.mark.parametrize("w, u_max", [(1.0, None), (1.0, 2.0), (0.1, 1.0)])
def test_single_solve_boundary_conditions_and_cost(w, u_max):
    solver = get_solver()
    x0, x1 = np.array([-np.pi, 0.0]), np.array([-np.pi + 0.4, 0.6])
    sol = solver.solve(x0, x1, time_weight=w, u_max=u_max)
    assert sol.success, sol.status
    np.testing.assert_allclose(sol.states[0], x0, atol=1e-12)
    np.testing.assert_allclose(sol.states[-1], x1, atol=1e-12)
    assert 0.05 <= sol.duration
    # the NLP's cost is the integral of w + u^2/2 of its own (piecewise quadratic) control
    assert sol.cost == pytest.approx(_quad_cost(sol, w), rel=1e-7)
    assert sol.node_costs(w)[-1] == pytest.approx(sol.cost, rel=1e-12)
    # and the control really drives x0 to x1 (Hermite-Simpson is 4th order)
    assert np.linalg.norm(_fine_end(sol) - x1) < 1e-4
    if u_max is not None:
        assert np.abs(sol.controls).max() <= u_max + 1e-6
        assert np.abs(sol.mid_controls).max() <= u_max + 1e-6


def test_execution_gap_and_polish():
    solver = get_solver()
    x0, x1 = np.array([-2.5, 0.3]), np.array([-1.6, 1.0])
    sol = solver.solve(x0, x1)
    assert sol.success
    u, states = execute(sol, 0.01)
    assert len(u) == max(1, round(sol.duration / 0.01))
    # the compiled execution is a plain RK4 (tests/references.py) of the paper's pendulum
    # theta'' = sin(theta) + u, each input held for one step
    x, want = x0, []
    for uk in u:
        x = references.hold(references.pendulum, x, [uk], 0.01, 1)[-1]
        want.append(x)
    np.testing.assert_allclose(states, np.array(want), rtol=0, atol=1e-10)
    raw_gap = np.linalg.norm(states[-1] - x1)
    fixed = polish(solver, sol, time_weight=1.0, u_max=None)
    assert fixed.duration == pytest.approx(round(sol.duration / 0.01) * 0.01, abs=1e-9)
    assert fixed.cost >= sol.cost - 1e-9  # T fixed: no better than the free-time optimum
    gap = np.linalg.norm(execute(fixed, 0.01)[1][-1] - x1)
    assert gap < 1e-3
    assert gap <= raw_gap + 1e-12


def test_dataset(dataset, tmp_path):
    data, stats = dataset
    p = len(data["cost"])
    assert stats["pairs"] == 400 and stats["solved"] == p > 50
    assert 0.9 <= stats["success_rate"] <= 1.0
    assert stats["cpu_s_per_solve"] > 0 and stats["cpu_s_per_point"] >= stats["cpu_s_per_solve"]
    assert (data["cost"] <= 2.0).all() and (data["cost"] > 0).all()
    assert np.linalg.norm(data["x1"] - data["x0"], axis=1).max() <= 1.5 + 1e-12
    np.testing.assert_array_equal(data["states"][:, 0], data["x0"])
    np.testing.assert_array_equal(data["states"][:, -1], data["x1"])
    assert data["controls"].shape == (p, 21) and data["mid_controls"].shape == (p, 20)
    np.testing.assert_allclose(data["node_cost"][:, -1], data["cost"], rtol=1e-10)
    # cost >= w T with w = 1
    assert (data["cost"] >= data["duration"] - 1e-9).all()
    X, y, _ = dataset_points(data, intermediate=True)
    assert X.shape == (20 * p, 4) and np.all(np.diff(y.reshape(p, 20), axis=1) > 0)
    # stored and reloaded unchanged
    save_direct_dataset(tmp_path / "d.npz", data, stats)
    back = load_direct_dataset(tmp_path / "d.npz")
    for k, v in data.items():
        np.testing.assert_array_equal(back[k], v)
    assert back["stats"]["solved"] == p


def test_dataset_seeded():
    a, sa = generate_direct_dataset(20, seed=11)
    b, sb = generate_direct_dataset(20, seed=11)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert sa["solved"] == sb["solved"]


def test_model_thresholds(dataset):
    data = dataset[0]
    pairs = fit_direct_model(data)
    assert pairs.n_points == len(data["cost"]) and pairs.validity.threshold > 0
    # query_valid agrees with brute force: V = summed distance to the 3 nearest <= threshold
    rng = np.random.default_rng(0)
    X = dataset_points(data)[0]
    Q = X[rng.integers(0, len(X), 200)] + rng.normal(0.0, 0.2, (200, 4))
    d = np.sort(np.linalg.norm(Q[:, None] - X[None], axis=2), axis=1)[:, :3].sum(axis=1)
    threshold = float(np.median(d))
    fixed = fit_direct_model(data, validity_threshold=threshold)
    assert fixed.validity.threshold == threshold
    rows, J = fixed.query_valid(Q)
    np.testing.assert_array_equal(rows, np.flatnonzero(d <= threshold))
    np.testing.assert_allclose(J, fixed.cost_to_go.predict(Q[rows]))
    assert 0 < rows.size < 200 and np.all((J > 0) & (J <= 2.0))
    with pytest.raises(ValueError):
        fit_direct_model(data, validity_threshold="median")


def _problem(tol, u_max=None, obstacles=()):
    return PlanningProblem.create(make_pendulum(), START, GOAL, tol, u_max=u_max,
                                  obstacles=list(obstacles))


def _limit(max_iterations=None):
    return TerminationCondition(120.0, max_iterations, 30.0)


def test_swing_up(model):
    prob = _problem(0.2)
    res = solve_direct_rrt(model, prob, _limit(), 0)
    assert res.solved and res.status == "exact", res.extra
    m = replay(prob, res)
    assert m["reaches_goal"]
    np.testing.assert_allclose([e["duration"] for e in res.edges()], 0.01)
    assert res.extra["resim_gap"] is not None and res.extra["edge_gap_max"] < 0.1
    assert res.final_goal_distance == pytest.approx(m["final_goal_distance"])
    # the tree stores re-simulated states, so the path ends where the re-simulation does
    assert m["final_goal_distance"] <= 0.2
    assert res.nodes == res.graph_states < res.tree.n_nodes + res.iterations
    again = solve_direct_rrt(model, prob, _limit(), 0)
    assert (again.iterations, again.nodes) == (res.iterations, res.nodes)
    np.testing.assert_array_equal(again.tree.controls[: again.tree.n_nodes],
                                  res.tree.controls[: res.tree.n_nodes])


def test_torque_limit_and_obstacle(model):
    sys = make_pendulum()
    block = {"type": "box", "low": [-3.0, 1.0], "high": [-2.4, 2.0]}
    prob = _problem(0.2, 3.0, [block])
    res = solve_direct_rrt(model, prob, _limit(), 1)
    assert res.solved, res.extra
    assert res.extra["collision"] > 0  # the obstacle did reject edges
    assert res.max_abs_u <= 3.0 + 1e-12
    x = np.concatenate(res.tree.trajectories[1:])
    x[:, 0] -= 2 * np.pi * np.floor((x[:, 0] + 1.5 * np.pi) / (2 * np.pi))
    inside = np.all((x >= block["low"]) & (x <= block["high"]), axis=1)
    assert not inside.any()
    assert np.linalg.norm(res.tree.states[res.path_nodes[-1]] - GOAL) <= 0.2
    assert replay(prob, res)["reaches_goal"]
    assert sys.name == "pendulum"


def test_iteration_limit_without_solution(model):
    res = solve_direct_rrt(model, _problem(0.1), TerminationCondition(10.0, 1), 0)
    assert res.iterations == 1 and not res.solved
    assert res.status in ("approximate", "timeout")
    with pytest.raises(ValueError):
        solve_direct_rrt(model, _problem(0.1), _limit(), 0, polish_edges="sometimes")

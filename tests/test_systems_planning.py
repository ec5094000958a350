"""Planning beyond the pendulum: weighted, angle-aware distances, recommended configurations,
and the planner options for higher dimensions, checked against independent re-simulation."""

from __future__ import annotations

import numpy as np
import pytest

from rrtcolearn import pipeline
from rrtcolearn.config import Config, load_config
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.systems import make, recommended_config


def di_rhs(z: np.ndarray, w: float) -> np.ndarray:
    """The double integrator's state+costate+cost ODE, written out by hand:
    H* = w + l_q v - l_v^2 / 2, u* = -l_v."""
    _q, v, lq, lv, _c = z
    return np.array([v, -lv, 0.0, -lq, w + 0.5 * lv * lv])


def rk4(z: np.ndarray, w: float, dt: float, steps: int) -> np.ndarray:
    for _ in range(steps):
        k1 = di_rhs(z, w)
        k2 = di_rhs(z + 0.5 * dt * k1, w)
        k3 = di_rhs(z + 0.5 * dt * k2, w)
        k4 = di_rhs(z + dt * k3, w)
        z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return z


@pytest.fixture(scope="module")
def di_model(tmp_path_factory):
    cfg = load_config(overrides=['system.name="double_integrator"',
                                 "generate.n_simulations=6000", "clean.k_max=500"])
    run = tmp_path_factory.mktemp("di")
    pipeline.generate(cfg, run)
    pipeline.clean(cfg, run)
    return pipeline.fit(cfg, run)


def di_cost_lower_bound(x0, x1, w: float) -> float:
    """The least cost w T + int u^2/2 of any double-integrator path from x0 to x1, by the
    textbook minimum-energy control for a fixed duration T (int u^2 dt = 12 e^2 / T^3 +
    dv^2 / T with e = dq - T (v0 + v1) / 2, dv = v1 - v0), minimised over T on a fine grid
    (an under-estimate of the minimum by less than the grid's spacing times w)."""
    dq, v0, v1 = x1[0] - x0[0], x0[1], x1[1]
    T = np.linspace(1e-3, 20.0, 200_001)
    e, dv = dq - T * (v0 + v1) / 2, v1 - v0
    return float(np.min(w * T + 0.5 * (12 * e**2 / T**3 + dv**2 / T))) - w * 1e-4


def test_the_lower_bound_is_attained_by_the_closed_form():
    """The bound's formula against the package's closed-form optimum at random pairs."""
    from rrtcolearn.systems.double_integrator import optimal_cost

    rng = np.random.default_rng(0)
    x0, x1 = rng.uniform(-1, 1, (20, 2)), rng.uniform(-1, 1, (20, 2))
    exact = optimal_cost(x0, x1, 1.0)
    for a, b, c in zip(x0, x1, exact, strict=True):
        if np.isfinite(c):
            assert di_cost_lower_bound(a, b, 1.0) == pytest.approx(c, abs=2e-4)


@pytest.mark.parametrize("options", [
    [],  # derived settings, goal connections switched on by the planner when it stalls
    ["plan.goal_connect=false", "plan.goal_funnel=0"],  # no goal connection
    ["plan.control_samples=8", "plan.extend_distance=0.5", "plan.max_candidates=4"],
    ["plan.goal_connect=true", "plan.goal_funnel=0"],  # the last edge by shooting
    # ... from along a funnel extremal
    ["plan.goal_funnel=500", "plan.goal_bias=0.5", "plan.goal_connect=false"],
])
def test_double_integrator_plans_resimulate(di_model, options):
    cfg = load_config(overrides=['system.name="double_integrator"', *options])
    p = pipeline.plan(di_model, [-1.0, 0.0], [1.0, 0.0], 0.1, seed=2, config=cfg,
                      time_limit=None, max_iterations=20_000)
    assert p.solved
    d = p.to_dict()
    w, dt = d["time_weight"], d["dt"]
    total = 0.0
    for e in d["path"]:
        x, lam = np.array(e["from"]), np.array(e["costate"])
        assert abs(w + lam[0] * x[1] - 0.5 * lam[1] ** 2) < 1e-9  # H* = 0 at the start
        z = rk4(np.r_[x, lam, 0.0], w, dt, round(e["duration"] / dt))
        np.testing.assert_allclose(z[:2], e["to"], atol=1e-9)
        assert z[4] == pytest.approx(e["cost"], abs=1e-9)
        total += e["cost"]
    assert d["path_cost"] == pytest.approx(total)
    assert np.linalg.norm(np.array(d["path"][-1]["to"]) - [1.0, 0.0]) <= 0.1
    # no path is cheaper than the optimal one between its ends (independent of the planner)
    assert d["path_cost"] >= di_cost_lower_bound(d["start"], d["path"][-1]["to"], w)
    if "plan.goal_funnel=0" in options and "plan.goal_connect=false" in options:
        assert "goal_connected" not in d
    if "plan.goal_connect=true" in options:
        assert "goal_connected" in d
    if "plan.goal_funnel=500" in options:
        assert d["connection"] == "funnel" and d["funnel_states"] > 0


def test_pendulum_distances_are_the_papers():
    assert np.array_equal(make("pendulum").metric_scale, [1.0, 1.0])
    scale = make("cartpole").metric_scale
    system = make("cartpole")
    np.testing.assert_allclose(scale * (system.state_high - system.state_low), 2 * np.pi)


def test_queries_near_an_angle_seam_find_neighbours_across_it():
    # the pendulum's angle coordinate 0 in [-3pi/2, pi/2); data just above -3pi/2, query just
    # below pi/2: one turn apart, so the same problem shifted by 2*pi
    from rrtcolearn.data.dataset import Dataset

    rng = np.random.default_rng(0)
    x0 = np.c_[-1.5 * np.pi + 0.01 + 0.02 * rng.random(50), rng.random(50)]
    x1 = x0 + 0.1
    data = Dataset(x0, x1, np.ones(50), np.ones((50, 1)), np.ones(50), x0, np.arange(50))
    query = np.array([[0.5 * np.pi - 0.02, 0.5, 0.5 * np.pi + 0.08, 0.6]])
    system = make("pendulum")
    kwargs = dict(n_neighbors=3, validity_threshold=0.5)
    flat = LearnedFunctions(periodic=False, **kwargs).fit(data, system)
    assert not flat.query(query)[2][0]
    wrapped = LearnedFunctions(**kwargs).fit(data, system)
    assert wrapped.query(query)[2][0]
    rows, _, idx = wrapped.query_valid(query)
    assert rows.tolist() == [0]
    assert (wrapped.source_[idx] < 50).all()  # padded rows point back at their data rows


def test_recommended_configuration_sits_under_the_users():
    assert load_config() == Config()  # the pendulum's are the package defaults
    assert recommended_config("pendulum") == {}
    # the registry states the standard query only; every learner and planner setting is
    # left to the library (derived)
    for name in ("cartpole", "acrobot", "double_integrator", "quadrotor"):
        assert set(recommended_config(name)) <= {"name", "plan"}
        assert set(recommended_config(name).get("plan", {})) <= {
            "goal_tolerance", "wrap_goal", "time_limit", "start", "goal"}
    cfg = load_config(overrides=['system.name="cartpole"'])
    assert cfg.name == "cartpole-swingup" and cfg.plan.goal_tolerance == 0.3
    assert cfg.plan.control_samples is None and cfg.learn.validity_threshold is None
    cfg = load_config(overrides=['system.name="cartpole"', "plan.goal_tolerance=0.2",
                                 'name="mine"'])
    assert cfg.name == "mine" and cfg.plan.goal_tolerance == 0.2
    assert cfg.plan.wrap_goal == recommended_config("cartpole")["plan"]["wrap_goal"]

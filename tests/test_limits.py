"""Input limits end to end: configured limits saturate the optimal control, plans stay within
them when re-simulated with hand-written saturated RK4, and a tree that cannot grow stops early
with a diagnosis."""

from __future__ import annotations

import json

import numpy as np
import pytest
import sympy
from tests.test_constraints import resimulated_states
from tests.test_planner import check_plan_file

from rrtcolearn import pipeline, systems
from rrtcolearn.config import load_config
from rrtcolearn.errors import ConfigError
from rrtcolearn.planning.rrt import CONTROLS_AFTER

U_MAX = 1.0


def rk4(rhs, z: np.ndarray, dt: float, steps: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Plain RK4 of ``rhs(z) -> (z', u)``; the end state and the input at every stage."""
    inputs = []
    for _ in range(steps):
        k1, u1 = rhs(z)
        k2, u2 = rhs(z + 0.5 * dt * k1)
        k3, u3 = rhs(z + 0.5 * dt * k2)
        k4, u4 = rhs(z + dt * k3)
        inputs += [u1, u2, u3, u4]
        z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return z, inputs


def pendulum_saturated(w: float, u_max: float):
    """The pendulum's state+costate+cost ODE under u* = clip(-l_om, -u_max, u_max), by hand:
    H = w + u^2/2 + l_th omega + l_om (sin theta + u)."""
    def rhs(z):
        th, om, lth, lom, _ = z
        u = min(max(-lom, -u_max), u_max)
        return np.array([om, np.sin(th) + u, -lom * np.cos(th), -lth, w + 0.5 * u * u]), [u]
    return rhs


def resimulate(plan: dict, rhs, hamiltonian, plain=None) -> float:
    """Re-integrate every path edge from its costate (an extremal) or under its held input
    (a random-control edge, by the plain dynamics ``plain(x, u)``, the pendulum's by
    default); the largest |input| met on the way. Each extremal must start on H* = 0; each
    edge must land on the next node."""
    if plain is None:
        def plain(x, u):
            return np.array([x[1], np.sin(x[0]) + u[0]])
    dt = plan["dt"]
    worst = 0.0
    for e in plan["path"]:
        if e["costate"] is None:  # a control edge: the input held, x' = plain(x, u)
            u = np.array(e["control"], dtype=float)
            x = np.array(e["from"], dtype=float)
            for _ in range(round(e["duration"] / dt)):
                k1 = plain(x, u)
                k2 = plain(x + 0.5 * dt * k1, u)
                k3 = plain(x + 0.5 * dt * k2, u)
                x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + plain(x + dt * k3, u))
            np.testing.assert_allclose(x, e["to"], atol=1e-9)
            np.testing.assert_allclose((plan["time_weight"] + 0.5 * u @ u) * e["duration"],
                                       e["cost"], rtol=1e-9)
            worst = max(worst, float(np.abs(u).max()))
            continue
        x, lam = np.array(e["from"]), np.array(e["costate"])
        assert abs(hamiltonian(x, lam)) < 1e-9
        z, inputs = rk4(rhs, np.r_[x, lam, 0.0], dt, round(e["duration"] / dt))
        np.testing.assert_allclose(z[: len(x)], e["to"], atol=1e-9)
        np.testing.assert_allclose(z[-1], e["cost"], rtol=1e-9, atol=1e-12)
        worst = max(worst, max(abs(v) for u in inputs for v in u))
    return worst


@pytest.fixture(scope="module")
def saturated_pendulum(tmp_path_factory):
    """The paper's pendulum at w = 1 with |u| <= 1: no unconstrained extremal leaves rest
    within the limit there, the saturated ones do."""
    cfg = load_config(overrides=[f"system.u_max={U_MAX}", "generate.n_simulations=10000",
                                 "clean.k_max=1000"])
    run = tmp_path_factory.mktemp("sat")
    pipeline.generate(cfg, run)
    pipeline.clean(cfg, run)
    return pipeline.fit(cfg, run)


def test_saturated_pendulum_plans_within_the_limit(saturated_pendulum, tmp_path):
    model = saturated_pendulum
    assert model.system.input_limited
    w = model.config.system.time_weight
    rhs = pendulum_saturated(w, U_MAX)

    def h_star(x, lam):
        u = min(max(-lam[1], -U_MAX), U_MAX)
        return w + 0.5 * u * u + lam[0] * x[1] + lam[1] * (np.sin(x[0]) + u)

    solved = 0
    for seed in range(3):
        p = pipeline.plan(model, [-np.pi, 0.0], [0.0, 0.0], 0.1, seed=seed, time_limit=None,
                          max_iterations=30_000)
        solved += p.solved
        path = tmp_path / f"plan{seed}.json"
        pipeline.write_plan(p, path)
        d = pipeline.read_plan(path)
        assert d["limit_mode"] == "saturate" and d["u_max"] == U_MAX
        assert d["input_low"] == [-U_MAX] and d["input_high"] == [U_MAX]
        if p.solved:
            worst = resimulate(d, rhs, h_star)
            assert worst <= U_MAX and d["max_abs_u"] <= U_MAX
            # a swing-up under |u| <= 1 from rest rides the limit
            assert worst == U_MAX
    assert solved >= 2


def test_saturated_model_refuses_another_limit(saturated_pendulum):
    with pytest.raises(ConfigError, match="train a model"):
        pipeline.plan(saturated_pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1, u_max=2.0,
                      time_limit=None, max_iterations=10)
    # the same limit, or none given, plans with the model's own
    for u_max in (U_MAX, None):
        p = pipeline.plan(saturated_pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1, u_max=u_max,
                          time_limit=None, max_iterations=10)
        assert p.to_dict()["u_max"] == U_MAX


def test_truncation_at_w1_stalls_with_a_diagnosis(tmp_path):
    """The old approach: unconstrained extremals from rest break |u| <= 1 at once when w = 1,
    so the data have nothing near the start; the paper's planner (learned steering only)
    says so and stops early. With random-control edges (the default) the same model plans."""
    cfg = load_config(overrides=[f"system.u_max={U_MAX}", "system.limit_mode='truncate'",
                                 "generate.n_simulations=4000", "clean.k_max=300",
                                 "plan.stall_iterations=2000", "plan.control_edges=false"])
    pipeline.generate(cfg, tmp_path)
    pipeline.clean(cfg, tmp_path)
    model = pipeline.fit(cfg, tmp_path)
    assert not model.system.input_limited
    p = pipeline.plan(model, [-np.pi, 0.0], [0.0, 0.0], 0.1, seed=0, time_limit=None,
                      max_iterations=30_000)
    assert not p.solved and p.extra["stalled"] and p.iterations == 2000
    assert p.nodes == 1 and p.to_dict()["limit_mode"] == "truncate"
    assert "invalid query" in p.extra["diagnosis"] and "saturate" in p.extra["diagnosis"]
    assert "no progress toward the goal" in p.extra["diagnosis"]  # the tree never left the start
    assert sum(p.extra["outcomes"].values()) == 2000
    # the default planner switches random-control edges on when the learned steering stalls
    q = pipeline.plan(model, [-np.pi, 0.0], [0.0, 0.0], 0.1, seed=0, time_limit=None,
                      max_iterations=30_000,
                      config=cfg.model_copy(update={"plan": cfg.plan.model_copy(
                          update={"control_edges": None})}))
    assert q.solved and q.extra["connections_switched_on"]["controls"] == CONTROLS_AFTER
    d = q.to_dict()
    check_plan_file(d)
    assert any(e["control"] is not None for e in d["path"])
    _, u = resimulated_states(d)
    assert np.abs(u).max() <= U_MAX + 1e-12


@pytest.mark.parametrize("overrides, match", [
    (["system.u_max=-1"], "positive"),
    (["system.u_max=[1.0, 0.0]"], "positive"),
    (["system.u_max=1", "system.u_low=[-1]", "system.u_high=[1]"], "not both"),
    (["system.u_low=[-1]"], "together"),
    (["system.u_low=[1]", "system.u_high=[0]"], "u_low < u_high"),
    (["system.u_max=[1.0]", "system.limit_mode='truncate'"], "single symmetric"),
])
def test_limit_configuration_is_validated(overrides, match):
    with pytest.raises(ConfigError, match=match):
        load_config(overrides=overrides)


def test_limits_per_input_must_match_the_system():
    cfg = load_config(overrides=["system.u_max=[1.0, 2.0]"])
    with pytest.raises(ConfigError, match="1 or 1 values"):
        pipeline.system_from_config(cfg)


# --------------------------------------------------------------------------- two inputs

LOW, HIGH = (-1.0, -0.5), (0.5, 1.0)


def make_two_input():
    """x' = 0.5 sin(y) + u1, y' = 0.5 sin(x) + u2 with u1 in [-1, 0.5], u2 in [-0.5, 1]."""
    from rrtcolearn.systems.symbolic import build_system

    x, y, u1, u2 = sympy.symbols("x y u1 u2", real=True)
    return build_system(
        "two_input_test", [x, y], [u1, u2], [sympy.sin(y) / 2, sympy.sin(x) / 2],
        [[1, 0], [0, 1]], state_low=[-2.0, -2.0], state_high=[2.0, 2.0],
        input_low=LOW, input_high=HIGH, defaults={"start": [-1.0, -1.0], "goal": [1.0, 1.0]})


def two_input_saturated(w: float):
    """Its state+costate+cost ODE by hand: u_i = clip(-l_i), l_x' = -l_y cos(x) / 2,
    l_y' = -l_x cos(y) / 2."""
    def rhs(z):
        x, y, lx, ly, _ = z
        u1 = min(max(-lx, LOW[0]), HIGH[0])
        u2 = min(max(-ly, LOW[1]), HIGH[1])
        return np.array([0.5 * np.sin(y) + u1, 0.5 * np.sin(x) + u2, -0.5 * ly * np.cos(x),
                         -0.5 * lx * np.cos(y), w + 0.5 * (u1 * u1 + u2 * u2)]), [u1, u2]
    return rhs


def test_two_input_asymmetric_limits_plan_and_resimulate(tmp_path, monkeypatch):
    # registered for this test only: other tests run every registered system
    monkeypatch.setattr(systems, "_REGISTRY", dict(systems._REGISTRY))
    monkeypatch.setattr(systems, "_CONFIGS", dict(systems._CONFIGS))
    systems.register("two_input_test", make_two_input)
    cfg = load_config(overrides=['system.name="two_input_test"', "generate.n_simulations=6000",
                                 "clean.k_max=500"])
    pipeline.generate(cfg, tmp_path)
    pipeline.clean(cfg, tmp_path)
    model = pipeline.fit(cfg, tmp_path)
    low, high = model.system.input_limits()
    assert low.tolist() == list(LOW) and high.tolist() == list(HIGH)
    w = cfg.system.time_weight
    rhs = two_input_saturated(w)

    def h_star(x, lam):
        u1 = min(max(-lam[0], LOW[0]), HIGH[0])
        u2 = min(max(-lam[1], LOW[1]), HIGH[1])
        return (w + 0.5 * (u1 * u1 + u2 * u2) + lam[0] * (0.5 * np.sin(x[1]) + u1)
                + lam[1] * (0.5 * np.sin(x[0]) + u2))

    p = pipeline.plan(model, [-1.0, -1.0], [1.0, 1.0], 0.1, seed=0, time_limit=None,
                      max_iterations=20_000)
    assert p.solved
    d = json.loads(json.dumps(p.to_dict()))
    assert d["limit_mode"] == "saturate" and d["u_max"] is None
    assert d["input_low"] == list(LOW) and d["input_high"] == list(HIGH)
    def plain(x, u):
        return np.array([0.5 * np.sin(x[1]) + u[0], 0.5 * np.sin(x[0]) + u[1]])

    resimulate(d, rhs, h_star, plain)
    for e in d["path"]:
        if e["costate"] is None:
            u = np.array([e["control"]])
        else:
            _, inputs = rk4(rhs, np.r_[e["from"], e["costate"], 0.0], d["dt"],
                            round(e["duration"] / d["dt"]))
            u = np.array(inputs)
        assert np.all(u >= np.array(LOW)) and np.all(u <= np.array(HIGH))


def test_limits_need_a_diagonal_input_weight():
    from rrtcolearn.systems.symbolic import build_system

    x, y, u1, u2 = sympy.symbols("x y u1 u2", real=True)
    kwargs = dict(state_low=[-1.0, -1.0], state_high=[1.0, 1.0])
    with pytest.raises(ValueError, match="diagonal R"):
        build_system("coupled", [x, y], [u1, u2], [0, 0], [[1, 0], [0, 1]],
                     [[2, 1], [1, 2]], input_low=-1.0, input_high=1.0, **kwargs)
    # without limits a coupled R is fine
    build_system("coupled", [x, y], [u1, u2], [0, 0], [[1, 0], [0, 1]], [[2, 1], [1, 2]],
                 **kwargs)


def test_saturated_data_do_not_depend_on_workers():
    """A re-derived (limited) system pickles to spawned workers as its generated source."""
    from rrtcolearn.data.generate import generate_data
    from rrtcolearn.parallel import ExecutionSettings

    cfg = load_config(overrides=["system.u_max=0.5"])
    system = pipeline.system_from_config(cfg)
    serial, _ = generate_data(system, 3, 600, chunk_size=150, time_weight=1.0)
    spawned, _ = generate_data(system, 3, 600, chunk_size=150, time_weight=1.0,
                               settings=ExecutionSettings("processes", 2))
    assert len(serial) > 1000
    for name in ("x0", "x1", "cost", "params", "duration", "costate", "simulation"):
        np.testing.assert_array_equal(getattr(serial, name), getattr(spawned, name))
    lam, x0 = serial.costate, serial.x0
    u = system.optimal_control(x0, lam)
    assert np.all(np.abs(u) <= 0.5) and np.any(np.abs(u) == 0.5)


def test_state_constraints_are_separate_from_the_sampling_box(saturated_pendulum):
    """|omega| <= 1.2 as a constraint: the data (|omega| <= pi) are unchanged, no plan edge
    leaves the constraint, and a start outside it is refused."""
    from rrtcolearn.planning.problem import ProblemError

    cfg = saturated_pendulum.config.model_copy(update={"plan": saturated_pendulum.config.plan
                                                       .model_copy(update={
                                                           "state_low": [-10.0, -1.2],
                                                           "state_high": [10.0, 1.2]})})
    tree_max = []
    for seed in range(3):
        p = pipeline.plan(saturated_pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1, seed=seed,
                          config=cfg, time_limit=None, max_iterations=3000)
        for traj in p.tree.trajectories:
            tree_max.append(np.abs(traj[:, 1]).max())
    assert max(tree_max) <= 1.2
    free = pipeline.plan(saturated_pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1, seed=0,
                         time_limit=None, max_iterations=3000)
    assert max(np.abs(t[:, 1]).max() for t in free.tree.trajectories) > 1.2
    with pytest.raises(ProblemError, match="outside the state box"):
        pipeline.plan(saturated_pendulum, [-np.pi, 1.5], [0.0, 0.0], 0.1, config=cfg,
                      max_iterations=10)


def test_a_bound_that_narrows_an_angle_is_refused_not_ignored():
    """The planner wraps angles and bounds them by nothing: a plan.state_low/high entry that
    would narrow an angle's box (a joint limit) is an error; one at or beyond the box (no
    constraint meant) is the box."""
    from rrtcolearn.planning.problem import ProblemError, state_bounds
    from rrtcolearn.systems import make

    pendulum = make("pendulum")
    low, high = state_bounds(pendulum, [-10.0, -1.2], [10.0, 1.2])
    assert low.tolist() == [pendulum.state_low[0], -1.2]
    assert high.tolist() == [pendulum.state_high[0], 1.2]
    for lo, hi in (([-1.0, -7.0], [1.0, 7.0]), ([None, -7.0], [0.0, 7.0])):
        with pytest.raises(ProblemError, match=r"narrows the box .* of an angle"):
            state_bounds(pendulum, lo, hi)

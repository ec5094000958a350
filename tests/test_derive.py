"""Settings the library derives from the system and its data (rrtcolearn.derive)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rrtcolearn import derive, pipeline
from rrtcolearn.config import Config, load_config, paper_config, read_toml
from rrtcolearn.data.generate import generate_data
from rrtcolearn.planning.rrt import CONNECT_AFTER
from rrtcolearn.systems import make


def test_pendulum_derivations_reproduce_the_papers_settings(pendulum):
    cfg = pipeline.resolve(Config(), pendulum)
    assert cfg.generate.n_simulations == 40_000
    assert cfg.plan.sigma == math.pi / 4 and cfg.plan.sigma_goal == math.pi / 2
    assert cfg.plan.control_samples == 1 and cfg.plan.extend_distance == 0.0
    assert cfg.learn.learner == "knn"
    # 90% of simulations leave the reach ball below this cost (the paper took 2)
    assert 3.5 <= cfg.generate.max_cost <= 5.5
    for key in ("generate.max_cost", "plan.sigma", "learn.learner"):
        assert key in cfg.derived and ":" in cfg.derived[key]  # value: reason


def test_resolution_is_deterministic_and_keeps_what_the_user_set(pendulum):
    a = pipeline.resolve(Config(), pendulum)
    assert a == pipeline.resolve(Config(), pendulum)
    mine = load_config(overrides=["generate.max_cost=3.0", "plan.sigma=0.5"])
    b = pipeline.resolve(mine, pendulum)
    assert b.generate.max_cost == 3.0 and b.plan.sigma == 0.5
    assert "generate.max_cost" not in b.derived and "plan.sigma" not in b.derived
    assert pipeline.resolve(b, pendulum) == b  # nothing left to derive
    assert pipeline.resolve(paper_config(), pendulum).derived == {}


def test_four_state_derivations_follow_the_dimension():
    cartpole = make("cartpole")
    cfg = pipeline.resolve(load_config(overrides=['system.name="cartpole"']), cartpole)
    assert cfg.generate.n_simulations == 100_000
    assert cfg.plan.sigma == pytest.approx(0.25) and cfg.plan.sigma_goal == pytest.approx(0.5)
    assert cfg.plan.control_samples == 16
    # a uniform target rarely lies within the data's reach in four dimensions
    assert derive.reach_coverage(cartpole, 1.5) < derive.EXTEND_MIN_COVERAGE
    assert cfg.plan.extend_distance == pytest.approx(0.5)


def test_derived_validity_threshold_accepts_held_out_valid_pairs(pendulum, paper_model):
    # derive V's threshold from one dataset, then query pairs of fresh simulations (another
    # seed): about the quantile's share must be accepted
    data, _ = generate_data(pendulum, 5, 8000)
    seed = np.random.SeedSequence(3)
    choice = derive.validity_threshold(data.inputs, data.simulation, pendulum.metric_scale, 3,
                                       seed, ((0, float(pendulum.state_low[0]),
                                               float(pendulum.state_high[0])),))
    assert choice.value > 0 and choice.key == "learn.validity_threshold"
    fresh, _ = generate_data(pendulum, 6, 500)
    functions = pipeline.fit_functions(
        pendulum, data, paper_config(learn={"validity_threshold": choice.value}))
    rows, _, _ = functions.query_valid(fresh.inputs)
    accepted = len(rows) / len(fresh)
    assert 0.9 <= accepted <= 0.995
    again = derive.validity_threshold(data.inputs, data.simulation, pendulum.metric_scale, 3,
                                      np.random.SeedSequence(3),
                                      ((0, float(pendulum.state_low[0]),
                                        float(pendulum.state_high[0])),))
    assert again == choice


def test_run_records_what_it_derived(tmp_path):
    cfg = load_config(overrides=["generate.n_simulations=3000", "clean.k_max=300"])
    pipeline.generate(cfg, tmp_path)
    pipeline.clean(cfg, tmp_path)
    model = pipeline.fit(cfg, tmp_path)
    saved = read_toml(tmp_path / "config.toml")
    assert saved["generate"]["n_simulations"] == 3000  # the user's value is kept
    assert "generate.n_simulations" not in saved["derived"]
    for key in ("generate.max_cost", "learn.validity_threshold", "plan.sigma"):
        assert key in saved["derived"]
    assert saved["learn"]["validity_threshold"] == model.functions.validity_.threshold
    assert model.config.learn.validity_threshold == model.functions.validity_.threshold


def test_planner_switches_the_goal_connection_on_when_it_stalls(paper_model):
    # a goal region the learned steering alone rarely hits (tolerance 0.01)
    auto = paper_config(plan={"goal_connect": None})
    off = paper_config()
    for seed in range(3):
        p = pipeline.plan(paper_model, [-np.pi, 0], [0, 0], 0.01, seed=seed, config=auto,
                          time_limit=None, max_iterations=3000)
        q = pipeline.plan(paper_model, [-np.pi, 0], [0, 0], 0.01, seed=seed, config=off,
                          time_limit=None, max_iterations=3000)
        assert p.solved and p.extra["connection"] == "shooting"
        assert p.extra["connections_switched_on"]["shooting"] >= CONNECT_AFTER
        assert "goal_connected" not in q.to_dict()
        # until the switch the trees are the same: the connection draws no random numbers
        k = min(p.nodes, q.nodes) - 1
        np.testing.assert_array_equal(p.tree.states[:k], q.tree.states[:k])


def test_offline_budget_chooses_simulations_by_convergence(tmp_path):
    cfg = load_config(overrides=["generate.offline_budget=4", "clean.k_max=300"])
    data, stats = pipeline.generate(cfg, tmp_path)
    saved = read_toml(tmp_path / "config.toml")
    n = saved["generate"]["n_simulations"]
    assert stats.simulations == n and n % cfg.generate.chunk_size == 0
    reason = saved["derived"]["generate.n_simulations"]
    assert "held-out J error by simulations 10000:" in reason
    assert ("converged" in reason) or ("offline budget 4 s" in reason)
    # the data are those of a plain run with that many simulations
    plain = load_config(overrides=[f"generate.n_simulations={n}", "clean.k_max=300"])
    again, _ = pipeline.generate(plain, tmp_path / "plain")
    np.testing.assert_array_equal(again.x1, data.x1)


@pytest.fixture(scope="module")
def fast_integrator():
    """A double integrator whose velocity moves by 2 per 0.01 s step at the input limit
    (gain 200, |u| <= 1) across a box of [-8, 8]: an eighth of its range per step, as
    dynobench's planar quadrotor's yaw rate (2.2 rad/s per step in [-8, 8])."""
    import sympy

    from rrtcolearn.systems.symbolic import build_system

    p, v, u = sympy.symbols("p v u", real=True)
    return build_system("fast_integrator", [p, v], [u], drift=[v, 0],
                        input_matrix=[[0], [200]], input_low=[-1.0], input_high=[1.0],
                        state_low=[-1.0, -8.0], state_high=[1.0, 8.0])


def _points_per_simulation(data) -> np.ndarray:
    counts = np.bincount(data.simulation)
    return counts[counts > 0]


def test_a_fast_system_gets_multi_step_data(fast_integrator):
    # the paper's reach (1.5) is left in the second step: one data point per simulation
    # (issue 32's quad2d); the derived reach keeps the median simulation REACH_STEPS steps
    cfg = pipeline.resolve(Config(), fast_integrator)
    reach = cfg.generate.max_state_distance
    assert reach > derive.PAPER_REACH
    assert "generate.max_state_distance" in cfg.derived
    options = {"max_cost": cfg.generate.max_cost, "chunk_size": 500}
    old, _ = generate_data(fast_integrator, 4, 1000, max_state_distance=1.5, **options)
    new, _ = generate_data(fast_integrator, 4, 1000, max_state_distance=reach, **options)
    assert np.median(_points_per_simulation(old)) <= 1
    assert np.median(_points_per_simulation(new)) >= derive.REACH_STEPS


def _rk4_reference(system, z: np.ndarray, w: float, dt: float) -> np.ndarray:
    """One classic RK4 step of the state+costate ODE, written out here."""
    def f(y):
        out = np.empty_like(y)
        system.rhs(y, w, out)
        return out
    k1 = f(z)
    k2 = f(z + 0.5 * dt * k1)
    k3 = f(z + 0.5 * dt * k2)
    k4 = f(z + dt * k3)
    return z + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


def test_the_reach_rule_against_a_hand_computation(fast_integrator):
    # the median over the pilot of each simulation's farthest weighted distance from its
    # start in its first REACH_STEPS steps, recomputed with a hand-written RK4 loop
    from rrtcolearn.data.generate import sample_starts

    seed = np.random.SeedSequence(11)
    choice = derive.pilot_reach(fast_integrator, time_weight=1.0, dt=0.01, seed=seed)
    x0, _, lam, valid = sample_starts(fast_integrator, seed, 0, derive.PILOT_SIMULATIONS, 1.0)
    scale = 2 * np.pi / np.array([2.0, 16.0])  # a range counts as a turn
    farthest = []
    for x, la in zip(x0[valid], lam[valid], strict=True):
        z = np.concatenate([x, la, [0.0]])
        far = 0.0
        for _ in range(derive.REACH_STEPS):
            z = _rk4_reference(fast_integrator, z, 1.0, 0.01)
            far = max(far, float(np.linalg.norm((z[:2] - x) * scale)))
        farthest.append(far)
    assert choice.key == "generate.max_state_distance"
    assert choice.value == pytest.approx(float(np.median(farthest)), rel=1e-9)
    # about REACH_STEPS steps of 2 (the saturated input) in v, weighted 2 pi / 16
    assert choice.value == pytest.approx(derive.REACH_STEPS * 2 * 2 * np.pi / 16, rel=0.2)


def test_slow_systems_keep_the_papers_reach(pendulum):
    # the pendulum's median pilot simulation stays within 1.5 for 63 steps: the paper's
    # reach, and so the paper's data, are kept
    cfg = pipeline.resolve(Config(), pendulum)
    assert cfg.generate.max_state_distance == derive.PAPER_REACH
    assert cfg.derived["generate.max_state_distance"].startswith("1.5: the paper's")

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

"""The co-learning loop (data.colearn): deterministic per seed, resumable after an
interruption to the same result, and its aimed data optimal extremals (H* = 0 at their
starts, checked against the pendulum's Hamiltonian written out by hand). And Alg. 3 on the
learners' features: blind to shifts along invariant coordinates, the raw rows without."""

import dataclasses

import numpy as np
import pytest

from rrtcolearn import pipeline
from rrtcolearn.config import Config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.colearn import colearn
from rrtcolearn.data.generate import generate_data
from rrtcolearn.data.store import digest
from rrtcolearn.learn.features import learning_geometry

N = 600  # uniform simulations: small, the loop's logic is what is tested
FIRST_ID = N


@pytest.fixture(scope="module")
def setup():
    cfg = Config.model_validate({"system": {"name": "pendulum"},
                                 "generate": {"n_simulations": N, "max_cost": 2.0},
                                 "clean": {"k_max": 500}, "learn": {"learner": "knn"}, "seed": 3})
    system = pipeline.system_from_config(cfg)
    cfg = pipeline.resolve(cfg, system)
    g = cfg.generate
    opts = dict(time_weight=cfg.system.time_weight, dt=g.dt, max_cost=cfg.max_cost,
                max_state_distance=g.max_state_distance, max_duration=g.max_duration)
    data, _ = generate_data(system, 3, N, **opts)

    def refit(d):
        return pipeline.fit_functions(system, pipeline.clean_dataset(cfg, system, d)[0], cfg)

    return system, data, refit, opts


def run(setup, **kw):
    system, data, refit, opts = setup
    return colearn(system, data, refit, seed=7, rounds=kw.pop("rounds", 2), simulations=40,
                   first_id=FIRST_ID, **opts, **kw)


def test_deterministic_for_a_seed(setup):
    a, ra = run(setup)
    b, rb = run(setup)
    assert digest(a.arrays()) == digest(b.arrays())
    assert [r.hit_rate for r in ra] == [r.hit_rate for r in rb]
    assert len(ra) >= 2 and ra[1].simulations == 40 and len(a) > len(setup[1])


def test_resume_after_interruption_gives_the_same_result(setup, tmp_path):
    full, records = run(setup)
    part, done = run(setup, store=tmp_path, stop_after=1)  # "killed" after round 0
    assert len(done) == 1 and len(part) == len(setup[1])
    resumed, again = run(setup, store=tmp_path)
    assert digest(resumed.arrays()) == digest(full.arrays())
    assert [r.hit_rate for r in again] == [r.hit_rate for r in records]
    # a finished store is loaded, not recomputed
    loaded, third = run(setup, store=tmp_path)
    assert digest(loaded.arrays()) == digest(full.arrays())
    assert all(r.cpu_s == 0.0 for r in third)


def test_aimed_data_are_optimal_extremals(setup):
    _, data, _, opts = setup
    out, _ = run(setup, rounds=1)
    aimed = out.simulation >= FIRST_ID
    assert aimed.any() and not (data.simulation >= FIRST_ID).any()
    x, lam, w = out.x0[aimed], out.costate[aimed], opts["time_weight"]
    # H* = w + u^2/2 + l_th om + l_om (sin th + u) with u* = -l_om, by hand
    u = -lam[:, 1]
    h = w + 0.5 * u**2 + lam[:, 0] * x[:, 1] + lam[:, 1] * (np.sin(x[:, 0]) + u)
    np.testing.assert_allclose(h, 0.0, atol=1e-9)
    # the aimed starts are states the data's trajectories pass (x0 of a query = a data x1)
    starts = np.unique(x, axis=0)
    assert np.isin(starts[:, 0], data.x1[:, 0]).all()


def test_pipeline_records_the_rounds(tmp_path):
    cfg = Config.model_validate({"system": {"name": "pendulum"}, "seed": 2,
                                 "generate": {"n_simulations": N, "max_cost": 2.0,
                                              "colearn_rounds": 1},
                                 "clean": {"k_max": 500}, "learn": {"learner": "knn"}})
    data, stats = pipeline.generate(cfg, tmp_path)
    rounds = __import__("json").loads((tmp_path / "colearn.json").read_text())
    assert [r["round"] for r in rounds] == [0, 1]
    assert stats.points == len(data) and (data.simulation >= N).any()
    assert "generate.colearn" in pipeline.read_run_config(tmp_path).derived
    assert not (tmp_path / "shards").exists()


def test_cleaning_on_features_is_blind_to_invariant_shifts():
    """`clean_data(features=)`: the cart-pole's cart position p is invariant, so rows shifted
    along p by a different amount each are the same pairs on the learners' features; the raw
    rows are not blind to the shift. The pipeline cleans the raw rows (`clean_dataset`, for
    the reason in its docstring), on the pendulum bit for bit as `clean_data` does."""
    cfg = Config.model_validate({"system": {"name": "cartpole"}, "seed": 4,
                                 "generate": {"n_simulations": 200, "max_cost": 2.0},
                                 "clean": {"k_max": 300, "d": 0.2}})
    system = pipeline.system_from_config(cfg)
    assert system.invariant_coordinates == (0,)
    data, _ = generate_data(system, 4, 200, max_cost=2.0)
    shift = np.zeros_like(data.x0)
    shift[:, 0] = np.random.default_rng(0).uniform(-3.0, 3.0, len(data))
    moved = dataclasses.replace(data, x0=data.x0 + shift, x1=data.x1 + shift)
    features, _ = learning_geometry(system, cfg.learn.periodic)
    kw = {"d": 0.2, "k_max": 300, "seed": pipeline.seed_stream(4, "clean"),
          "scale": system.metric_scale}
    kept, res = clean_data(data, features=features, **kw)
    _, res_moved = clean_data(moved, features=features, **kw)
    assert 0 < len(kept) < len(data)  # the cleaning removed something
    np.testing.assert_array_equal(res.keep, res_moved.keep)
    raw, _ = clean_data(data, **kw)
    raw_moved, _ = clean_data(moved, **kw)
    assert len(raw) != len(raw_moved) or not np.array_equal(raw.simulation,
                                                            raw_moved.simulation)

    pcfg = Config.model_validate({"system": {"name": "pendulum"}, "seed": 4,
                                  "clean": {"k_max": 300}})
    pend = pipeline.system_from_config(pcfg)
    pdata, _ = generate_data(pend, 4, 300, max_cost=2.0)
    new, _ = pipeline.clean_dataset(pcfg, pend, pdata)
    old, _ = clean_data(pdata, d=pcfg.clean.d, k_max=300, method=pcfg.clean.method,
                        seed=pipeline.seed_stream(4, "clean"), scale=pend.metric_scale)
    assert digest(new.arrays()) == digest(old.arrays())

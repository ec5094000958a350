"""learn.learner = "mlp": J and U from neural networks, V from k-NN, saved without pickle."""

import numpy as np
import pytest
import sklearn  # noqa: F401  (an extra: `make test` installs it; missing, the suite fails)

from rrtcolearn import pipeline
from rrtcolearn.config import load_config
from rrtcolearn.data.generate import generate_data
from rrtcolearn.errors import ArtefactError
from rrtcolearn.integrate import rollout
from rrtcolearn.systems.double_integrator import optimal_cost

OVERRIDES = ['system.name="double_integrator"', "generate.n_simulations=2000",
             'learn.learner="mlp"', "learn.mlp_max_iter=20", "learn.mlp_max_samples=10000",
             "learn.mlp_hidden=[32, 32]"]


@pytest.fixture(scope="module")
def mlp_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("mlp")
    cfg = load_config(None, OVERRIDES)
    pipeline.generate(cfg, run_dir)
    pipeline.clean(cfg, run_dir)
    return cfg, run_dir, pipeline.fit(cfg, run_dir)


def _held_out(model):
    held, _ = generate_data(model.system, 99, 300, max_cost=2.0, max_state_distance=1.5)
    return held.inputs


def test_networks_answer_j_and_u_and_knn_answers_v(mlp_run):
    _, _, model = mlp_run
    f = model.functions
    assert f.networks_ is not None
    X = _held_out(model)
    cost, steer, valid = f.query(X)
    j_net, u_net = f.networks_
    F = f.features_.transform(X)  # the networks learn on the features (x1 - x0 along q)
    np.testing.assert_array_equal(cost, np.clip(j_net.predict(F), 1e-5, 1e5))
    np.testing.assert_array_equal(steer, u_net.predict(F))
    dist, _ = f.cost_to_go_.kneighbors(F * f.input_scale_)
    np.testing.assert_array_equal(valid, dist.sum(axis=1) <= f.validity_.threshold)
    # the planner's path gives the same J for the rows V accepts
    rows, cost_v, _ = f.query_valid(X)
    np.testing.assert_array_equal(rows, np.flatnonzero(valid))
    # the same networks answer both paths; a matrix product over a subset of the rows may
    # differ in the last bit (BLAS picks its blocking by the number of rows)
    np.testing.assert_allclose(cost_v, cost[valid], rtol=1e-13, atol=0.0)
    # J is a cost-to-go, not noise: within a factor of two of the exact one for most queries
    oracle = optimal_cost(X[valid, :2], X[valid, 2:], 1.0)
    ratio = cost[valid] / oracle
    assert np.median(np.abs(ratio - 1.0)) < 0.5


def test_load_model_reads_the_saved_networks_bit_identically(mlp_run):
    _, run_dir, model = mlp_run
    assert (run_dir / pipeline.FUNCTIONS_FILE).is_file()
    loaded = pipeline.load_model(run_dir)
    X = _held_out(model)
    for a, b in zip(model.functions.query(X), loaded.functions.query(X), strict=True):
        np.testing.assert_array_equal(a, b)


def test_same_seed_same_networks(mlp_run, tmp_path):
    cfg, run_dir, model = mlp_run
    (tmp_path / pipeline.CLEANED_FILE).write_bytes((run_dir / pipeline.CLEANED_FILE).read_bytes())
    again = pipeline.fit(cfg, tmp_path)
    for a, b in zip(model.functions.networks_, again.functions.networks_, strict=True):
        for k, v in a.to_arrays().items():
            assert np.array_equal(v, b.to_arrays()[k]), k
    digests = {r["file"]: r["sha256"] for r in pipeline.inspect_run(run_dir)}
    again_digests = {r["file"]: r["sha256"] for r in pipeline.inspect_run(tmp_path)}
    assert again_digests[pipeline.FUNCTIONS_FILE] == digests[pipeline.FUNCTIONS_FILE]


def test_damaged_or_missing_functions_file_is_refused(mlp_run, tmp_path):
    _, run_dir, _ = mlp_run
    for name in (pipeline.MODEL_FILE, pipeline.CLEANED_FILE, "config.toml"):
        (tmp_path / name).write_bytes((run_dir / name).read_bytes())
    data = bytearray((run_dir / pipeline.FUNCTIONS_FILE).read_bytes())
    data[len(data) // 2] ^= 0xFF
    (tmp_path / pipeline.FUNCTIONS_FILE).write_bytes(bytes(data))
    with pytest.raises(ArtefactError):
        pipeline.load_model(tmp_path)
    (tmp_path / pipeline.FUNCTIONS_FILE).unlink()
    with pytest.raises(ArtefactError, match="not found"):
        pipeline.load_model(tmp_path)


def test_plans_with_network_steering_resimulate(mlp_run):
    cfg, _, model = mlp_run
    start, goal = pipeline.query_states(cfg, model.system)
    p = pipeline.plan(model, start, goal, cfg.plan.goal_tolerance, seed=1, time_limit=None,
                      max_iterations=3000)
    assert p.solved
    t = p.tree
    for node in p.path_nodes[1:]:
        parent = int(t.parents[node])
        steps = round(float(t.durations[node]) / cfg.generate.dt)
        z0 = np.r_[t.states[parent], t.costates[node], 0.0]
        end = rollout(model.system, z0, 1.0, cfg.generate.dt, steps)[-1]
        np.testing.assert_allclose(end[:2], t.states[node], atol=1e-9)
    assert np.linalg.norm(t.states[p.path_nodes[-1]] - goal) <= cfg.plan.goal_tolerance


def test_missing_scikit_learn_is_a_one_line_environment_error(mlp_run, monkeypatch):
    from rrtcolearn.data.store import load_dataset
    from rrtcolearn.errors import EnvironmentProblem

    cfg, run_dir, model = mlp_run
    data, _ = load_dataset(run_dir / pipeline.CLEANED_FILE)
    for name in ("sklearn", "sklearn.exceptions", "sklearn.neural_network"):
        monkeypatch.setitem(__import__("sys").modules, name, None)
    with pytest.raises(EnvironmentProblem, match=r"rrtcolearn\[mlp\]") as info:
        pipeline.fit_functions(model.system, data, cfg)
    assert info.value.exit_code == 3

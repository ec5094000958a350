"""Invariant coordinates: found in the sympy model, and J, U, V exactly invariant there."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import sympy

from rrtcolearn.data.generate import generate_data
from rrtcolearn.derive import validity_threshold
from rrtcolearn.errors import ArtefactError
from rrtcolearn.learn.features import QueryFeatures, learning_geometry
from rrtcolearn.learn.models import LearnedFunctions, best_valid
from rrtcolearn.systems import make
from rrtcolearn.systems.symbolic import build_system

ROOT = Path(__file__).resolve().parents[1]


def _unicycle(with_wheel: bool = False):
    """A first-order unicycle typed in as a user would: x' = v cos th, y' = v sin th,
    th' = omega; ``with_wheel`` adds a wheel angle phi' = v that nothing depends on."""
    x, y, th, phi, v, om = sympy.symbols("x y theta phi v omega", real=True)
    states = [x, y, th] + ([phi] if with_wheel else [])
    b = [[sympy.cos(th), 0], [sympy.sin(th), 0], [0, 1]] + ([[1, 0]] if with_wheel else [])
    n = len(states)
    return build_system(
        "unicycle_wheel" if with_wheel else "unicycle", states=states, inputs=[v, om],
        drift=[0] * n, input_matrix=b,
        state_low=[-5, -5, -np.pi] + ([-np.pi] if with_wheel else []),
        state_high=[5, 5, np.pi] + ([np.pi] if with_wheel else []),
        angle_dims=[2, 3] if with_wheel else [2])


def _sparse_rrt_cartpole():
    sys.path.insert(0, str(ROOT))
    try:
        from examples.sparse_rrt_cartpole import make_cartpole
    finally:
        sys.path.remove(str(ROOT))
    return make_cartpole()


# ------------------------------------------------------------------------------ detection


def test_detection_finds_the_cart_position_and_nothing_on_the_pendulums():
    assert make("cartpole").invariant_coordinates == (0,)  # p
    assert _sparse_rrt_cartpole().invariant_coordinates == (0,)  # x
    assert make("pendulum").invariant_coordinates == ()
    assert make("acrobot").invariant_coordinates == ()
    sys.path.insert(0, str(ROOT))
    try:
        from examples.sparse_rrt_acrobot import make_acrobot
    finally:
        sys.path.remove(str(ROOT))
    assert make_acrobot().invariant_coordinates == ()
    assert make("quadrotor").invariant_coordinates == (0, 1)  # x, z: gravity is uniform


def test_detection_finds_x_and_y_of_a_unicycle_and_a_free_wheel_angle():
    assert _unicycle().invariant_coordinates == (0, 1)  # the heading enters B
    # an angle that nothing depends on is free: its wrap is a shift like any other
    assert _unicycle(with_wheel=True).invariant_coordinates == (0, 1, 3)


def test_a_parametrisation_that_reads_a_coordinate_breaks_its_invariance():
    from rrtcolearn.systems.symbolic import CostateParametrisation

    def line(x, p):  # a (contrived) costate line that depends on x0
        return [0, 0], [sympy.cos(p[0]) * (1 + x[0] ** 2), sympy.sin(p[0])], 1

    q, v, u = sympy.symbols("q v u", real=True)
    args = dict(states=[q, v], inputs=[u], drift=[v, 0], input_matrix=[[0], [1]],
                state_low=[-1, -1], state_high=[1, 1])
    assert build_system("di", **args).invariant_coordinates == (0,)
    cp = CostateParametrisation(("phi",), (-np.pi,), (np.pi,), (True,), line)
    assert build_system("di_x", **args, costate_parametrisation=cp).invariant_coordinates == ()


def test_a_system_without_sympy_has_no_invariant_coordinates():
    sym = make("double_integrator")
    plain = {f.name: getattr(sym, f.name) for f in dataclasses.fields(type(sym).__mro__[1])
             if f.name != "invariant_coordinates"}
    system = type(sym).__mro__[1](**plain)  # the base `System`, numeric callables only
    assert type(system).__name__ == "System"
    assert system.invariant_coordinates == ()
    assert learning_geometry(system)[0].invariant == ()


# ------------------------------------------------------------------------------ features


def test_features_drop_x0_and_difference_x1_along_invariant_coordinates():
    f = QueryFeatures(3, (2, 0))
    assert f.invariant == (0, 2) and f.width == 4
    X = np.array([[1.0, 2.0, 3.0, 10.0, 20.0, 30.0]])
    np.testing.assert_array_equal(f.transform(X), [[2.0, 9.0, 20.0, 27.0]])
    np.testing.assert_array_equal(f.scale(np.array([1.0, 2.0, 3.0])), [2.0, 1.0, 2.0, 3.0])
    plain = QueryFeatures(3)
    assert plain.transform(X) is X  # no invariants: the query itself
    with pytest.raises(ValueError):
        QueryFeatures(2, (2,))


# ------------------------------------------------------------------------------ learning


@pytest.fixture(scope="module")
def di_data():
    system = make("double_integrator")
    data, _ = generate_data(system, 3, 3000, max_cost=2.0, max_state_distance=1.5)
    return system, data


def _shifted(X: np.ndarray, n: int, coords: tuple[int, ...], c: np.ndarray) -> np.ndarray:
    Y = X.copy()
    for i in coords:
        Y[:, i] += c
        Y[:, n + i] += c
    return Y


@pytest.mark.parametrize("learner", ["knn", "mlp"])
def test_shifted_queries_get_the_same_answers(di_data, learner):
    system, data = di_data
    assert system.invariant_coordinates == (0,)
    f = LearnedFunctions(validity_threshold=0.1, learner=learner, mlp_max_iter=5,
                         mlp_hidden=(16,), mlp_max_samples=20_000).fit(data, system)
    rng = np.random.default_rng(0)
    X = data.inputs[rng.choice(len(data), 300, replace=False)]
    X[:, 2:] += rng.normal(0.0, 0.1, (300, 2))  # not training rows: real neighbour searches
    # on a grid of 2^-20, the shifted states and x1 - x0 are exact: bit-for-bit answers
    X = np.round(X * 2.0**20) / 2.0**20
    J, U, V = f.query(X)
    assert V.any() and not V.all()
    for c in (3.0, -40.0, 1024.0):
        Y = _shifted(X, 2, (0,), np.full(len(X), c))
        J2, U2, V2 = f.query(Y)
        np.testing.assert_array_equal(V2, V)
        np.testing.assert_array_equal(J2, J)
        np.testing.assert_array_equal(U2, U)
        rows, cost, _ = f.query_valid(Y)
        np.testing.assert_array_equal(rows, np.flatnonzero(V))
        np.testing.assert_allclose(cost, J[V], rtol=1e-13, atol=0)
        assert best_valid(f, Y)[0] == best_valid(f, X)[0]
    # any shift of any query: x1 - x0 rounds, the answers stay within 1e-12
    X = X + rng.uniform(0.0, 1e-3, X.shape)
    J, U, V = f.query(X)
    Y = _shifted(X, 2, (0,), rng.uniform(-3.0, 3.0, len(X)))
    J2, U2, V2 = f.query(Y)
    np.testing.assert_array_equal(V2, V)
    np.testing.assert_allclose(J2, J, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(U2, U, rtol=1e-12, atol=1e-12)


def test_without_invariance_a_shift_changes_the_answers(di_data):
    """The check above is not vacuous: the raw model answers shifted queries differently."""
    system, data = di_data
    raw = dataclasses.replace(system, invariant_coordinates=())
    f = LearnedFunctions(validity_threshold=0.5).fit(data, raw)
    X = data.inputs[:300]
    Y = _shifted(X, 2, (0,), np.full(len(X), 10.0))
    J, _, V = f.query(X)
    J2, _, V2 = f.query(Y)
    assert V.all() and not V2.any()  # shifted out of the data's box: nothing near it
    assert not np.array_equal(J, J2)


def test_the_unicycle_learns_on_xy_differences():
    system = _unicycle()
    data, _ = generate_data(system, 5, 2000, max_cost=2.0, max_state_distance=1.5)
    f = LearnedFunctions(validity_threshold=1.0).fit(data, system)
    assert f.features_.invariant == (0, 1) and f.cost_to_go_.index_ is not None
    X = data.inputs[::50]
    J, U, V = f.query(X)
    assert V.any()
    Y = X.copy()
    Y[:, [0, 3]] += 2.5
    Y[:, [1, 4]] -= 1.25
    J2, U2, V2 = f.query(Y)
    np.testing.assert_array_equal(V2, V)
    np.testing.assert_array_equal(J2, J)
    np.testing.assert_array_equal(U2, U)


def test_validity_threshold_is_derived_in_the_learners_space(di_data):
    """The derived threshold measures distances the fitted V compares it with: on the
    features, where a shifted held-out pair is as near its data as it was."""
    system, data = di_data
    features, periodic = learning_geometry(system)
    seed = np.random.SeedSequence(7)
    a = validity_threshold(data.inputs, data.simulation, system.metric_scale, 3, seed,
                           periodic, features)
    moved = _shifted(data.inputs, 2, (0,), np.arange(len(data)) % 7 * 0.5)
    b = validity_threshold(moved, data.simulation, system.metric_scale, 3, seed,
                           periodic, features)
    assert a.value == pytest.approx(b.value, rel=1e-9)
    c = validity_threshold(moved, data.simulation, system.metric_scale, 3, seed, periodic)
    assert c.value > 2 * a.value  # on raw queries the shifts spread the data out


def test_save_load_round_trip_and_old_files(di_data, tmp_path):
    system, data = di_data
    f = LearnedFunctions(validity_threshold=0.5).fit(data, system)
    f.save(tmp_path / "f.npz")
    g, meta = LearnedFunctions.load(tmp_path / "f.npz")
    assert meta["version"] == 3 and g.features_ == f.features_
    X = _shifted(data.inputs[:200], 2, (0,), np.full(200, 5.0))
    for a, b in zip(f.query(X), g.query(X), strict=True):
        np.testing.assert_array_equal(a, b)
    # a file from before the features (no version, no invariant coordinates) was fitted on
    # the raw queries and loads as such
    from rrtcolearn.data.store import load_arrays, save_arrays
    from rrtcolearn.learn.models import FUNCTIONS_FORMAT

    arrays, meta = load_arrays(tmp_path / "f.npz", FUNCTIONS_FORMAT)
    old = {k: v for k, v in arrays.items() if k not in ("data.invariant", "data.rotation")}
    header = {k: v for k, v in meta.items() if k in ("params",)}
    save_arrays(tmp_path / "old.npz", FUNCTIONS_FORMAT, old, header)
    h, _ = LearnedFunctions.load(tmp_path / "old.npz")
    assert h.features_.invariant == ()
    raw = LearnedFunctions(validity_threshold=0.5).fit(
        data, dataclasses.replace(system, invariant_coordinates=()))
    for a, b in zip(raw.query(X), h.query(X), strict=True):
        np.testing.assert_array_equal(a, b)
    # a newer version is refused with a message that says what to do
    save_arrays(tmp_path / "new.npz", FUNCTIONS_FORMAT, arrays, {**header, "version": 4})
    with pytest.raises(ArtefactError, match="refit"):
        LearnedFunctions.load(tmp_path / "new.npz")


def test_check_system_refuses_a_coordinate_claimed_invariant_that_is_not():
    from rrtcolearn.systems.check import SystemCheckError, check_system

    system = make("cartpole")
    check_system(system, n_samples=50)
    with pytest.raises(SystemCheckError, match="invariant coordinate 1"):
        check_system(dataclasses.replace(system, invariant_coordinates=(0, 1)), n_samples=50)


def test_a_fitted_run_records_its_invariant_coordinates_and_reloads_them(tmp_path):
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    cfg = load_config(None, ['system.name="double_integrator"', "generate.n_simulations=500",
                             'learn.learner="knn"'])
    pipeline.generate(cfg, tmp_path)
    pipeline.clean(cfg, tmp_path)
    model = pipeline.fit(cfg, tmp_path)
    recorded = pipeline.read_run_config(tmp_path).derived["learn.invariant_coordinates"]
    assert recorded.startswith("[0]: q:")
    loaded = pipeline.load_model(tmp_path)
    assert loaded.functions.features_.invariant == (0,)
    X = _shifted(np.array([[0.5, 0.0, 0.75, 0.25]]), 2, (0,), np.array([2.0]))
    for a, b in zip(model.functions.query(X), loaded.functions.query(X), strict=True):
        np.testing.assert_array_equal(a, b)

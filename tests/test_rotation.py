"""Planar rotation: found exactly in the sympy model, and J, U, V exactly equivariant there."""

from __future__ import annotations

import dataclasses
import sys
from itertools import permutations
from pathlib import Path

import numpy as np
import pytest
import sympy

from rrtcolearn.data.generate import generate_data
from rrtcolearn.errors import ArtefactError
from rrtcolearn.evaluate import landing_states
from rrtcolearn.learn.features import QueryFeatures, learning_geometry
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.systems import make
from rrtcolearn.systems.symbolic import CostateParametrisation, build_system

ROOT = Path(__file__).resolve().parents[1]


def _example(module: str, attr: str):
    sys.path.insert(0, str(ROOT))
    try:
        return getattr(__import__(f"examples.{module}", fromlist=[attr]), attr)()
    finally:
        sys.path.remove(str(ROOT))


def _typed_unicycle(**kwargs):
    """A first-order unicycle typed in as a user would, its states in another order
    (theta first) so that nothing relies on (x, y, theta) being (0, 1, 2)."""
    th, x, y, v, om = sympy.symbols("theta x y v omega", real=True)
    return build_system("unicycle_typed", [th, x, y], [v, om], drift=[0, 0, 0],
                        input_matrix=[[0, 1], [sympy.cos(th), 0], [sympy.sin(th), 0]],
                        state_low=[-np.pi, -5, -5], state_high=[np.pi, 5, 5], angle_dims=[0],
                        **kwargs)


def _numerically_equivariant(system, i: int, j: int, k: int, seed: int = 0) -> bool:
    """Independent of the sympy check: the plain numeric dynamics at random states, inputs
    and angles satisfy f(g x, u) = T f(x, u) (g rotates (x_i, x_j) by phi and adds phi to
    x_k; T rotates the (i, j) components)."""
    rng = np.random.default_rng(seed)
    n, m = system.n_states, system.n_inputs
    x = rng.uniform(-2.0, 2.0, (200, n))
    u = rng.uniform(-1.0, 1.0, (200, m))
    phi = rng.uniform(-np.pi, np.pi, 200)
    c, s = np.cos(phi), np.sin(phi)
    gx = x.copy()
    gx[:, i], gx[:, j] = c * x[:, i] - s * x[:, j], s * x[:, i] + c * x[:, j]
    gx[:, k] += phi
    f, fg = system.dynamics(x, u), system.dynamics(gx, u)
    tf = f.copy()
    tf[:, i], tf[:, j] = c * f[:, i] - s * f[:, j], s * f[:, i] + c * f[:, j]
    return bool(np.allclose(fg, tf, rtol=1e-10, atol=1e-10))


# ------------------------------------------------------------------------------ detection


def test_detection_finds_the_unicycles_heading():
    from rrtcolearn.dynobench import unicycle1_v0, unicycle2_v0

    for system in (unicycle1_v0(), unicycle2_v0()):
        assert system.planar_rotation == (0, 1, 2)
        assert _numerically_equivariant(system, 0, 1, 2)
        assert not _numerically_equivariant(system, 1, 0, 2)  # the other sense is not
    typed = _typed_unicycle()
    assert typed.invariant_coordinates == (1, 2) and typed.planar_rotation == (1, 2, 0)
    assert _numerically_equivariant(typed, 1, 2, 0)


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "acrobot", "quadrotor",
                                  "double_integrator", "sparse_rrt_cartpole",
                                  "sparse_rrt_acrobot"])
def test_no_rotation_where_none_is_exact(name):
    system = _example(f"{name}", f"make_{name.split('_')[-1]}") \
        if name.startswith("sparse_rrt") else make(name)
    assert system.planar_rotation == ()
    # independently: no pair of coordinates rotates with any third as its heading (the
    # planar quadrotor's x, z are invariant, but gravity fixes a direction)
    n = system.n_states
    for i, j in permutations(range(n), 2):
        for k in set(range(n)) - {i, j}:
            assert not _numerically_equivariant(system, i, j, k), (i, j, k)


def test_an_authors_parametrisation_is_not_rotated():
    def line(x, p):  # the heading's costate on a circle of directions in (x, y)
        return [0, 0, 0], [sympy.cos(p[0]), sympy.sin(p[0]), p[1]], 1

    cp = CostateParametrisation(("a", "b"), (-np.pi, -1.0), (np.pi, 1.0), (True, False), line)
    th, x, y, v, om = sympy.symbols("theta x y v omega", real=True)
    system = build_system("unicycle_cp", [x, y, th], [v, om], drift=[0, 0, 0],
                          input_matrix=[[sympy.cos(th), 0], [sympy.sin(th), 0], [0, 1]],
                          state_low=[-5, -5, -np.pi], state_high=[5, 5, np.pi],
                          angle_dims=[2], costate_parametrisation=cp)
    assert system.invariant_coordinates == (0, 1) and system.planar_rotation == ()


def test_the_rotation_survives_pickling_and_the_build_record(tmp_path):
    import pickle

    from rrtcolearn.dynobench import unicycle1_v0
    from rrtcolearn.systems.build_record import _decode, _encode

    system = unicycle1_v0()
    assert pickle.loads(pickle.dumps(system)).planar_rotation == (0, 1, 2)
    record = _encode(system)
    assert record["fields"]["planar_rotation"] == {"tuple": [0, 1, 2]}
    again = _decode(record, unicycle1_v0, None)
    assert again is not None and again.planar_rotation == (0, 1, 2)


# ------------------------------------------------------------------------------ features


def test_features_are_the_query_in_x0s_body_frame():
    f = QueryFeatures(4, (0, 1), (0, 1, 2), heading_wraps=True)
    assert f.width == 5
    # x0 at (1, 2) heading +90 degrees; x1 3 ahead of it, turned by 0.3 and one more turn
    X = np.array([[1.0, 2.0, np.pi / 2, 0.7, 1.0, 5.0, np.pi / 2 + 0.3 + 2 * np.pi, -0.2]])
    np.testing.assert_allclose(f.transform(X), [[0.7, 3.0, 0.0, 0.3, -0.2]], atol=1e-12)
    Y = np.array([[0.6, -0.8, 0.5, 0.25, 2.0]])  # (d_x, d_y, d_theta, d_w, duration)
    body = f.steering_to_body(X, Y)
    np.testing.assert_allclose(body, [[-0.8, -0.6, 0.5, 0.25, 2.0]], atol=1e-12)
    np.testing.assert_allclose(f.steering_to_world(X, body), Y, atol=1e-15)
    assert QueryFeatures(4, (0, 1)).steering_to_body(X, Y) is not None
    np.testing.assert_array_equal(QueryFeatures(4, (0, 1)).steering_to_body(X, Y), Y)
    # equal weights for the body-frame components: a distance that rotates with them
    np.testing.assert_allclose(f.scale(np.array([1.0, 3.0, 5.0, 7.0])),
                               [7.0, 2.0, 2.0, 5.0, 7.0])
    with pytest.raises(ValueError, match="planar rotation"):
        QueryFeatures(3, (0,), (0, 1, 2))
    features, wrapped = learning_geometry(_typed_unicycle())
    assert features.rotation == (1, 2, 0) and features.heading_wraps and wrapped == ()


# ------------------------------------------------------------------------------ learning


@pytest.fixture(scope="module")
def unicycle_data():
    from rrtcolearn.dynobench import unicycle1_v0

    system = unicycle1_v0()
    data, _ = generate_data(system, 5, 600, max_cost=3.0, max_state_distance=1.5)
    return system, data


def _wrap(a: np.ndarray) -> np.ndarray:
    return a - 2.0 * np.pi * np.floor((a + np.pi) / (2.0 * np.pi))


def _moved(X: np.ndarray, phi: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Queries (Q, 6) of the unicycle rotated by phi about the origin and shifted."""
    c, s = np.cos(phi), np.sin(phi)
    Y = X.copy()
    for o in (0, 3):
        Y[:, o] = c * X[:, o] - s * X[:, o + 1] + shift[:, 0]
        Y[:, o + 1] = s * X[:, o] + c * X[:, o + 1] + shift[:, 1]
        Y[:, o + 2] = _wrap(X[:, o + 2] + phi)
    return Y


def _queries(data, rng) -> np.ndarray:
    X = data.inputs[rng.choice(len(data), 300, replace=False)].copy()
    X[:, 3:] += rng.normal(0.0, 0.05, (300, 3))  # not training rows
    X[:, 5] = _wrap(X[:, 5])
    return X


@pytest.mark.parametrize(("learner", "steering"),
                         [("knn", "mean"), ("knn", "local_linear"), ("mlp", "mean")])
def test_rotated_and_shifted_queries_get_the_same_J_and_turned_U(unicycle_data, learner,
                                                                  steering):
    system, data = unicycle_data
    f = LearnedFunctions(validity_threshold=0.1, learner=learner, steering=steering,
                         mlp_max_iter=3, mlp_hidden=(16,),
                         mlp_max_samples=5000).fit(data, system)
    assert f.features_.rotation == (0, 1, 2)
    rng = np.random.default_rng(1)
    X = _queries(data, rng)
    J, U, V = f.query(X)
    assert V.any() and not V.all()
    phi = rng.uniform(-np.pi, np.pi, len(X))
    Y = _moved(X, phi, rng.uniform(-4.0, 4.0, (len(X), 2)))
    J2, U2, V2 = f.query(Y)
    np.testing.assert_array_equal(V2, V)
    np.testing.assert_allclose(J2, J, rtol=1e-9, atol=1e-12)
    c, s = np.cos(phi), np.sin(phi)
    turned = U.copy()
    turned[:, 0], turned[:, 1] = c * U[:, 0] - s * U[:, 1], s * U[:, 0] + c * U[:, 1]
    np.testing.assert_allclose(U2, turned, rtol=1e-9, atol=1e-9)
    rows, cost, _ = f.query_valid(Y)
    np.testing.assert_array_equal(rows, np.flatnonzero(V))
    np.testing.assert_allclose(cost, J[V], rtol=1e-9)


def test_without_the_rotation_a_turn_changes_the_answers(unicycle_data):
    """The check above is not vacuous: translation alone answers turned queries otherwise."""
    system, data = unicycle_data
    f = LearnedFunctions(validity_threshold=0.1).fit(
        data, dataclasses.replace(system, planar_rotation=()))
    rng = np.random.default_rng(1)
    X = _queries(data, rng)
    J, _, V = f.query(X)
    J2, _, V2 = f.query(_moved(X, np.full(len(X), 1.0), np.zeros((len(X), 2))))
    both = V & V2
    assert not np.allclose(J2[both], J[both], rtol=1e-6)


def test_turned_steering_lands_where_the_turned_query_aims(unicycle_data):
    """U of a rotated query, turned back into the world, re-simulates to the rotated landing
    of the unrotated query's U: the extremal itself is rotated."""
    system, data = unicycle_data
    f = LearnedFunctions(validity_threshold=0.1).fit(data, system)
    rng = np.random.default_rng(2)
    X = _queries(data, rng)
    _, U, V = f.query(X)
    X, U = X[V][:40], U[V][:40]
    phi = rng.uniform(-np.pi, np.pi, len(X))
    shift = rng.uniform(-4.0, 4.0, (len(X), 2))
    Y = _moved(X, phi, shift)
    _, U2, V2 = f.query(Y)
    assert V2.all()
    land = landing_states(system, X[:, :3], U, 1.0, 0.01)
    land2 = landing_states(system, Y[:, :3], U2, 1.0, 0.01)
    assert np.isfinite(land).all()
    expected = _moved(np.hstack([land, land]), phi, shift)[:, :3]
    np.testing.assert_allclose(land2[:, :2], expected[:, :2], atol=1e-8)
    np.testing.assert_allclose(_wrap(land2[:, 2] - expected[:, 2]), 0.0, atol=1e-8)


def test_model_files_record_the_rotation(unicycle_data, tmp_path):
    from rrtcolearn.data.store import load_arrays, save_arrays
    from rrtcolearn.learn.models import FUNCTIONS_FORMAT

    system, data = unicycle_data
    f = LearnedFunctions(validity_threshold=0.1).fit(data, system)
    f.save(tmp_path / "f.npz")
    g, meta = LearnedFunctions.load(tmp_path / "f.npz")
    assert meta["version"] == 3 and g.features_ == f.features_
    X = _queries(data, np.random.default_rng(3))
    for a, b in zip(f.query(X), g.query(X), strict=True):
        np.testing.assert_array_equal(a, b)
    arrays, meta = load_arrays(tmp_path / "f.npz", FUNCTIONS_FORMAT)
    # a version-2 file (before the rotation) is translation-invariant only, and loads so
    old = {k: v for k, v in arrays.items() if k != "data.rotation"}
    save_arrays(tmp_path / "v2.npz", FUNCTIONS_FORMAT, old, {**meta, "version": 2})
    h, _ = LearnedFunctions.load(tmp_path / "v2.npz")
    assert h.features_.rotation == () and h.features_.invariant == (0, 1)
    raw = LearnedFunctions(validity_threshold=0.1).fit(
        data, dataclasses.replace(system, planar_rotation=()))
    for a, b in zip(raw.query(X), h.query(X), strict=True):
        np.testing.assert_array_equal(a, b)
    # a version-2 header on rotated data is not a file any version wrote
    save_arrays(tmp_path / "bad.npz", FUNCTIONS_FORMAT, arrays, {**meta, "version": 2})
    with pytest.raises(ArtefactError, match="version 2 with rotation"):
        LearnedFunctions.load(tmp_path / "bad.npz")


def test_check_system_verifies_a_claimed_rotation():
    from rrtcolearn.dynobench import unicycle1_v0
    from rrtcolearn.systems.check import SystemCheckError, check_system

    unicycle = unicycle1_v0()
    check_system(unicycle, n_samples=50)
    with pytest.raises(SystemCheckError, match="planar rotation"):  # the other sense
        check_system(dataclasses.replace(unicycle, planar_rotation=(1, 0, 2)), n_samples=50)
    quadrotor = make("quadrotor")  # x, z invariant, theta a heading, but gravity
    assert quadrotor.state_names[:3] == ("x", "z", "theta")
    with pytest.raises(SystemCheckError, match="planar rotation"):
        check_system(dataclasses.replace(quadrotor, planar_rotation=(0, 1, 2)), n_samples=50)


def test_a_fitted_run_records_its_rotation_and_reloads_it(tmp_path):
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    cfg = load_config(None, ['system.name="rrtcolearn.dynobench:unicycle1_v0"',
                             "generate.n_simulations=300", "clean.k_max=50",
                             'learn.learner="knn"'])
    pipeline.generate(cfg, tmp_path)
    pipeline.clean(cfg, tmp_path)
    model = pipeline.fit(cfg, tmp_path)
    recorded = pipeline.read_run_config(tmp_path).derived["learn.planar_rotation"]
    assert recorded.startswith("[0, 1, 2]: (x, y) turn with the heading theta")
    loaded = pipeline.load_model(tmp_path)
    assert loaded.functions.features_.rotation == (0, 1, 2)
    X = np.array([[1.0, 2.0, 0.5, 1.5, 2.25, 1.0]])
    for a, b in zip(model.functions.query(X), loaded.functions.query(X), strict=True):
        np.testing.assert_array_equal(a, b)

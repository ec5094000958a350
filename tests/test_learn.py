"""k-NN learners: predictions on small synthetic sets, circular averaging, validity."""

import numpy as np
import pytest

from rrtcolearn.learn import (
    CostToGoRegressor,
    LearnedFunctions,
    SteeringRegressor,
    ValidityClassifier,
)

X = np.array([[0.0, 0, 0, 0], [1, 0, 0, 0], [0, 1, 0, 0], [5, 5, 5, 5], [5, 5, 5, 6]])


def test_cost_to_go_is_the_saturated_mean_of_the_nearest():
    y = np.array([1.0, 2.0, 3.0, 10.0, 1e7])
    model = CostToGoRegressor(n_neighbors=3).fit(X, y)
    assert model.predict(np.array([[0.1, 0.1, 0, 0]]))[0] == pytest.approx(2.0)
    # neighbours 3, 4 and one of the near-origin points -> mean above 1e5 saturates
    assert model.predict(np.array([[5, 5, 5, 5.5]]))[0] == pytest.approx(1e5)
    low = CostToGoRegressor(n_neighbors=1).fit(X, np.array([0.0, 1, 1, 1, 1]))
    assert low.predict(X[:1])[0] == pytest.approx(1e-5)


def test_circular_parameter_averages_across_the_branch_cut():
    lo, hi = -np.pi / 2, 3 * np.pi / 2
    phi = np.array([hi - 0.01, lo + 0.01, lo + 0.03, 0.0, 0.0])
    y = np.stack([phi, np.array([0.1, 0.2, 0.3, 0.4, 0.5])], axis=1)
    model = SteeringRegressor(3, circular=(True,), low=(lo,), high=(hi,)).fit(X, y)
    pred = model.predict(np.array([[0.1, 0.1, 0, 0]]))[0]
    # the arithmetic mean would be about pi/2, the opposite side of the circle
    wrapped_gap = np.angle(np.exp(1j * (pred[0] - lo)))
    assert abs(wrapped_gap - 0.01) < 1e-9
    assert lo <= pred[0] < hi
    assert pred[1] == pytest.approx(0.2)


def test_validity_rejects_queries_far_from_the_data():
    model = ValidityClassifier(n_neighbors=2, threshold=1.5).fit(X)
    q = np.array([[0.2, 0.2, 0, 0], [5, 5, 5, 5.5], [20, 0, 0, 0]])
    np.testing.assert_array_equal(model.predict(q), [True, True, False])


def test_query_valid_prefilter_changes_nothing(paper_model):
    """The coverage grid only skips queries the exact summed-distance test would reject."""
    f = paper_model.functions
    rng = np.random.default_rng(0)
    x0 = rng.uniform([-4.7, -3.1], [1.5, 3.1], (3000, 2))
    q = np.hstack([x0, x0 + rng.normal(0, 0.7, (3000, 2))])
    cost, _, valid = f.query(q)
    rows, cost_v, _ = f.query_valid(q)
    np.testing.assert_array_equal(rows, np.flatnonzero(valid))
    np.testing.assert_allclose(cost_v, cost[valid])
    assert 0 < len(rows) < len(q)
    # with the 1-NN prefilter on (as after mostly rejected queries): the same answers
    f._accepted = 0.0
    for start in range(0, 3000, 32):
        f._accepted = 0.0
        got = f.query_valid(q[start : start + 32])
        want = np.flatnonzero(valid[start : start + 32])
        np.testing.assert_array_equal(got[0], want)
        np.testing.assert_array_equal(got[1], cost[start : start + 32][want])


def test_fit_contract_returns_self_and_refuses_too_few_samples():
    m = CostToGoRegressor(n_neighbors=3)
    assert m.fit(X, np.ones(5)) is m
    with pytest.raises(ValueError, match="at least 3"):
        CostToGoRegressor(n_neighbors=3).fit(X[:2], np.ones(2))
    from rrtcolearn.data.dataset import Dataset
    from rrtcolearn.systems import make

    data = Dataset(X[:, :2], X[:, 2:], np.ones(5), np.ones((5, 1)), np.ones(5), X[:, :2],
                   np.arange(5))
    f = LearnedFunctions(validity_threshold=100.0, periodic=False)
    assert f.fit(data, make("pendulum")) is f
    j, u, v = f.query(X[:2])
    assert j.shape == (2,) and u.shape == (2, 2) and v.all()


def test_circular_mean_stays_below_the_domain_end():
    """A mean angle a hair below the branch cut must not come back as exactly ``high``."""
    from rrtcolearn.learn.models import SteeringRegressor

    low, high = -np.pi / 2, 3 * np.pi / 2
    # just below high (almost the same angle as low, a turn on), and low twice: the mean
    # direction is a hair below the cut, which the mapping back used to round up to high
    y = np.array([[np.nextafter(high, low), 1.0], [low, 1.0], [low, 1.0]])
    reg = SteeringRegressor(3, circular=(True,), low=(low,), high=(high,)).fit(np.zeros((3, 1)), y)
    out = reg.predict(np.zeros((1, 1)))
    assert low <= out[0, 0] < high


def test_learned_functions_save_and_load_without_pickle(tmp_path):
    from rrtcolearn.data.generate import generate_data
    from rrtcolearn.errors import ArtefactError
    from rrtcolearn.systems import make

    system = make("pendulum")
    data, _ = generate_data(system, 5, 400, max_cost=2.0, max_state_distance=1.5)
    f = LearnedFunctions(validity_threshold=0.8).fit(data, system)
    # scikit-learn's contract: hyper-parameters untouched, learned state in *_ attributes
    assert f.validity_threshold == 0.8 and f.learner == "knn" and f.networks_ is None
    assert f.max_duration_ == float(data.duration.max())
    f.save(tmp_path / "f.npz", {"note": "test"})
    g, meta = LearnedFunctions.load(tmp_path / "f.npz")
    assert meta["note"] == "test"
    Q = np.hstack([data.x0[:50], data.x1[::-1][:50]])
    for a, b in zip(f.query(Q), g.query(Q), strict=True):
        np.testing.assert_array_equal(a, b)
    # the neighbour index comes back from its saved leaf order: the same tree
    for a, b in zip(f.cost_to_go_.index_._tree, g.cost_to_go_.index_._tree, strict=True):
        np.testing.assert_array_equal(a, b)
    raw = bytearray((tmp_path / "f.npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (tmp_path / "g.npz").write_bytes(bytes(raw))
    with pytest.raises(ArtefactError):
        LearnedFunctions.load(tmp_path / "g.npz")


def test_compiled_knn_answers_are_numpys():
    """`_mean_cost`, `_mean_steer` and `_covered` (compiled, for a planner's few rows) give
    the numbers of the numpy formulas they replace, to the bit."""
    from rrtcolearn.learn.models import _covered, _mean_cost, _mean_steer

    rng = np.random.default_rng(0)
    targets = np.column_stack([rng.uniform(-np.pi, np.pi, 500), rng.uniform(0, 2, 500)])
    cost = rng.uniform(0, 3, 500)
    idx = rng.integers(0, 500, size=(40, 3))
    np.testing.assert_array_equal(_mean_cost(cost, idx, 1e-5, 2.0),
                                  np.clip(cost[idx].mean(axis=1), 1e-5, 2.0))
    low, period = np.array([-np.pi, 0.0]), np.array([2 * np.pi, 0.0])
    angle = 2.0 * np.pi * (targets[:, :1] - low[0]) / period[0]
    cos_, sin_ = np.cos(angle), np.sin(angle)
    expect = targets[idx].mean(axis=1)
    mean = np.arctan2(sin_[idx].mean(axis=1), cos_[idx].mean(axis=1))[:, 0]
    val = low[0] + np.mod(mean, 2.0 * np.pi) * period[0] / (2.0 * np.pi)
    expect[:, 0] = np.where(val >= low[0] + period[0], low[0], val)
    from rrtcolearn.learn.models import SteeringRegressor

    steer = SteeringRegressor(3, circular=(True,), low=(-np.pi,), high=(np.pi,))
    steer.fit(rng.random((500, 4)), targets)
    np.testing.assert_array_equal(steer.predict_from_neighbours(None, idx), expect)
    out, cm, sm = _mean_steer(targets, cos_, sin_, idx)
    np.testing.assert_array_equal(out[:, 1], targets[idx, 1].mean(axis=1))
    np.testing.assert_array_equal(cm, cos_[idx].mean(axis=1))
    np.testing.assert_array_equal(sm, sin_[idx].mean(axis=1))
    grid = rng.random((6, 7, 5)) < 0.5
    lo, cell = np.array([-1.0, -2.0, 0.5]), 0.4
    X = rng.uniform(-2.0, 3.5, size=(300, 3))
    X[0, 1] = np.nan
    c = np.floor((X - lo) / cell)
    inside = ((c >= 0) & (c < grid.shape)).all(axis=1)
    flat = np.where(inside, np.nan_to_num(c, nan=0).astype(np.int64) @ grid.strides, 0)
    np.testing.assert_array_equal(
        _covered(X, lo, cell, np.array(grid.shape), np.array(grid.strides), grid.ravel()),
        inside & grid.ravel()[flat])

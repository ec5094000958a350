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


# --- Alg. 1's parent choice against brute force (issue 34) -------------------------------
# `best_valid` is the row of a batch of queries that V accepts with the least J, the first
# among equal J. Its k-NN branch goes through `query_valid` (a bounded tree search, a
# coverage prefilter, an adaptive 1-NN prefilter); its network branch through a different
# algorithm (rows sorted by the networks' J, V asked in that order until one is valid).
# Brute force here: every distance to every training input (and to its copies one turn over
# in the angles, where the model wraps them), the m smallest, V's sum, J's mean or the
# network's forward pass written out, and a plain argmin.


def _clustered_dataset(rng, n_centres: int = 30, per: int = 5):
    """A pendulum dataset of tight clusters (valid queries exist near each centre), some
    centres near the angle's seam; integer costs so that means tie exactly."""
    from rrtcolearn.data.dataset import Dataset

    centres = rng.uniform([-1.5 * np.pi, -np.pi, -1.5 * np.pi, -np.pi],
                          [0.5 * np.pi, np.pi, 0.5 * np.pi, np.pi], size=(n_centres, 4))
    centres[:5, 0] = rng.uniform(-1.5 * np.pi, -1.45 * np.pi, 5)  # at the low seam
    centres[5:10, 0] = rng.uniform(0.45 * np.pi, 0.5 * np.pi, 5)  # at the high seam
    X = np.repeat(centres, per, axis=0) + rng.normal(0.0, 0.04, size=(n_centres * per, 4))
    X[:, 0] = np.clip(X[:, 0], -1.5 * np.pi, 0.5 * np.pi - 1e-9)
    N = len(X)
    return Dataset(x0=X[:, :2], x1=X[:, 2:], cost=rng.integers(1, 7, N).astype(float),
                   params=rng.uniform(-0.5 * np.pi, 1.5 * np.pi, (N, 1)),
                   duration=rng.uniform(0.1, 1.0, N), costate=np.zeros((N, 2)),
                   simulation=np.arange(N)), centres


def _queries(rng, data, centres, q: int) -> np.ndarray:
    """Near data (mostly valid), anywhere (mostly invalid), and repeats (exact ties)."""
    near = data.inputs[rng.integers(0, len(data), q)] + rng.normal(0.0, 0.03, (q, 4))
    near[:, 0] = np.clip(near[:, 0], -1.5 * np.pi, 0.5 * np.pi - 1e-9)
    anywhere = rng.uniform(centres.min(axis=0), centres.max(axis=0), (q, 4))
    X = np.concatenate([near, anywhere])[rng.permutation(2 * q)][: rng.integers(1, 2 * q + 1)]
    return np.concatenate([X, X[rng.integers(0, len(X), rng.integers(0, 4))]])


def _brute_neighbours(data, X: np.ndarray, m: int, periodic: bool):
    """(data rows (Q, m) and distances (Q, m) of the m nearest training inputs) over every
    point, the copies one turn over in theta (of x0 and x1 together) included where
    ``periodic``. The pendulum's metric weights are 2 pi / (its box's width) = 1."""
    scale = np.tile(2.0 * np.pi / (np.array([0.5, 1.0]) * np.pi - np.array([-1.5, -1.0])
                                   * np.pi), 2)
    points, source = data.inputs, np.arange(len(data))
    if periodic:
        turn = np.array([2.0 * np.pi, 0.0, 2.0 * np.pi, 0.0])
        points = np.concatenate([points - turn, points, points + turn])
        source = np.tile(source, 3)
    d = np.sqrt((((X[:, None, :] - points[None]) * scale) ** 2).sum(axis=2))
    nearest = np.argsort(d, axis=1, kind="stable")[:, :m]
    return source[nearest], np.take_along_axis(d, nearest, axis=1)


def _brute_best(valid: np.ndarray, J: np.ndarray) -> int:
    """The first valid row of least J, -1 if none."""
    if not valid.any():
        return -1
    return int(np.flatnonzero(valid & (J == J[valid].min()))[0])


@pytest.mark.parametrize(("periodic", "offset"), [(False, False), (True, False), (True, True)])
def test_best_valid_knn_is_the_brute_force_argmin(periodic, offset):
    """``offset`` (RRT*'s choose-parent, a parent's cost-to-come per row): the least J plus
    it; integer offsets, so that ties still occur."""
    from rrtcolearn.learn.models import best_valid
    from rrtcolearn.systems import make

    system = make("pendulum")
    rng = np.random.default_rng(11)
    data, centres = _clustered_dataset(rng)
    m, threshold, bounds = 3, 0.3, (1e-5, 1e5)
    f = LearnedFunctions(n_neighbors=m, validity_threshold=threshold, cost_bounds=bounds,
                         periodic=periodic).fit(data, system)
    found = ties = 0
    for _ in range(150):
        X = _queries(rng, data, centres, int(rng.integers(1, 25)))
        rows, dist = _brute_neighbours(data, X, m, periodic)
        valid = dist.sum(axis=1) <= threshold
        J = np.clip(data.cost[rows].mean(axis=1), *bounds)
        extra = rng.integers(0, 3, len(X)).astype(float) if offset else None
        want = _brute_best(valid, J if extra is None else J + extra)
        row, neighbours = best_valid(f, X, extra)
        assert row == want
        if want < 0:
            assert neighbours is None
            continue
        found += 1
        total = J if extra is None else J + extra
        ties += int((valid & (total == total[want])).sum() > 1)
        # the neighbours handed to U are the brute-force ones (as data rows)
        assert sorted(f.source_[neighbours].tolist()) == sorted(rows[want].tolist())
    assert found >= 50 and ties >= 10  # both outcomes and the tie rule were exercised


@pytest.mark.filterwarnings("ignore:Got `batch_size`:UserWarning")  # 150 rows: one batch
@pytest.mark.parametrize("offset", [False, True])
def test_best_valid_network_branch_is_the_brute_force_argmin(offset):
    """The networks' J (their forward pass written out here from their weights: standardise,
    relu layers, undo the standardisation, exp of the log cost, clip) and brute-force V;
    ``offset``: the least J plus a per-row offset (a parent's cost-to-come)."""
    from rrtcolearn.learn.models import best_valid
    from rrtcolearn.systems import make

    system = make("pendulum")
    rng = np.random.default_rng(12)
    data, centres = _clustered_dataset(rng)
    m, threshold, bounds = 3, 0.3, (1e-5, 1e5)
    f = LearnedFunctions(n_neighbors=m, validity_threshold=threshold, cost_bounds=bounds,
                         learner="mlp", mlp_hidden=(16, 16), mlp_max_iter=20,
                         mlp_max_samples=None, seed=3).fit(data, system)
    net = f.networks_[0]

    def network_cost(X: np.ndarray) -> np.ndarray:
        h = (X - net.x_mean_) / net.x_std_
        for w, b in zip(net.coefs_[:-1], net.intercepts_[:-1], strict=True):
            h = np.maximum(h @ w + b, 0.0)
        z = (h @ net.coefs_[-1] + net.intercepts_[-1])[:, 0] * net.z_std_[0] + net.z_mean_[0]
        return np.clip(np.exp(z), *bounds)

    found = 0
    for _ in range(150):
        X = _queries(rng, data, centres, int(rng.integers(1, 25)))
        _, dist = _brute_neighbours(data, X, m, True)
        valid = dist.sum(axis=1) <= threshold
        extra = rng.uniform(0.0, 3.0, len(X)) if offset else None
        J = network_cost(X) if extra is None else network_cost(X) + extra
        want = _brute_best(valid, J)
        row, neighbours = best_valid(f, X, extra)
        assert neighbours is None
        if want < 0:
            assert row == -1
            continue
        found += 1
        # the same row, or one whose J equals the least to rounding (the networks' batch
        # and row-by-row products differ in the last bits)
        assert valid[row] and J[row] <= J[want] * (1 + 1e-12), (row, want)
        assert row == want or abs(J[row] - J[want]) <= 1e-12 * J[want]
    assert found >= 50


def _ridge_reference(P: np.ndarray, Y: np.ndarray, q: np.ndarray, ridge: float) -> np.ndarray:
    """Intercept of the ridge fit of Y on P - q, by least squares on the augmented system
    [1, P - q; 0, sqrt(r) I] b = [Y; 0] (numpy's lstsq, written here independently)."""
    D = P - q
    K, d = D.shape
    r = ridge * float(np.sum(D**2)) / K
    A = np.vstack([np.hstack([np.ones((K, 1)), D]),
                   np.hstack([np.zeros((d, 1)), np.sqrt(r) * np.eye(d)])])
    B = np.vstack([Y, np.zeros((d, Y.shape[1]))])
    return np.linalg.lstsq(A, B, rcond=None)[0][0]


def test_local_linear_steering_is_the_brute_force_ridge_fit():
    rng = np.random.default_rng(3)
    P = rng.normal(size=(200, 4))
    lo, hi = -np.pi, np.pi
    # a circular column near its branch cut and a smooth non-circular one plus duration
    phi = np.mod(3.0 + 0.4 * P[:, 0] - 0.2 * P[:, 2] + 0.05 * rng.normal(size=200) - lo,
                 hi - lo) + lo
    y = np.stack([phi, 1.0 + P[:, 1] + 0.3 * P[:, 3] ** 2, 2.0 + 0.1 * P[:, 0]], axis=1)
    model = SteeringRegressor(3, circular=(True, False), low=(lo, 0.0),
                              high=(hi, 10.0)).fit(P, y)
    Q = rng.normal(size=(25, 4)) * 0.8
    K, ridge = 16, 0.05
    _, idx = model.index_.query(Q, K)
    got = model.predict_local(Q, idx, ridge, clip=False)
    for r in range(len(Q)):
        Y = y[idx[r]].copy()
        # unwrap the angle around the nearest neighbour's, fit, wrap back
        Y[:, 0] = Y[0, 0] + np.angle(np.exp(1j * (Y[:, 0] - Y[0, 0])))
        want = _ridge_reference(P[idx[r]], Y, Q[r], ridge)
        want[0] = lo + np.mod(want[0] - lo, hi - lo)
        assert abs(np.angle(np.exp(1j * (got[r, 0] - want[0])))) < 1e-9
        np.testing.assert_allclose(got[r, 1:], want[1:], rtol=1e-9, atol=1e-9)
    # clipped: within the range the neighbours span, and the unclipped value where inside
    clipped = model.predict_local(Q, idx, ridge)
    span = y[idx][:, :, 1:]
    inside = (got[:, 1:] >= span.min(axis=1)) & (got[:, 1:] <= span.max(axis=1))
    assert np.all(clipped[:, 1:] >= span.min(axis=1)) and np.all(
        clipped[:, 1:] <= span.max(axis=1))
    np.testing.assert_array_equal(clipped[:, 1:][inside], got[:, 1:][inside])
    assert inside.any()


def test_local_linear_steering_is_exact_on_an_affine_map():
    """First-order exactness: without the ridge an affine map of the features is
    reproduced at any query inside the neighbours' range, where the mean is off."""
    rng = np.random.default_rng(4)
    P = rng.uniform(-1, 1, size=(300, 3))
    y = np.stack([0.5 + P @ [1.0, -2.0, 0.5], 3.0 + P @ [0.2, 0.1, -0.4]], axis=1)
    model = SteeringRegressor(3).fit(P, y)
    Q = rng.uniform(-0.5, 0.5, size=(20, 3))
    _, idx = model.index_.query(Q, 12)
    want = np.stack([0.5 + Q @ [1.0, -2.0, 0.5], 3.0 + Q @ [0.2, 0.1, -0.4]], axis=1)
    np.testing.assert_allclose(model.predict_local(Q, idx, 0.0), want, atol=1e-10)
    assert np.abs(model.predict(Q) - want).max() > 1e-3


def test_local_linear_steering_is_deterministic_and_survives_save_load(tmp_path):
    from rrtcolearn.data.generate import generate_data
    from rrtcolearn.systems import make

    system = make("pendulum")
    data, _ = generate_data(system, 5, 400, max_cost=2.0, max_state_distance=1.5)
    f = LearnedFunctions(validity_threshold=0.8, steering="local_linear").fit(data, system)
    Q = np.hstack([data.x0[:60], data.x1[::-1][:60]])
    a = f.query(Q)[1]
    b = LearnedFunctions(validity_threshold=0.8, steering="local_linear").fit(
        data, system).query(Q)[1]
    np.testing.assert_array_equal(a, b)
    mean = LearnedFunctions(validity_threshold=0.8).fit(data, system).query(Q)[1]
    assert not np.array_equal(a, mean)
    f.save(tmp_path / "f.npz")
    g, meta = LearnedFunctions.load(tmp_path / "f.npz")
    assert g.steering == meta["params"]["steering"] == "local_linear"
    np.testing.assert_array_equal(g.query(Q)[1], a)
    # switched back, the model answers as the mean does; saved so, its file has no
    # steering key (the file of before the option) and loads as the mean
    np.testing.assert_array_equal(g.set_steering("mean").query(Q)[1], mean)
    g.save(tmp_path / "g.npz")
    h, meta = LearnedFunctions.load(tmp_path / "g.npz")
    assert "steering" not in meta["params"] and h.steering == "mean"
    np.testing.assert_array_equal(h.query(Q)[1], mean)
    with pytest.raises(ValueError, match="steering"):
        LearnedFunctions(steering="median").fit(data, system)
    # a file naming a predictor this rrtcolearn does not have is refused, not guessed at
    from rrtcolearn.data.store import load_arrays, save_arrays
    from rrtcolearn.errors import ArtefactError
    from rrtcolearn.learn.models import FUNCTIONS_FORMAT

    arrays, header = load_arrays(tmp_path / "f.npz", FUNCTIONS_FORMAT)
    header["params"]["steering"] = "median"
    save_arrays(tmp_path / "bad.npz", FUNCTIONS_FORMAT, arrays, header)
    with pytest.raises(ArtefactError, match="median"):
        LearnedFunctions.load(tmp_path / "bad.npz")


def test_the_learn_section_chooses_the_steering_predictor(small_dataset, pendulum):
    from rrtcolearn.config import load_config
    from rrtcolearn.errors import ConfigError
    from rrtcolearn.pipeline import fit_functions

    base = fit_functions(pendulum, small_dataset, load_config(overrides=[
        "learn.validity_threshold=0.8", 'learn.learner="knn"']))
    local = fit_functions(pendulum, small_dataset, load_config(overrides=[
        "learn.validity_threshold=0.8", 'learn.learner="knn"', 'learn.steering="local_linear"']))
    assert base.steering == "mean" and local.steering == "local_linear"
    Q = small_dataset.inputs[:40]
    np.testing.assert_array_equal(base.query(Q)[0], local.query(Q)[0])  # J is the same
    assert not np.array_equal(base.query(Q)[1], local.query(Q)[1])
    with pytest.raises(ConfigError):
        load_config(overrides=['learn.steering="median"'])

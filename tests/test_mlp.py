"""NeuralRegressor: accuracy on the double integrator, circular targets, determinism and the
plain-array round trip (including rejection of damaged or foreign array sets)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import sklearn  # noqa: F401  (an extra: `make test` installs it; missing, the suite fails)

from rrtcolearn.learn.mlp import NeuralRegressor
from rrtcolearn.systems.double_integrator import optimal_cost

LOW, HIGH = -np.pi / 2, 3 * np.pi / 2  # the pendulum's phi domain: a branch cut at LOW


def double_integrator_pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Inputs (x0, x1) (N, 4) in [-2, 2]^4 with |x1 - x0| <= 1 per axis, exact cost (N,)."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(-2, 2, size=(n, 2))
    x1 = np.clip(x0 + rng.uniform(-1, 1, size=(n, 2)), -2, 2)
    y = optimal_cost(x0, x1, 1.0)
    ok = np.isfinite(y) & (y > 0)
    return np.hstack([x0, x1])[ok], y[ok]


def small_net(**kw) -> NeuralRegressor:
    return NeuralRegressor(**{"hidden": (16, 16), "max_iter": 40, **kw})


@pytest.fixture(scope="module")
def cost_model() -> tuple[NeuralRegressor, np.ndarray, np.ndarray]:
    X, y = double_integrator_pairs(4000, seed=1)
    return NeuralRegressor(hidden=(32, 32), max_iter=300, log_target=True).fit(X, y), X, y


def test_fits_the_double_integrator_cost_to_go(cost_model):
    model, _, _ = cost_model
    Xt, yt = double_integrator_pairs(1000, seed=2)
    pred = model.predict(Xt)
    assert pred.shape == yt.shape
    # measured 0.07-0.10 over seeds 0-4 (a constant guess: ~0.6); bound with 2x margin
    assert np.median(np.abs(pred - yt) / yt) < 0.2
    assert (pred > 0).all()  # log_target: positive by construction


def test_circular_targets_near_the_branch_cut_stay_in_range():
    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, size=(3000, 2))
    # phi crosses the cut at x0 = 0: just below HIGH for x0 < 0, just above LOW for x0 > 0
    phi = LOW + np.mod(0.4 * X[:, 0], HIGH - LOW)
    y = np.stack([1.0 + X[:, 1] ** 2, phi], axis=1)
    model = NeuralRegressor(hidden=(32, 32), max_iter=100, circular=(False, True),
                            low=(0.0, LOW), high=(0.0, HIGH)).fit(X, y)
    Xt = np.stack([np.linspace(-0.2, 0.2, 201), np.zeros(201)], axis=1)
    pred = model.predict(Xt)
    assert pred.shape == (201, 2)
    assert ((pred[:, 1] >= LOW) & (pred[:, 1] < HIGH)).all()
    want = LOW + np.mod(0.4 * Xt[:, 0], HIGH - LOW)
    err = np.angle(np.exp(1j * (pred[:, 1] - want)))  # circular difference
    assert np.abs(err).max() < 0.1
    assert np.abs(pred[:, 0] - 1.0).max() < 0.1


def test_an_angle_rounding_up_to_high_wraps_to_low():
    # a network whose output is exactly (cos, sin) = (1, -1e-300): atan2 mod 2 pi rounds to
    # 2 pi, so low + angle * period / (2 pi) would be high itself
    arrays = {
        "mlp_format": np.array(1), "hidden": np.array([2]), "max_iter": np.array(1),
        "seed": np.array(0), "alpha": np.array(0.0), "max_samples": np.array(-1),
        "circular": np.array([True]), "low": np.array([LOW]), "high": np.array([HIGH]),
        "log_target": np.array(False), "n_targets_": np.array(1),
        "flat_target_": np.array(True), "n_iter_": np.array(1),
        "x_mean_": np.zeros(1), "x_std_": np.ones(1),
        "z_mean_": np.array([1.0, -1e-300]), "z_std_": np.ones(2),
        "coef_0_": np.zeros((1, 2)), "intercept_0_": np.zeros(2),
        "coef_1_": np.zeros((2, 2)), "intercept_1_": np.zeros(2),
    }
    pred = NeuralRegressor.from_arrays(arrays).predict(np.zeros((3, 1)))
    assert pred.shape == (3,)
    assert (pred == LOW).all()


def test_fit_is_deterministic_and_the_seed_matters():
    X, y = double_integrator_pairs(1500, seed=4)
    Xt, _ = double_integrator_pairs(300, seed=5)
    a = small_net(seed=7, max_samples=1000).fit(X, y).predict(Xt)
    b = small_net(seed=7, max_samples=1000).fit(X, y).predict(Xt)
    c = small_net(seed=8, max_samples=1000).fit(X, y).predict(Xt)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_array_round_trip_is_bit_identical(cost_model, tmp_path):
    model, X, _ = cost_model
    arrays = model.to_arrays()
    assert all(isinstance(v, np.ndarray) and v.dtype != object for v in arrays.values())
    restored = NeuralRegressor.from_arrays(arrays)
    np.savez(tmp_path / "mlp.npz", **arrays)
    with np.load(tmp_path / "mlp.npz", allow_pickle=False) as f:
        loaded = NeuralRegressor.from_arrays(f)
    want = model.predict(X)
    assert np.array_equal(restored.predict(X), want)
    assert np.array_equal(loaded.predict(X), want)
    for name in ("hidden", "max_iter", "seed", "alpha", "max_samples", "circular", "low",
                 "high", "log_target"):
        assert getattr(loaded, name) == getattr(model, name), name


def test_multi_output_round_trip_keeps_the_layout():
    X, y = double_integrator_pairs(600, seed=6)
    Y = np.stack([y, LOW + np.mod(X[:, 0], HIGH - LOW)], axis=1)
    model = small_net(max_samples=None, circular=(False, True), low=(0.0, LOW),
                      high=(0.0, HIGH)).fit(X, Y)
    restored = NeuralRegressor.from_arrays(model.to_arrays())
    assert restored.max_samples is None
    assert model.predict(X).shape == (len(X), 2)
    assert np.array_equal(restored.predict(X), model.predict(X))


def _damage(arrays: dict[str, np.ndarray], how: str) -> dict[str, np.ndarray]:
    a = dict(arrays)
    if how == "missing key":
        del a["z_std_"]
    elif how == "missing layer":
        del a["coef_1_"]
    elif how == "unexpected key":
        a["coef_9_"] = np.zeros((2, 2))
    elif how == "wrong shape":
        a["coef_0_"] = a["coef_0_"][:, :-1]
    elif how == "wrong hidden":
        a["hidden"] = np.array([3, 3])
    elif how == "non-finite weight":
        a["coef_1_"] = a["coef_1_"].copy()
        a["coef_1_"][0, 0] = np.nan
    elif how == "infinite mean":
        a["x_mean_"] = np.full_like(a["x_mean_"], np.inf)
    elif how == "zero std":
        a["x_std_"] = np.zeros_like(a["x_std_"])
    elif how == "integer weights":
        a["intercept_0_"] = a["intercept_0_"].astype(np.int64)
    elif how == "string array":
        a["alpha"] = np.array("1e-4")
    elif how == "version":
        a["mlp_format"] = np.array(99)
    elif how == "foreign":
        a = {"cost_": np.ones(3), "targets_": np.ones((3, 2))}
    elif how == "bad period":
        a["circular"] = np.array([True])
        a["low"] = np.array([1.0])
        a["high"] = np.array([1.0])
    return a


@pytest.mark.parametrize("how", [
    "missing key", "missing layer", "unexpected key", "wrong shape", "wrong hidden",
    "non-finite weight", "infinite mean", "zero std", "integer weights", "string array",
    "version", "foreign", "bad period",
])
def test_from_arrays_rejects_damaged_or_foreign_sets(cost_model, how):
    arrays = _damage(cost_model[0].to_arrays(), how)
    with pytest.raises(ValueError) as info:
        NeuralRegressor.from_arrays(arrays)
    assert "\n" not in str(info.value)


def test_fit_rejects_bad_targets():
    X = np.random.default_rng(0).uniform(size=(50, 2))
    with pytest.raises(ValueError, match="finite"):
        small_net().fit(X, np.where(np.arange(50) == 3, np.nan, 1.0))
    with pytest.raises(ValueError, match="positive"):
        small_net(log_target=True).fit(X, X[:, 0] - 0.5)
    with pytest.raises(ValueError, match="low < high"):
        small_net(circular=(True,), low=(1.0,), high=(0.0,)).fit(X, X[:, 0])
    with pytest.raises(ValueError, match="shape"):
        small_net().fit(X, np.ones(49))


def test_missing_sklearn_gives_an_install_hint(monkeypatch):
    for name in ("sklearn", "sklearn.exceptions", "sklearn.neural_network"):
        monkeypatch.setitem(sys.modules, name, None)  # None in sys.modules: ImportError
    X = np.zeros((20, 2))
    with pytest.raises(ImportError, match=r"pip install 'rrtcolearn\[mlp\]'"):
        NeuralRegressor().fit(X, np.ones(20))


def test_an_unfitted_model_says_so():
    with pytest.raises(RuntimeError, match="not fitted"):
        NeuralRegressor().predict(np.zeros((1, 4)))

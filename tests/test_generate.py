"""Alg. 2: the data are optimal trajectory segments that satisfy their stopping rules."""

import numpy as np
from tests.conftest import rk4_numpy

from rrtcolearn.data.generate import generate_data


def test_points_respect_stopping_rules(small_dataset):
    d = small_dataset
    assert len(d) > 1000
    assert d.cost.max() <= 2.0
    assert np.linalg.norm(d.x1 - d.x0, axis=1).max() <= 1.5
    assert d.duration.min() >= 0.01 - 1e-12
    # cost >= w * t since the running cost is w + u^2/2
    assert np.all(d.cost >= d.duration - 1e-9)


def test_points_resimulate(small_dataset):
    d = small_dataset
    rng = np.random.default_rng(0)
    for i in rng.choice(len(d), 30, replace=False):
        steps = round(d.duration[i] / 0.01)
        traj = rk4_numpy(np.r_[d.x0[i], d.costate[i], 0.0], 1.0, 0.01, steps)
        np.testing.assert_allclose(traj[-1, :2], d.x1[i], atol=1e-9)
        assert abs(traj[-1, 4] - d.cost[i]) < 1e-9


def test_starts_satisfy_h_star_zero(small_dataset):
    d = small_dataset
    lam = d.costate
    h = 1.0 + lam[:, 0] * d.x0[:, 1] + lam[:, 1] * np.sin(d.x0[:, 0]) - 0.5 * lam[:, 1] ** 2
    assert np.abs(h).max() < 1e-9


def test_every_step_is_a_point_until_the_stop(pendulum):
    d, stats = generate_data(pendulum, 3, 50, chunk_size=50)
    for s in np.unique(d.simulation):
        dur = np.sort(d.duration[d.simulation == s])
        np.testing.assert_allclose(dur, 0.01 * np.arange(1, len(dur) + 1))
    assert stats.points == len(d)


def test_same_seed_same_data_bit_identical(pendulum):
    a, _ = generate_data(pendulum, 11, 300, chunk_size=100)
    b, _ = generate_data(pendulum, 11, 300, chunk_size=100)
    for k, v in a.arrays().items():
        assert np.array_equal(v, b.arrays()[k]), k
    c, _ = generate_data(pendulum, 12, 300, chunk_size=100)
    assert not np.array_equal(a.x1[:10], c.x1[:10])

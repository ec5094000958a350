"""Pontryagin optimality conditions of the pendulum (paper Section 3)."""

import numpy as np
import pytest
from tests.conftest import pendulum_rhs_numpy

from rrtcolearn.integrate import rollout

W = [1.0, 0.3]


def h_star(x, lam, w):
    return w + lam[:, 0] * x[:, 1] + lam[:, 1] * np.sin(x[:, 0]) - 0.5 * lam[:, 1] ** 2


@pytest.mark.parametrize("w", W)
def test_sampled_costates_satisfy_h_star_zero(pendulum, w):
    rng = np.random.default_rng(0)
    x = rng.uniform(pendulum.state_low, pendulum.state_high, (5000, 2))
    p = rng.uniform(pendulum.param_low, pendulum.param_high, (5000, 1))
    lam, valid = pendulum.costate_from_params(x, p, w)
    assert valid.mean() > 0.5
    u = pendulum.optimal_control(x, lam)
    h = pendulum.hamiltonian(x[valid], lam[valid], u[valid], w)
    assert np.max(np.abs(h)) < 1e-9
    np.testing.assert_allclose(h_star(x[valid], lam[valid], w), 0, atol=1e-9)
    # the square-root argument is negative exactly where no costate exists
    arg = np.sin(x[:, 0]) ** 2 + 2 * (w + np.tan(p[:, 0]) * x[:, 1])
    np.testing.assert_array_equal(valid, arg >= 0)


def test_optimal_control_minimises_hamiltonian(pendulum):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200, 2))
    lam = rng.normal(size=(200, 2))
    u_star = pendulum.optimal_control(x, lam)
    h_star_val = pendulum.hamiltonian(x, lam, u_star, 1.0)
    for du in (-1.0, -1e-3, 1e-3, 0.5):
        assert np.all(pendulum.hamiltonian(x, lam, u_star + du, 1.0) > h_star_val)
    eps = 1e-6
    dh_du = (pendulum.hamiltonian(x, lam, u_star + eps, 1.0)
             - pendulum.hamiltonian(x, lam, u_star - eps, 1.0)) / (2 * eps)
    np.testing.assert_allclose(dh_du, 0, atol=1e-6)


def test_ode_is_hamiltonian_flow(pendulum):
    """x' = dH*/dlambda and lambda' = -dH*/dx, by central finite differences."""
    rng = np.random.default_rng(2)
    w, eps = 1.0, 1e-6
    for _ in range(50):
        z = np.r_[rng.normal(size=4), 0.0]
        out = np.empty(5)
        pendulum.rhs(z, w, out)
        grad = np.empty(4)
        for j in range(4):
            zp, zm = z[:4].copy(), z[:4].copy()
            zp[j] += eps
            zm[j] -= eps
            grad[j] = (h_star(zp[None, :2], zp[None, 2:], w)[0]
                       - h_star(zm[None, :2], zm[None, 2:], w)[0]) / (2 * eps)
        np.testing.assert_allclose(out[:2], grad[2:], atol=1e-7)
        np.testing.assert_allclose(out[2:4], -grad[:2], atol=1e-7)
        # the running cost under u* = -lambda_omega
        assert out[4] == pytest.approx(w + 0.5 * z[3] ** 2)
        np.testing.assert_allclose(out, pendulum_rhs_numpy(z, w), atol=1e-15)


def test_h_star_conserved_along_rk4_trajectories(pendulum):
    rng = np.random.default_rng(3)
    x = rng.uniform(pendulum.state_low, pendulum.state_high, (200, 2))
    p = rng.uniform(pendulum.param_low, pendulum.param_high, (200, 1))
    lam, valid = pendulum.costate_from_params(x, p, 1.0)
    worst = 0.0
    for i in np.flatnonzero(valid)[:50]:
        traj = rollout(pendulum, np.r_[x[i], lam[i], 0.0], 1.0, 0.01, 100)
        if not np.isfinite(traj).all() or np.abs(traj[:, 2:4]).max() > 50:
            continue
        worst = max(worst, np.abs(h_star(traj[:, :2], traj[:, 2:4], 1.0)).max())
    assert worst < 1e-6


def test_rk4_is_fourth_order(pendulum):
    z0 = np.array([-2.0, 0.5, 0.3, -0.4, 0.0])
    t_end = 1.0
    ref = rollout(pendulum, z0, 1.0, t_end / 4096, 4096)[-1]
    errors = [np.abs(rollout(pendulum, z0, 1.0, t_end / n, n)[-1] - ref).max()
              for n in (16, 32, 64)]
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    for r in ratios:
        assert 13 < r < 19  # 2^4 = 16

"""Pontryagin optimality conditions of the pendulum (paper Section 3), and the registered
pendulum (derived by the generic symbolic path) against its equations derived by hand."""

import numpy as np
import pytest

from rrtcolearn.data.generate import generate_data, sample_starts
from rrtcolearn.integrate import rollout
from rrtcolearn.systems.symbolic import SymbolicSystem

W = [1.0, 0.3]


# --------------------------------------------------------------------------- hand-derived reference
# Plain numpy, written out by hand from H = w + u^2/2 + l_th*omega + l_om*(sin(theta) + u).


def ref_rhs(z, w):
    """State+costate ODE under u* = -l_om and the running cost, rows z = (th, om, lth, lom, c)."""
    th, om, lth, lom = z[:, 0], z[:, 1], z[:, 2], z[:, 3]
    return np.stack([om, np.sin(th) - lom, -lom * np.cos(th), -lth, w + 0.5 * lom**2], axis=1)


def ref_optimal_control(x, lam):
    return -lam[:, 1:2]


def ref_hamiltonian(x, lam, u, w):
    return w + 0.5 * u[:, 0] ** 2 + lam[:, 0] * x[:, 1] + lam[:, 1] * (np.sin(x[:, 0]) + u[:, 0])


def ref_dynamics(x, u):
    return np.stack([x[:, 1], np.sin(x[:, 0]) + u[:, 0]], axis=1)


def ref_costate_from_params(x, p, w):
    """l_th = tan(phi), l_om = sin(th) + sign(cos(phi)) sqrt(sin(th)^2 + 2 (w + l_th om))."""
    s, l_th = np.sin(x[:, 0]), np.tan(p[:, 0])
    arg = s**2 + 2.0 * (w + l_th * x[:, 1])
    valid = arg >= 0.0
    l_om = s + np.sign(np.cos(p[:, 0])) * np.sqrt(np.where(valid, arg, 0.0))
    return np.stack([l_th, l_om], axis=1), valid


def ref_rk4(z0, w, dt, steps):
    """(steps+1, N, 5): classical RK4 on ``ref_rhs``, the stages in the package's order."""
    z = np.array(z0, dtype=float)
    out = [z]
    for _ in range(steps):
        k1 = ref_rhs(z, w)
        k2 = ref_rhs(z + 0.5 * dt * k1, w)
        k3 = ref_rhs(z + 0.5 * dt * k2, w)
        k4 = ref_rhs(z + dt * k3, w)
        z = z + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        out.append(z)
    return np.array(out)


def close(actual, desired):
    np.testing.assert_allclose(actual, desired, rtol=1e-12, atol=1e-12)


def test_registered_pendulum_is_the_generic_one(pendulum):
    assert isinstance(pendulum, SymbolicSystem)
    assert pendulum.param_names == ("phi",)
    np.testing.assert_array_equal(pendulum.param_low, [-0.5 * np.pi])
    np.testing.assert_array_equal(pendulum.param_high, [1.5 * np.pi])
    assert pendulum.param_circular == (True,)
    assert pendulum.angle_dims == (0,)
    np.testing.assert_array_equal(pendulum.state_low, [-1.5 * np.pi, -np.pi])
    np.testing.assert_array_equal(pendulum.state_high, [0.5 * np.pi, np.pi])


def test_equations_match_hand_derived(pendulum):
    rng = np.random.default_rng(10)
    w = 0.7
    z = np.c_[rng.normal(scale=3.0, size=(500, 4)), rng.normal(size=500)]
    out = np.empty((500, 5))
    for i in range(500):
        pendulum.rhs(z[i], w, out[i])
        assert pendulum.input_max_abs_jit(z[i]) == abs(z[i, 3])
    close(out, ref_rhs(z, w))
    x, lam, u = z[:, :2], z[:, 2:4], rng.normal(scale=3.0, size=(500, 1))
    close(pendulum.optimal_control(x, lam), ref_optimal_control(x, lam))
    close(pendulum.hamiltonian(x, lam, u, w), ref_hamiltonian(x, lam, u, w))
    close(pendulum.dynamics(x, u), ref_dynamics(x, u))


@pytest.mark.parametrize("w", W)
def test_costate_parametrisation_matches_hand_derived(pendulum, w):
    rng = np.random.default_rng(11)
    x = rng.uniform(pendulum.state_low, pendulum.state_high, (2000, 2))
    p = rng.uniform(pendulum.param_low, pendulum.param_high, (2000, 1))
    ref, ref_valid = ref_costate_from_params(x, p, w)
    assert 0.5 < ref_valid.mean() < 1.0
    lam, valid = pendulum.costate_from_params(x, p, w)
    np.testing.assert_array_equal(valid, ref_valid)
    close(lam[valid], ref[valid])
    out = np.empty(2)
    for i in range(len(x)):
        assert pendulum.costate_from_params_jit(x[i], p[i], w, out) == ref_valid[i]
        if ref_valid[i]:
            close(out, ref[i])


@pytest.mark.parametrize("w", W)
def test_rollout_matches_hand_derived_rk4(pendulum, w):
    rng = np.random.default_rng(12)
    x = rng.uniform(pendulum.state_low, pendulum.state_high, (40, 2))
    p = rng.uniform(pendulum.param_low, pendulum.param_high, (40, 1))
    lam, valid = ref_costate_from_params(x, p, w)
    z0 = np.c_[x, lam, np.zeros(40)][valid]
    ref = ref_rk4(z0, w, 0.01, 150)
    for i in range(len(z0)):
        close(rollout(pendulum, z0[i], w, 0.01, 150), ref[:, i])


@pytest.mark.parametrize("w", W)
def test_generated_dataset_matches_hand_derived(pendulum, w):
    """Alg. 2's data against the reference RK4 from the reference costates, with the same
    stopping rule (cost above max_cost or state farther than max_dist from its start)."""
    seed, n_sims, dt, max_cost, max_dist = 4, 300, 0.01, 2.0, 1.5
    data, stats = generate_data(pendulum, seed, n_sims, time_weight=w, dt=dt,
                                max_cost=max_cost, max_state_distance=max_dist, chunk_size=128)
    x0, p, _, _ = sample_starts(pendulum, seed, 0, n_sims, w)
    lam, valid = ref_costate_from_params(x0, p, w)
    assert stats.invalid_costates == (~valid).sum()
    max_steps = int(np.ceil(max_cost / (w * dt)) + 1)
    traj = ref_rk4(np.c_[x0, lam, np.zeros(n_sims)][valid], w, dt, max_steps)
    sims = np.flatnonzero(valid)
    # reference lengths: steps before the first one that breaks a bound
    dist2 = np.sum((traj[1:, :, :2] - traj[0, None, :, :2]) ** 2, axis=2)
    stop = (traj[1:, :, 4] > max_cost) | (dist2 > max_dist * max_dist)
    lengths = np.where(stop.any(axis=0), stop.argmax(axis=0), max_steps)
    assert stats.points == len(data) == lengths.sum()
    np.testing.assert_array_equal(np.unique(data.simulation), sims[lengths > 0])
    row = np.searchsorted(sims, data.simulation)
    step = np.rint(data.duration / dt).astype(int)
    np.testing.assert_array_equal(np.bincount(row, minlength=len(sims)), lengths)
    close(data.x0, x0[sims][row])
    close(data.params, p[sims][row])
    close(data.costate, lam[sims][row])
    close(data.x1, traj[step, row, :2])
    close(data.cost, traj[step, row, 4])


# --------------------------------------------------------------------------- optimality


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
        np.testing.assert_allclose(out, ref_rhs(z[None], w)[0], atol=1e-15)


def test_h_star_conserved_along_rk4_trajectories(pendulum):
    rng = np.random.default_rng(3)
    x = rng.uniform(pendulum.state_low, pendulum.state_high, (200, 2))
    p = rng.uniform(pendulum.param_low, pendulum.param_high, (200, 1))
    lam, valid = pendulum.costate_from_params(x, p, 1.0)
    starts = np.flatnonzero(valid)[:50]
    assert len(starts) == 50  # 153 of the 200 draws have a valid costate
    worst = 0.0
    for i in starts:  # every one checked: none is skipped (none diverges in 1 s)
        traj = rollout(pendulum, np.r_[x[i], lam[i], 0.0], 1.0, 0.01, 100)
        assert np.isfinite(traj).all()
        worst = max(worst, np.abs(h_star(traj[:, :2], traj[:, 2:4], 1.0)).max())
    assert worst < 1e-6  # measured 5.4e-7 (median 3.9e-10)


def test_rk4_is_fourth_order(pendulum):
    z0 = np.array([-2.0, 0.5, 0.3, -0.4, 0.0])
    t_end = 1.0
    ref = rollout(pendulum, z0, 1.0, t_end / 4096, 4096)[-1]
    errors = [np.abs(rollout(pendulum, z0, 1.0, t_end / n, n)[-1] - ref).max()
              for n in (16, 32, 64)]
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    for r in ratios:
        assert 13 < r < 19  # 2^4 = 16

"""The planar quadrotor: its transcription of Tedrake's equations, hover, the saturated optimal
control u* = clip(-B^T lambda, 0, f_max), and the public checker.

The reference equations here are written out by hand from the model (quadrotor.py's
docstring) with the parameters as literals, independently of the sympy definition.
"""

from __future__ import annotations

import numpy as np
import pytest
from tests.references import rk4

from rrtcolearn.integrate import rollout
from rrtcolearn.systems import list_systems, make, recommended_config
from rrtcolearn.systems.check import check_system
from rrtcolearn.systems.quadrotor import make_quadrotor

M, R_ARM, INERTIA, G = 0.486, 0.25, 0.00383, 9.81
F_MAX = M * G
HOVER = M * G / 2.0


@pytest.fixture(scope="module")
def quad():
    return make_quadrotor()


def hand_dynamics(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """m x'' = -(f1 + f2) sin(theta), m z'' = (f1 + f2) cos(theta) - m g,
    I theta'' = r (f1 - f2); one state (6,) and input (2,)."""
    _, _, th, dx, dz, dth = x
    f = u[0] + u[1]
    return np.array([dx, dz, dth, -f * np.sin(th) / M, f * np.cos(th) / M - G,
                     R_ARM * (u[0] - u[1]) / INERTIA])


def hand_u_star(x: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """argmin over [0, f_max]^2 of (f1^2 + f2^2) / 2 + lambda^T B f: clip(-B^T lambda)."""
    th = x[2]
    common = (-np.sin(th) * lam[3] + np.cos(th) * lam[4]) / M
    turn = R_ARM * lam[5] / INERTIA
    return np.clip(-np.array([common + turn, common - turn]), 0.0, F_MAX)


def hand_rhs(z: np.ndarray, w: float) -> np.ndarray:
    """(x', lambda', cost') under u*: lambda' = -dH/dx at u* (envelope theorem), by hand."""
    x, lam = z[:6], z[6:12]
    u = hand_u_star(x, lam)
    th, f = x[2], u[0] + u[1]
    lam_dot = np.array([0.0, 0.0, f * (lam[3] * np.cos(th) + lam[4] * np.sin(th)) / M,
                        -lam[0], -lam[1], -lam[2]])
    return np.concatenate([hand_dynamics(x, u), lam_dot, [w + 0.5 * u @ u]])


# --------------------------------------------------------------------------- definition


def test_limits_box_and_defaults(quad):
    low, high = quad.input_limits()
    np.testing.assert_allclose(low, [0.0, 0.0], rtol=0, atol=0)
    np.testing.assert_allclose(high, [F_MAX, F_MAX], rtol=1e-15)
    assert quad.input_limited
    assert quad.n_states == 6 and quad.n_inputs == 2
    assert quad.angle_dims == (2,)
    assert quad.state_names == ("x", "z", "theta", "x_dot", "z_dot", "theta_dot")
    # theta's range is one full turn (angles are wrapped into it)
    assert quad.state_high[2] - quad.state_low[2] == pytest.approx(2 * np.pi)
    # the default query: level and at rest, both inside the box
    for key in ("start", "goal"):
        x = np.array(quad.defaults[key])
        assert np.all((quad.state_low <= x) & (x <= quad.state_high))
        assert np.all(x[2:] == 0.0)
    # the climbing query of the docstring fits too, with room for overshoot
    assert quad.state_low[1] <= -1.0 and quad.state_high[1] >= 2.0


def test_hover_is_an_equilibrium_at_half_thrust(quad):
    assert HOVER == pytest.approx(F_MAX / 2)
    rng = np.random.default_rng(0)
    x = rng.uniform(quad.state_low, quad.state_high, (50, 6))
    x[:, 2:] = 0.0  # level and at rest, anywhere in the box
    x = np.vstack([x, quad.defaults["start"], quad.defaults["goal"]])
    acc = quad.dynamics(x, np.full((len(x), 2), HOVER))
    np.testing.assert_allclose(acc, 0.0, rtol=0, atol=1e-12)
    # and the limits bracket it: full thrust climbs at g, no thrust falls at g
    for f, z_acc in ((F_MAX, G), (0.0, -G)):
        acc = quad.dynamics(x[:1], np.full((1, 2), f))[0]
        np.testing.assert_allclose(acc, [0, 0, 0, 0, z_acc, 0], rtol=0, atol=1e-12)


def test_dynamics_match_the_hand_equations(quad):
    rng = np.random.default_rng(1)
    x = rng.uniform(quad.state_low, quad.state_high, (200, 6))
    u = rng.uniform(0.0, F_MAX, (200, 2))
    expected = np.array([hand_dynamics(xi, ui) for xi, ui in zip(x, u, strict=True)])
    np.testing.assert_allclose(quad.dynamics(x, u), expected, rtol=1e-12, atol=1e-12)


def test_rk4_of_system_dynamics_matches_hand_integration(quad):
    dt, steps = 0.01, 20
    # a differential thrust spins the body up while it climbs and drifts sideways
    x0 = np.array([-1.0, 0.0, 0.1, 0.5, -0.2, 1.0])
    u = np.array([3.0, 2.0])
    ours = rk4(lambda x: quad.dynamics(x[None], u[None])[0], x0, dt, steps)
    hand = rk4(lambda x: hand_dynamics(x, u), x0, dt, steps)
    np.testing.assert_allclose(ours, hand, rtol=1e-12, atol=1e-12)
    # theta'' is constant, so RK4 is exact there: theta = theta0 + theta'0 t + a t^2 / 2
    t = dt * np.arange(steps + 1)
    alpha = R_ARM * (u[0] - u[1]) / INERTIA
    np.testing.assert_allclose(ours[:, 2], x0[2] + x0[5] * t + alpha * t**2 / 2, atol=1e-12)
    # level equal thrusts: a vertical parabola, exact too
    x0 = np.array([0.0, 0.0, 0.0, 0.0, 0.3, 0.0])
    u = np.array([4.0, 4.0])
    ours = rk4(lambda x: quad.dynamics(x[None], u[None])[0], x0, dt, steps)
    z_acc = 8.0 / M - G
    np.testing.assert_allclose(ours[:, 1], 0.3 * t + z_acc * t**2 / 2, atol=1e-12)
    np.testing.assert_allclose(ours[:, [0, 2, 3, 5]], 0.0, atol=1e-15)


def test_optimal_control_is_the_clipped_minimiser(quad):
    rng = np.random.default_rng(2)
    x = rng.uniform(quad.state_low, quad.state_high, (500, 6))
    lam = rng.normal(size=(500, 6)) * rng.choice([0.1, 1.0, 10.0], size=(500, 1))
    u = quad.optimal_control(x, lam)
    assert u.shape == (500, 2)
    assert np.all((u >= 0.0) & (u <= F_MAX))
    # both limits are active somewhere, and the interior too
    assert (u == 0.0).any() and (u == F_MAX).any() and ((u > 0) & (u < F_MAX)).any()
    expected = np.array([hand_u_star(xi, li) for xi, li in zip(x, lam, strict=True)])
    np.testing.assert_allclose(u, expected, rtol=1e-12, atol=1e-12)
    # no input in the box has a lower Hamiltonian (grid of 41 x 41 thrust pairs)
    grid = np.linspace(0.0, F_MAX, 41)
    pairs = np.array(np.meshgrid(grid, grid)).reshape(2, -1).T
    for i in range(0, 500, 50):
        xs, ls = np.repeat(x[i : i + 1], len(pairs), 0), np.repeat(lam[i : i + 1], len(pairs), 0)
        h_grid = quad.hamiltonian(xs, ls, pairs, 1.0)
        h_star = quad.hamiltonian(x[i : i + 1], lam[i : i + 1], u[i : i + 1], 1.0)[0]
        assert h_star <= h_grid.min() + 1e-12 * (1 + abs(h_star))


def test_extremals_match_the_hand_costate_equations(quad):
    """rollout_jit (state, costate and cost under the saturated u*) against RK4 of the
    hand-written Pontryagin equations, from costates on H* = 0 at the default start."""
    w, dt, steps = 1.0, 0.01, 50
    rng = np.random.default_rng(3)
    x0 = np.tile(np.array(quad.defaults["start"]), (8, 1))
    lam0, valid = quad.costate_from_params(x0, rng.uniform(-1, 1, (8, 6)), w)
    assert valid.all()
    saturated = False
    for xi, li in zip(x0, lam0, strict=True):
        z0 = np.concatenate([xi, li, [0.0]])
        ours = rollout(quad, z0, w, dt, steps)
        hand = rk4(lambda z: hand_rhs(z, w), z0, dt, steps)
        scale = 1.0 + np.abs(hand).max(axis=0)
        np.testing.assert_allclose(ours / scale, hand / scale, rtol=0, atol=1e-9)
        u = quad.optimal_control(ours[:, :6], ours[:, 6:12])
        saturated |= bool(((u == 0.0) | (u == F_MAX)).any())
    assert saturated  # the clipped law was exercised


# --------------------------------------------------------------------------- check_system


def test_passes_check_system(quad):
    """The public checker, with its input-box conditions (u* in the box and minimising H
    over it, the KKT signs where it saturates, H* conserved across the switches)."""
    check_system(quad, n_samples=100)
    check_system(quad, n_samples=100, seed=1, time_weight=0.3)


def test_registered_without_a_recommended_config(quad):
    assert "quadrotor" in list_systems()
    assert recommended_config("quadrotor") == {}
    made = make("quadrotor")
    assert made.name == "quadrotor" and made.source == quad.source

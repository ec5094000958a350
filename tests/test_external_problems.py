"""The transcriptions of sparse_rrt's acrobot and cart-pole (examples/sparse_rrt_*.py) against
the equations of sparse_rrt's cart_pole.cpp and two_link_acrobot.cpp (described in
docs/external_problems.md), written out again here in numpy with the constants as literals,
independently of the sympy definitions.

Checks: equilibria, the input-affine split (a(x) + B(x) u equal to the written equations at
random states and inputs, for the generated kernels and for the sympy expressions), a few
integration steps, the energy balance (the cart-pole conserves energy with F = 0; the
acrobot's energy changes at exactly theta2' tau - 0.1 (theta1'^2 + theta2'^2), so it never
grows with tau = 0), the acrobot's goal ball inside sparse_rrt's task-space region, the
module:attribute loading `rrtcolearn run --system` uses, and `check_system`.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest
import sympy

from rrtcolearn.systems import make
from rrtcolearn.systems.check import check_system

ROOT = Path(__file__).parents[1]


@pytest.fixture(scope="module")
def cp_mod():
    sys.path.insert(0, str(ROOT))
    try:
        return importlib.import_module("examples.sparse_rrt_cartpole")
    finally:
        sys.path.remove(str(ROOT))


@pytest.fixture(scope="module")
def ac_mod():
    sys.path.insert(0, str(ROOT))
    try:
        return importlib.import_module("examples.sparse_rrt_acrobot")
    finally:
        sys.path.remove(str(ROOT))


@pytest.fixture(scope="module")
def cartpole(cp_mod):
    return cp_mod.make_cartpole()


@pytest.fixture(scope="module")
def acrobot(ac_mod):
    return ac_mod.make_acrobot()


# ----------------------------------------------------------------- sparse_rrt's equations by hand

def cartpole_ref(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    """sparse_rrt's cart_pole, states (N, 4) = (x, v, theta, w), force (N,)."""
    inertia, ell, big_m, m, g = 10.0, 2.5, 10.0, 5.0, 9.8
    _, v, th, w = x.T
    d = (big_m + m) * (inertia + m * ell**2) - m**2 * ell**2 * np.cos(th) ** 2
    vdot = ((inertia + m * ell**2) * (f + m * ell * w**2 * np.sin(th))
            + m**2 * ell**2 * np.cos(th) * np.sin(th) * g) / d
    wdot = (-m * ell * np.cos(th) * (f + m * ell * w**2 * np.sin(th))
            + (big_m + m) * (-m * g * ell * np.sin(th))) / d
    return np.stack([v, vdot, w, wdot], axis=1)


def cartpole_energy(x: np.ndarray) -> np.ndarray:
    """Kinetic energy with mass matrix [[M + m, m L cos], [m L cos, I + m L^2]] plus
    V = -m g L cos(theta) (the Lagrangian of sparse_rrt's equations)."""
    inertia, ell, big_m, m, g = 10.0, 2.5, 10.0, 5.0, 9.8
    _, v, th, w = x.T
    kin = 0.5 * ((big_m + m) * v**2 + 2 * m * ell * np.cos(th) * v * w
                 + (inertia + m * ell**2) * w**2)
    return kin - m * g * ell * np.cos(th)


def acrobot_ref(x: np.ndarray, tau: np.ndarray, damping: float = 0.1) -> np.ndarray:
    """sparse_rrt's two_link_acrobot, states (N, 4) = (theta1, theta2, theta1', theta2')."""
    m, ell, lc, lc2, l2, i1, i2, g = 1.0, 1.0, 0.5, 0.25, 1.0, 0.2, 1.0, 9.8
    th1, th2, dth1, dth2 = x.T
    t1, t2 = th1 - np.pi / 2, th2
    d11 = m * lc2 + m * (l2 + lc2 + 2 * ell * lc * np.cos(t2)) + i1 + i2
    d22 = m * lc2 + i2
    d12 = d21 = m * (lc2 + ell * lc * np.cos(t2)) + i2
    c1 = -m * ell * lc * dth2**2 * np.sin(t2) - 2 * m * ell * lc * dth1 * dth2 * np.sin(t2)
    c2 = m * ell * lc * dth1**2 * np.sin(t2)
    g1 = (m * lc + m * ell) * g * np.cos(t1) + m * lc * g * np.cos(t1 + t2)
    g2 = m * lc * g * np.cos(t1 + t2)
    u1 = -damping * dth1
    u2 = tau - damping * dth2
    det = d11 * d22 - d12 * d21
    a1 = (d22 * (u1 - c1 - g1) - d12 * (u2 - c2 - g2)) / det
    a2 = (d11 * (u2 - c2 - g2) - d21 * (u1 - c1 - g1)) / det
    return np.stack([dth1, dth2, a1, a2], axis=1)


def acrobot_energy(x: np.ndarray) -> np.ndarray:
    """q'^T D q' / 2 + V with D = [[d11, d12], [d12, d22]] and V whose gradient is (g1, g2)."""
    th1, th2, dth1, dth2 = x.T
    t1, t2 = th1 - np.pi / 2, th2
    d11, d22, d12 = 2.7 + np.cos(t2), 1.25, 1.25 + 0.5 * np.cos(t2)
    kin = 0.5 * (d11 * dth1**2 + 2 * d12 * dth1 * dth2 + d22 * dth2**2)
    return kin + 1.5 * 9.8 * np.sin(t1) + 0.5 * 9.8 * np.sin(t1 + t2)


def random_states(system, rng, n=400):
    return rng.uniform(system.state_low, system.state_high, size=(n, system.n_states))


def rk4(f, x, dt, steps):
    out = [x]
    for _ in range(steps):
        k1 = f(x)
        k2 = f(x + 0.5 * dt * k1)
        k3 = f(x + 0.5 * dt * k2)
        k4 = f(x + dt * k3)
        x = x + dt * (k1 + 2 * k2 + 2 * k3 + k4) / 6
        out.append(x)
    return np.array(out)


# --------------------------------------------------------------------------- definitions

def test_metadata(cartpole, acrobot, cp_mod, ac_mod):
    assert cartpole.state_names == ("x", "v", "theta", "w")
    assert cartpole.angle_dims == (2,)
    np.testing.assert_allclose(cartpole.state_low, [-30, -40, 0, -2])
    np.testing.assert_allclose(cartpole.state_high, [30, 40, 2 * np.pi, 2])
    np.testing.assert_allclose(cartpole.input_limits(), [[-300], [300]])
    assert cartpole.defaults == {"start": [-20.0, 0.0, 3.14, 0.0], "goal": [20.0, 0.0, 3.14, 0.0],
                                 "config": {"plan": {"goal_tolerance": 1.5, "time_limit": 60.0}}}
    assert acrobot.angle_dims == (0, 1)
    np.testing.assert_allclose(acrobot.state_low, [-np.pi, -np.pi, -6, -6])
    np.testing.assert_allclose(acrobot.state_high, [np.pi, np.pi, 6, 6])
    np.testing.assert_allclose(acrobot.input_limits(), [[-4], [4]])
    d = acrobot.defaults
    assert d["start"] == [0.0, 0.0, 0.0, 0.0] and d["goal"] == [3.14, 0.0, 0.0, 0.0]
    assert d["config"] == {"plan": {"goal_tolerance": 2.0, "time_limit": 60.0}}
    # the goal region: sparse_rrt's task-space test, velocities free
    rng = np.random.default_rng(1)
    draws = np.array([d["goal_sampler"](rng) for _ in range(200)])
    assert ac_mod.in_task_goal(draws).all() and np.ptp(draws[:, 2]) > 6
    assert d["goal_fn"](np.array([d["goal"]]))[0] == 0.0
    assert d["goal_fn"](np.array([d["start"]]))[0] > 2.0
    for system in (cartpole, acrobot):  # R = identity
        assert system.derivation.input_weight == sympy.eye(1)
    wide = cp_mod.make_cartpole_wide()
    np.testing.assert_allclose(wide.state_high, [30, 60, 2 * np.pi, 3])
    wide = ac_mod.make_acrobot_wide()
    np.testing.assert_allclose(wide.state_high, [np.pi, np.pi, 9, 9])


@pytest.mark.parametrize("theta", [0.0, np.pi, 2 * np.pi])
def test_cartpole_equilibria(cartpole, theta):
    x = np.array([[-20.0, 0.0, theta, 0.0], [7.0, 0.0, theta, 0.0]])
    np.testing.assert_allclose(cartpole.dynamics(x, np.zeros((2, 1))), 0.0, atol=1e-12)


def test_cartpole_upright_is_unstable_hanging_is_stable(cartpole):
    # a small tilt from theta = pi accelerates away from pi, one from 0 back towards 0
    eps = 1e-3
    acc = cartpole.dynamics(np.array([[0, 0, np.pi + eps, 0], [0, 0, eps, 0]]),
                            np.zeros((2, 1)))[:, 3]
    assert acc[0] > 0 and acc[1] < 0


@pytest.mark.parametrize("q", [(0.0, 0.0), (np.pi, 0.0), (-np.pi, 0.0), (0.0, np.pi),
                               (np.pi, np.pi)])
def test_acrobot_equilibria(acrobot, q):
    x = np.array([[q[0], q[1], 0.0, 0.0]])
    np.testing.assert_allclose(acrobot.dynamics(x, np.zeros((1, 1))), 0.0, atol=1e-12)


def test_query_states_are_nearly_equilibria(cartpole, acrobot):
    # 3.14 is not pi: the queries' states drift slowly, as in sparse_rrt
    for system in (cartpole, acrobot):
        for key in ("start", "goal"):
            xdot = system.dynamics(np.array([system.defaults[key]]), np.zeros((1, 1)))
            assert np.abs(xdot).max() < 0.02


@pytest.mark.parametrize("which", ["cartpole", "acrobot"])
def test_dynamics_match_external_equations(which, cartpole, acrobot):
    system, ref, lim = ((cartpole, cartpole_ref, 300.0) if which == "cartpole"
                        else (acrobot, acrobot_ref, 4.0))
    rng = np.random.default_rng(3)
    x = random_states(system, rng)
    # beyond the box too: the equations hold everywhere
    x_far = x * rng.uniform(0.5, 2.0, size=x.shape)
    for states in (x, x_far):
        for u in (np.zeros(len(states)), rng.uniform(-lim, lim, len(states)),
                  rng.uniform(-3 * lim, 3 * lim, len(states))):
            got = system.dynamics(states, u[:, None])
            want = ref(states, u)
            assert np.all(np.abs(got - want) <= 1e-12 * (1 + np.abs(want)))


@pytest.mark.parametrize("which", ["cartpole", "acrobot"])
def test_sympy_split_matches_external_equations(which, cp_mod, ac_mod):
    """a(x) and B(x) as written in the example (before code generation) vs the numpy
    reference: a = f(x, 0), B = f(x, 1) - f(x, 0)."""
    mod, ref, params = ((cp_mod, cartpole_ref, cp_mod.PARAMETERS) if which == "cartpole"
                        else (ac_mod, acrobot_ref, ac_mod.PARAMETERS))
    eqs = mod.cartpole_equations() if which == "cartpole" else mod.acrobot_equations()
    states, _, drift, input_matrix, symbols = eqs
    subs = {symbols[k]: v for k, v in params.items()}
    a = sympy.lambdify(states, sympy.Matrix(drift).xreplace(subs), "numpy")
    b = sympy.lambdify(states, sympy.Matrix(input_matrix).xreplace(subs), "numpy")
    rng = np.random.default_rng(4)
    x = rng.uniform(-7, 7, size=(50, 4))
    for xi in x:
        a_val = np.array(a(*xi), dtype=float).ravel()
        b_val = np.array(b(*xi), dtype=float).ravel()
        f0 = ref(xi[None], np.zeros(1))[0]
        f1 = ref(xi[None], np.ones(1))[0]
        np.testing.assert_allclose(a_val, f0, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b_val, f1 - f0, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("which", ["cartpole", "acrobot"])
def test_integration_steps_match_hand_integration(which, cartpole, acrobot):
    """50 steps of 0.02 s (sparse_rrt's step) under a constant input: RK4 of the generated
    dynamics against RK4 of the reference; explicit Euler (sparse_rrt's integrator) tends to
    the same end state at first order."""
    system, ref, u0 = ((cartpole, cartpole_ref, 120.0) if which == "cartpole"
                       else (acrobot, acrobot_ref, 2.5))
    x0 = np.array([[-20.0, 1.0, 3.0, 0.5]] if which == "cartpole" else [[0.3, -0.2, 1.0, -1.0]])
    u = np.full(1, u0)
    ours = rk4(lambda x: system.dynamics(x, u[:, None]), x0, 0.02, 50)
    theirs = rk4(lambda x: ref(x, u), x0, 0.02, 50)
    np.testing.assert_allclose(ours, theirs, rtol=1e-10, atol=1e-10)

    def euler_gap(dt):
        x = x0
        for _ in range(round(1.0 / dt)):
            x = x + dt * ref(x, u)
        return np.abs(x - theirs[-1]).max()

    # sparse_rrt's explicit Euler converges to the same solution at first order
    ratio = euler_gap(0.01) / euler_gap(0.02)
    assert 0.4 < ratio < 0.6, ratio


def test_cartpole_energy_balance(cartpole):
    """dE/dt = F v exactly (a conservative mechanical system driven by the cart force)."""
    rng = np.random.default_rng(5)
    x = random_states(cartpole, rng)
    f = rng.uniform(-300, 300, len(x))
    h = 1e-6
    for force in (np.zeros(len(x)), f):
        xdot = cartpole.dynamics(x, force[:, None])
        rate = (cartpole_energy(x + h * xdot) - cartpole_energy(x - h * xdot)) / (2 * h)
        scale = 1 + np.abs(cartpole_energy(x))
        np.testing.assert_allclose(rate, force * x[:, 1], atol=1e-6 * scale.max())
    # and along a long unforced RK4 trajectory
    traj = rk4(lambda z: cartpole.dynamics(z, np.zeros((len(z), 1))),
               np.array([[-20.0, 3.0, 2.0, 1.5]]), 0.01, 1000)[:, 0]
    e = cartpole_energy(traj)
    assert np.abs(e - e[0]).max() < 1e-6 * np.abs(e[0])


def test_acrobot_energy_balance(acrobot):
    """dE/dt = theta2' tau - 0.1 (theta1'^2 + theta2'^2): conserved without the damping terms,
    dissipated (never gained) with them at tau = 0."""
    rng = np.random.default_rng(6)
    x = random_states(acrobot, rng)
    tau = rng.uniform(-4, 4, len(x))
    h = 1e-6
    for t in (np.zeros(len(x)), tau):
        xdot = acrobot.dynamics(x, t[:, None])
        rate = (acrobot_energy(x + h * xdot) - acrobot_energy(x - h * xdot)) / (2 * h)
        power = x[:, 3] * t - 0.1 * (x[:, 2] ** 2 + x[:, 3] ** 2)
        np.testing.assert_allclose(rate, power, atol=1e-6)
        if not t.any():
            assert (rate <= 1e-9).all()
    # undamped reference (the example's equations without the -0.1 theta' terms): conserved
    traj = rk4(lambda z: acrobot_ref(z, np.zeros(len(z)), damping=0.0),
               np.array([[0.5, -1.0, 2.0, -3.0]]), 0.005, 2000)[:, 0]
    e = acrobot_energy(traj)
    assert np.abs(e - e[0]).max() < 1e-6 * (1 + np.abs(e[0]))
    # damped (the system as built): energy never grows along an unforced trajectory
    traj = rk4(lambda z: acrobot.dynamics(z, np.zeros((len(z), 1))),
               np.array([[0.5, -1.0, 2.0, -3.0]]), 0.005, 2000)[:, 0]
    e = acrobot_energy(traj)
    assert (np.diff(e) <= 1e-9).all() and e[-1] < e[0] - 1.0


def test_acrobot_goal_ball_inside_task_space_goal(ac_mod):
    """Every state within GOAL_RADIUS of the goal (angles wrapped, any velocities within the
    ball) satisfies sparse_rrt's end-effector test; a slightly larger ball does not."""
    rng = np.random.default_rng(7)
    goal = np.array(ac_mod.GOAL)
    d = rng.normal(size=(20000, 4))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = ac_mod.GOAL_RADIUS
    assert ac_mod.in_task_goal(goal + r * d).all()
    assert ac_mod.in_task_goal(goal + r * d + [2 * np.pi, -2 * np.pi, 0, 0]).all()
    worst = np.array([2.0, 1.0, 0.0, 0.0]) / np.sqrt(5.0)  # along the end effector's motion
    assert not ac_mod.in_task_goal(goal + 1.01 * r * worst).all()
    # sparse_rrt's region does not constrain velocities: far larger than the ball
    assert ac_mod.in_task_goal(goal + np.array([0.0, 0.0, 5.0, -5.0])).all()


def test_module_attribute_loading(monkeypatch):
    """`rrtcolearn run --system examples.sparse_rrt_cartpole:make_cartpole` from the
    repository root (the CLI puts the current directory on the path)."""
    monkeypatch.chdir(ROOT)
    for spec, name in (("examples.sparse_rrt_cartpole:make_cartpole", "sparse_rrt_cartpole"),
                       ("examples.sparse_rrt_acrobot:make_acrobot", "sparse_rrt_acrobot")):
        assert make(spec).name == name


@pytest.mark.parametrize("which", ["cartpole", "acrobot"])
def test_check_system(which, cartpole, acrobot):
    check_system(cartpole if which == "cartpole" else acrobot)

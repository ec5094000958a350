"""The shipped systems against their sources, transcribed by hand in `tests/references.py`
(Tedrake's *Underactuated Robotics* ch. 3 for the cart-pole, acrobot and planar quadrotor,
the paper for the pendulum): the plain dynamics, the compiled RK4 the planner steps with,
and the compiled state+costate equations of the data generation, at random states and
inputs. `check_system` compares a system's generated functions with each other, so a wrong
mass or sign passes it; these fail. The examples' sparse_rrt systems likewise, against
sparse_rrt's C++ (`update_derivative`), their input limits included."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
from tests import references as ref

from rrtcolearn.integrate import propagate
from rrtcolearn.systems import make

# name -> (reference dynamics, input range to draw from, the energy and the input's power
# where the reference has them)
SYSTEMS = {
    "cartpole": (ref.cartpole, (-40.0, 40.0), ref.cartpole_energy, ref.cartpole_power),
    "acrobot": (ref.acrobot, (-20.0, 20.0), ref.acrobot_energy, ref.acrobot_power),
    "quadrotor": (ref.quadrotor, (0.0, 4.768), None, None),
    "pendulum": (ref.pendulum, (-3.0, 3.0), None, None),
    "examples.sparse_rrt_cartpole:make_cartpole": (ref.sparse_rrt_cartpole, (-300.0, 300.0),
                                                   None, None),
    "examples.sparse_rrt_acrobot:make_acrobot": (ref.sparse_rrt_acrobot, (-4.0, 4.0), None,
                                                 None),
}


def _samples(system, rng, n: int, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """States over the system's box widened by half on each side, inputs over [lo, hi]."""
    low, high = system.state_low, system.state_high
    pad = 0.5 * (high - low)
    x = rng.uniform(low - pad, high + pad, size=(n, system.n_states))
    u = rng.uniform(lo, hi, size=(n, system.n_inputs))
    return x, u


@pytest.fixture(scope="module", params=sorted(SYSTEMS))
def shipped(request):
    name = request.param
    if ":" in name:  # an example, built as a user would
        module, factory = name.split(":")
        return name, getattr(importlib.import_module(module), factory)()
    return name, make(name)


def test_dynamics_are_the_textbooks(shipped):
    name, system = shipped
    f_ref, (lo, hi), _, _ = SYSTEMS[name]
    x, u = _samples(system, np.random.default_rng(0), 200, lo, hi)
    want = f_ref(x, u)
    np.testing.assert_allclose(system.dynamics(x, u), want, rtol=1e-10,
                               atol=1e-10 * np.abs(want).max())


def test_the_compiled_rk4_is_a_plain_rk4_of_the_textbooks(shipped):
    """`integrate.propagate` (the planner's, the LQR's and the re-simulation's step) against
    a plain RK4 of the reference, 20 steps of 0.01 s under a held input."""
    name, system = shipped
    f_ref, (lo, hi), _, _ = SYSTEMS[name]
    rng = np.random.default_rng(1)
    x, u = _samples(system, rng, 12, lo, hi)
    x[:, system.bounded_dims] = rng.uniform(system.state_low, system.state_high,
                                            size=x.shape)[:, system.bounded_dims]
    for x0, u0 in zip(x, u, strict=True):
        want = ref.hold(f_ref, x0, u0, 0.01, 20)
        got = propagate(system, x0, u0, 0.01, 20)
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * np.abs(want).max())


def test_the_state_costate_equations_are_pontryagins_on_the_textbooks(shipped):
    """The compiled rhs(z = (x, lambda, cost)) of the data generation against Pontryagin's
    equations built on the reference dynamics: u* = -R^-1 B' lambda (clipped into the input
    box where the system has one), lambda' = -(df/dx)' lambda, cost' = w + u*'Ru*/2, with
    R the identity the systems declare."""
    name, system = shipped
    f_ref, _, _, _ = SYSTEMS[name]
    n, m = system.n_states, system.n_inputs
    low, high = system.input_limits()
    rng = np.random.default_rng(2)
    for w in (0.5, 2.0):
        rhs_ref = ref.state_costate_rhs(f_ref, m, w, low=low, high=high)
        for _ in range(15):
            x = rng.uniform(system.state_low, system.state_high)
            lam = rng.normal(0.0, 3.0, n)
            z = np.concatenate([x, lam, [0.0]])
            want = rhs_ref(z)
            got = np.empty(2 * n + 1)
            system.rhs(z, w, got)
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("name", ["cartpole", "acrobot"])
def test_the_power_balance_of_the_mechanics(name):
    """A second derivation, from the geometry alone: along the shipped dynamics the energy
    of the masses (`references.cartpole_energy`, `acrobot_energy`) changes at the rate the
    input puts work in, dE/dt = grad E . f(x, u) = f p' (the cart) or u theta2' (the
    elbow). A wrong mass, length or sign breaks the balance."""
    system = make(name)
    _, (lo, hi), energy, power = SYSTEMS[name]
    x, u = _samples(system, np.random.default_rng(3), 100, lo, hi)
    f = system.dynamics(x, u)
    rate = np.array([ref.complex_step_jacobian(lambda y: energy(y[None])[0], xi) @ fi
                     for xi, fi in zip(x, f, strict=True)])
    want = power(x, u)
    np.testing.assert_allclose(rate, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


def test_the_power_balance_holds_for_the_references_themselves():
    """The two derivations in `references` agree with each other (the check above is no
    stronger than they are)."""
    rng = np.random.default_rng(4)
    for f_ref, energy, power in ((ref.cartpole, ref.cartpole_energy, ref.cartpole_power),
                                 (ref.acrobot, ref.acrobot_energy, ref.acrobot_power)):
        x = rng.uniform(-4.0, 4.0, size=(50, 4))
        u = rng.uniform(-10.0, 10.0, size=(50, 1))
        f = f_ref(x, u)
        rate = np.array([ref.complex_step_jacobian(lambda y, e=energy: e(y[None])[0], xi) @ fi
                         for xi, fi in zip(x, f, strict=True)])
        np.testing.assert_allclose(rate, power(x, u), rtol=1e-10, atol=1e-9)


def test_the_upright_and_hover_equilibria_are_where_the_sources_put_them():
    """The sources' conventions, one point each: the cart-pole's and the acrobot's upright
    (theta = pi, theta1 = pi) are equilibria at zero input and hanging is stable (a small
    tilt accelerates back); the quadrotor hovers at f1 = f2 = m g / 2; the pendulum's
    upright is theta = 0."""
    cart, acro, quad, pend = (make(k) for k in ("cartpole", "acrobot", "quadrotor",
                                                 "pendulum"))
    np.testing.assert_allclose(cart.dynamics(np.array([[0.3, np.pi, 0, 0]]), np.zeros((1, 1))),
                               0.0, atol=1e-12)
    assert cart.dynamics(np.array([[0, 0.1, 0, 0]]), np.zeros((1, 1)))[0, 3] < 0
    np.testing.assert_allclose(acro.dynamics(np.array([[np.pi, 0, 0, 0]]), np.zeros((1, 1))),
                               0.0, atol=1e-12)
    assert acro.dynamics(np.array([[0.1, 0, 0, 0]]), np.zeros((1, 1)))[0, 2] < 0
    hover = np.full((1, 2), ref.QUADROTOR["m"] * ref.QUADROTOR["g"] / 2)
    np.testing.assert_allclose(quad.dynamics(np.zeros((1, 6)), hover), 0.0, atol=1e-12)
    np.testing.assert_allclose(pend.dynamics(np.zeros((1, 2)), np.zeros((1, 1))), 0.0)
    assert pend.dynamics(np.array([[0.1, 0.0]]), np.zeros((1, 1)))[0, 1] > 0  # falls away

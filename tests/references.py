"""Independent references for the tests: the shipped systems' equations transcribed by hand
from their sources, a plain RK4, and Pontryagin's state+costate equations built on them.

Nothing here imports rrtcolearn: a wrong constant, sign or term in the package's systems, its
compiled integrators or its re-simulation cannot also be in these. Every function accepts
complex arrays, so derivatives are taken by the complex step (f(x + i h e_j).imag / h: exact
to rounding, no cancellation), not by the package's finite differences.

Sources and conventions
-----------------------
* Cart-pole, acrobot, planar quadrotor: R. Tedrake, *Underactuated Robotics* (MIT course notes),
  chapter 3 "Acrobots, Cart-Poles, and Quadrotors". The cart-pole and the acrobot are written
  in the manipulator form the chapter gives them in, M(q) q'' + C(q, q') q' = tau_g(q) + B u,
  and solved for q'' numerically (the package writes the cart-pole's closed form and solves
  the acrobot's symbolically). Angles as the chapter draws them: the cart-pole's theta and
  the acrobot's theta1 are 0 hanging straight down and grow counter-clockwise, the acrobot's
  theta2 is the elbow angle relative to the first link; the acrobot's inertias I1, I2 are
  about the pivots (the chapter's convention), from the centre-of-mass inertias by parallel
  axes. Parameters: the chapter's examples (Drake's `CartPole`/`AcrobotParams`/
  `quadrotor2d`): cart-pole m_c 10, m_p 1, l 0.5, g 9.81; acrobot (after Spong 1995,
  "The swing up control problem for the Acrobot") m1 = m2 = 1, l1 = 1, lc1 = 0.5, lc2 = 1,
  Ic1 = 0.083, Ic2 = 0.33, g 9.81, no joint damping; quadrotor m 0.486, r 0.25,
  I 0.00383, g 9.81, f1 the rotor on the body's +x side.
* The energies (`cartpole_energy`, `acrobot_energy`) are a second, separate derivation from
  the geometry alone (positions of the masses): along the true dynamics dE/dt is the power
  the input puts in (f p' for the cart, u theta2' at the elbow).
* Pendulum: the paper (Section 2), f = (omega, sin(theta) + u), theta = 0 upright.
* sparse_rrt (Littlefield, Li, Bekris; src/systems/cart_pole.cpp and two_link_acrobot.cpp,
  `update_derivative`): the examples' cart-pole and acrobot, transcribed from the C++.
* dynobench 0.0.4 (github.com/quimortiz/dynobench): its acrobot and planar quadrotor are the
  chapter's (`acrobot`, `quadrotor` above) with the parameters of its models/acrobot_v0.yaml
  and models/quad2d_v0.yaml and g = 9.81 (include/dynobench/acrobot.hpp, planar_rotor.hpp);
  the acrobot's I1, I2 (1/3 m l^2) are about the pivots, so Ic = I - m lc^2; the quadrotor's
  inputs are thrusts in units of the hover thrust m g / 2 (src/planar_rotor.cpp,
  `u_nominal`), its arm l. The 2-D double integrator (src/integrator2_2d.cpp):
  (x, y, vx, vy)' = (vx, vy, ax, ay).
"""

from __future__ import annotations

import numpy as np

G_TEDRAKE = 9.81

CARTPOLE = {"mc": 10.0, "mp": 1.0, "l": 0.5, "g": G_TEDRAKE}
ACROBOT = {"m1": 1.0, "m2": 1.0, "l1": 1.0, "lc1": 0.5, "lc2": 1.0, "Ic1": 0.083,
           "Ic2": 0.33, "g": G_TEDRAKE}
QUADROTOR = {"m": 0.486, "r": 0.25, "I": 0.00383, "g": G_TEDRAKE}


def _solve2(M: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """q'' from M (N, 2, 2) q'' = rhs (N, 2) (works on complex arrays)."""
    return np.linalg.solve(M, rhs[..., None])[..., 0]


def cartpole(x: np.ndarray, u: np.ndarray, p: dict = CARTPOLE) -> np.ndarray:
    """Tedrake ch. 3, the cart-pole in manipulator form; x (N, 4) = (p, theta, p', theta'),
    u (N, 1) the force on the cart. q = (p, theta):
    M = [[mc + mp, mp l cos], [mp l cos, mp l^2]], C = [[0, -mp l theta' sin], [0, 0]],
    tau_g = (0, -mp g l sin), B = (1, 0)."""
    x, u = np.atleast_2d(x), np.atleast_2d(u)
    th, dp, dth = x[:, 1], x[:, 2], x[:, 3]
    mc, mp, ell, g = p["mc"], p["mp"], p["l"], p["g"]
    c, s = np.cos(th), np.sin(th)
    M = np.empty((len(x), 2, 2), dtype=np.result_type(x, u, float))
    M[:, 0, 0], M[:, 0, 1] = mc + mp, mp * ell * c
    M[:, 1, 0], M[:, 1, 1] = mp * ell * c, mp * ell**2
    cq = np.stack([-mp * ell * dth * s * dth, 0 * dth], axis=1)  # C(q, q') q'
    tau = np.stack([u[:, 0] + 0 * th, -mp * g * ell * s], axis=1)  # tau_g + B u
    qdd = _solve2(M, tau - cq)
    return np.stack([dp, dth, qdd[:, 0], qdd[:, 1]], axis=1)


def cartpole_energy(x: np.ndarray, p: dict = CARTPOLE) -> np.ndarray:
    """Cart at (p, 0), point mass at (p + l sin theta, -l cos theta): kinetic + potential."""
    x = np.atleast_2d(x)
    th, dp, dth = x[:, 1], x[:, 2], x[:, 3]
    vx = dp + p["l"] * np.cos(th) * dth
    vy = p["l"] * np.sin(th) * dth
    return 0.5 * p["mc"] * dp**2 + 0.5 * p["mp"] * (vx**2 + vy**2) \
        - p["mp"] * p["g"] * p["l"] * np.cos(th)


def cartpole_power(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The input's power: the force times the cart's velocity."""
    return np.atleast_2d(u)[:, 0] * np.atleast_2d(x)[:, 2]


def acrobot(x: np.ndarray, u: np.ndarray, p: dict = ACROBOT) -> np.ndarray:
    """Tedrake ch. 3 (Spong 1995), the acrobot's manipulator equations; x (N, 4) =
    (theta1, theta2, theta1', theta2'), u (N, 1) the elbow torque, B = (0, 1)."""
    x, u = np.atleast_2d(x), np.atleast_2d(u)
    q1, q2, dq1, dq2 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    m1, m2, l1, lc1, lc2, g = (p[k] for k in ("m1", "m2", "l1", "lc1", "lc2", "g"))
    I1 = p["Ic1"] + m1 * lc1**2  # about the pivots
    I2 = p["Ic2"] + m2 * lc2**2
    c2, s1, s2, s12 = np.cos(q2), np.sin(q1), np.sin(q2), np.sin(q1 + q2)
    M = np.empty((len(x), 2, 2), dtype=np.result_type(x, u, float))
    M[:, 0, 0] = I1 + I2 + m2 * l1**2 + 2 * m2 * l1 * lc2 * c2
    M[:, 0, 1] = M[:, 1, 0] = I2 + m2 * l1 * lc2 * c2
    M[:, 1, 1] = I2 + 0 * c2
    cq = np.stack([-2 * m2 * l1 * lc2 * s2 * dq2 * dq1 - m2 * l1 * lc2 * s2 * dq2 * dq2,
                   m2 * l1 * lc2 * s2 * dq1 * dq1], axis=1)
    tau = np.stack([-m1 * g * lc1 * s1 - m2 * g * (l1 * s1 + lc2 * s12),  # tau_g + B u
                    -m2 * g * lc2 * s12 + u[:, 0]], axis=1)
    qdd = _solve2(M, tau - cq)
    return np.stack([dq1, dq2, qdd[:, 0], qdd[:, 1]], axis=1)


def acrobot_energy(x: np.ndarray, p: dict = ACROBOT) -> np.ndarray:
    """Kinetic + potential energy from the links' geometry: centres of mass at
    lc1 (sin q1, -cos q1) and l1 (sin q1, -cos q1) + lc2 (sin(q1+q2), -cos(q1+q2)), each link
    spinning about its centre of mass with Ic at its absolute angular rate."""
    x = np.atleast_2d(x)
    q1, q2, dq1, dq2 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    a = q1 + q2
    v1x, v1y = p["lc1"] * np.cos(q1) * dq1, p["lc1"] * np.sin(q1) * dq1
    v2x = p["l1"] * np.cos(q1) * dq1 + p["lc2"] * np.cos(a) * (dq1 + dq2)
    v2y = p["l1"] * np.sin(q1) * dq1 + p["lc2"] * np.sin(a) * (dq1 + dq2)
    kinetic = 0.5 * p["m1"] * (v1x**2 + v1y**2) + 0.5 * p["Ic1"] * dq1**2 \
        + 0.5 * p["m2"] * (v2x**2 + v2y**2) + 0.5 * p["Ic2"] * (dq1 + dq2) ** 2
    y1 = -p["lc1"] * np.cos(q1)
    y2 = -p["l1"] * np.cos(q1) - p["lc2"] * np.cos(a)
    return kinetic + p["g"] * (p["m1"] * y1 + p["m2"] * y2)


def acrobot_power(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The elbow torque's power: torque times the elbow's relative rate."""
    return np.atleast_2d(u)[:, 0] * np.atleast_2d(x)[:, 3]


def quadrotor(x: np.ndarray, u: np.ndarray, p: dict = QUADROTOR) -> np.ndarray:
    """Tedrake ch. 3, the planar quadrotor; x (N, 6) = (x, z, theta, x', z', theta'),
    u (N, 2) the thrusts: m x'' = -(f1 + f2) sin, m z'' = (f1 + f2) cos - m g,
    I theta'' = r (f1 - f2)."""
    x, u = np.atleast_2d(x), np.atleast_2d(u)
    th = x[:, 2]
    thrust = u[:, 0] + u[:, 1]
    return np.stack([x[:, 3], x[:, 4], x[:, 5],
                     -thrust * np.sin(th) / p["m"],
                     thrust * np.cos(th) / p["m"] - p["g"],
                     p["r"] * (u[:, 0] - u[:, 1]) / p["I"]], axis=1)


DYNOBENCH_ACROBOT = {"m1": 1.0, "m2": 1.0, "l1": 1.0, "lc1": 0.5, "lc2": 0.5,
                     "Ic1": 0.33333 - 0.25, "Ic2": 0.33333 - 0.25, "g": 9.81}
DYNOBENCH_QUAD2D = {"m": 0.034, "r": 0.1, "I": 1e-4, "g": 9.81}


def dynobench_quad2d(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """dynobench's quad2d_v0: `quadrotor` with thrusts u (m g / 2) per unit input."""
    p = DYNOBENCH_QUAD2D
    return quadrotor(x, np.atleast_2d(u) * p["m"] * p["g"] / 2, p)


def dynobench_acrobot(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """dynobench's acrobot_v0: `acrobot` with its parameters."""
    return acrobot(x, u, DYNOBENCH_ACROBOT)


def double_integrator_2d(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """dynobench's integrator2_2d_v0: positions' rates the velocities, velocities' the inputs."""
    x, u = np.atleast_2d(x), np.atleast_2d(u)
    return np.concatenate([x[:, 2:4], u + 0 * x[:, :2]], axis=1)


def pendulum(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The paper's pendulum, f = (omega, sin(theta) + u), theta = 0 upright."""
    x, u = np.atleast_2d(x), np.atleast_2d(u)
    return np.stack([x[:, 1], np.sin(x[:, 0]) + u[:, 0]], axis=1)


SPARSE_CARTPOLE = {"I": 10.0, "L": 2.5, "M": 10.0, "m": 5.0, "g": 9.8}
SPARSE_ACROBOT = {"m": 1.0, "l": 1.0, "lc": 0.5, "lc2": 0.25, "l2": 1.0, "I1": 0.2,
                  "I2": 1.0, "g": 9.8, "damping": 0.1}


def sparse_rrt_cartpole(x: np.ndarray, u: np.ndarray, p: dict = SPARSE_CARTPOLE) -> np.ndarray:
    """sparse_rrt cart_pole.cpp `update_derivative`; x (N, 4) = (x, v, theta, w), u = F."""
    x, u = np.atleast_2d(x), np.atleast_2d(u)
    v, th, w, F = x[:, 1], x[:, 2], x[:, 3], u[:, 0]
    I_, L, Mc, m, g = p["I"], p["L"], p["M"], p["m"], p["g"]
    det = (Mc + m) * (I_ + m * L * L) - m * m * L * L * np.cos(th) ** 2
    push = F + m * L * w * w * np.sin(th)
    dv = ((I_ + m * L * L) * push + m * m * L * L * np.cos(th) * np.sin(th) * g) / det
    dw = (-m * L * np.cos(th) * push + (Mc + m) * (-m * g * L * np.sin(th))) / det
    return np.stack([v, dv, w, dw], axis=1)


def sparse_rrt_acrobot(x: np.ndarray, u: np.ndarray, p: dict = SPARSE_ACROBOT) -> np.ndarray:
    """sparse_rrt two_link_acrobot.cpp `update_derivative` (its "extra" terms and the 0.1
    joint damping included); x (N, 4) = (theta1, theta2, theta1', theta2'), u = tau."""
    x, u = np.atleast_2d(x), np.atleast_2d(u)
    t1, t2, d1, d2 = x[:, 0] - np.pi / 2, x[:, 1], x[:, 2], x[:, 3]
    m, ell, lc, lc2, l2, I1, I2, g = (p[k] for k in ("m", "l", "lc", "lc2", "l2", "I1", "I2",
                                                   "g"))
    d11 = m * lc2 + m * (l2 + lc2 + 2 * ell * lc * np.cos(t2)) + I1 + I2
    d22 = m * lc2 + I2 + 0 * t2
    d12 = m * (lc2 + ell * lc * np.cos(t2)) + I2
    c1 = -m * ell * lc * d2 * d2 * np.sin(t2) - 2 * m * ell * lc * d1 * d2 * np.sin(t2)
    c2 = m * ell * lc * d1 * d1 * np.sin(t2)
    g1 = (m * lc + m * ell) * g * np.cos(t1) + m * lc * g * np.cos(t1 + t2)
    g2 = m * lc * g * np.cos(t1 + t2)
    u1 = -p["damping"] * d1
    u2 = u[:, 0] - p["damping"] * d2
    det = d11 * d22 - d12 * d12
    dd1 = (d22 * (u1 - c1 - g1) - d12 * (u2 - c2 - g2)) / det
    dd2 = (d11 * (u2 - c2 - g2) - d12 * (u1 - c1 - g1)) / det
    return np.stack([d1, d2, dd1, dd2], axis=1)


# ----------------------------------------------------------------------------- integration


def rk4(f, x0: np.ndarray, dt: float, steps: int) -> np.ndarray:
    """Classical RK4 of x' = f(x) (x (n,) -> (n,)) from x0: all (steps + 1, n) states."""
    x = np.asarray(x0, dtype=float).copy()
    out = [x.copy()]
    for _ in range(steps):
        k1 = f(x)
        k2 = f(x + 0.5 * dt * k1)
        k3 = f(x + 0.5 * dt * k2)
        k4 = f(x + dt * k3)
        x = x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        out.append(x.copy())
    return np.array(out)


def hold(dynamics, x0: np.ndarray, u: np.ndarray, dt: float, steps: int) -> np.ndarray:
    """RK4 of ``dynamics`` ((N, n), (N, m) -> (N, n)) under the input ``u`` held constant."""
    u = np.atleast_2d(np.asarray(u, dtype=float))
    return rk4(lambda x: dynamics(x[None], u)[0], x0, dt, steps)


def complex_step_jacobian(f, x: np.ndarray, h: float = 1e-30) -> np.ndarray:
    """(k, n) Jacobian of f ((n,) -> (k,)) at x by the complex step."""
    x = np.asarray(x, dtype=float)
    cols = []
    for j in range(x.size):
        z = x.astype(complex)
        z[j] += 1j * h
        cols.append(np.asarray(f(z)).imag / h)
    return np.stack(cols, axis=-1)


def input_matrix(dynamics, x: np.ndarray, m: int) -> np.ndarray:
    """(n, m) B(x) = df/du of an input-affine system, by the complex step at u = 0."""
    return complex_step_jacobian(lambda u: dynamics(np.asarray(x)[None], u[None])[0],
                                 np.zeros(m))


def optimal_input(dynamics, x: np.ndarray, lam: np.ndarray, m: int, R: np.ndarray | None = None,
                  low=None, high=None) -> np.ndarray:
    """u* = argmin over the box of u'Ru/2 + lam'B(x)u: -R^-1 B'lam, clipped into [low, high]
    (exact for a diagonal R)."""
    R = np.eye(m) if R is None else np.asarray(R, dtype=float)
    u = -np.linalg.solve(R, input_matrix(dynamics, x, m).T @ lam)
    return np.clip(u, -np.inf if low is None else low, np.inf if high is None else high)


def state_costate_rhs(dynamics, m: int, w: float, R: np.ndarray | None = None, low=None,
                      high=None):
    """z = (x, lambda, cost) -> z' under u*: x' = f(x, u*), lambda' = -(df/dx)' lambda (dH/dx
    at u*: the minimiser's own dependence on x drops out), cost' = w + u*'Ru*/2."""
    R = np.eye(m) if R is None else np.asarray(R, dtype=float)

    def rhs(z: np.ndarray) -> np.ndarray:
        n = (len(z) - 1) // 2
        x, lam = z[:n], z[n : 2 * n]
        u = optimal_input(dynamics, x, lam, m, R, low, high)
        fx = complex_step_jacobian(lambda y: dynamics(y[None], u[None])[0], x)
        return np.concatenate([dynamics(x[None], u[None])[0], -fx.T @ lam,
                               [w + 0.5 * u @ R @ u]])

    return rhs

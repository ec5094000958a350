"""Cart-pole swing-up, x = (p, theta, p', theta'), built through `symbolic`.

Point-mass pole on a cart, as in R. Tedrake, *Underactuated Robotics* (MIT course notes),
chapter "Acrobots, Cart-Poles, and Quadrotors": theta = 0 hanging down, theta = pi upright,
force f on the cart, with the parameters of that chapter's examples: cart mass m_c = 10 kg,
pole mass m_p = 1 kg, pole length l = 0.5 m, g = 9.81 m/s^2. With D = m_c + m_p sin^2(theta):

    p''     = (f + m_p sin(theta) (l theta'^2 + g cos(theta))) / D
    theta'' = (-f cos(theta) - m_p l theta'^2 cos(theta) sin(theta)
               - (m_c + m_p) g sin(theta)) / (l D)

which is input-affine in f. The running cost is w + R f^2 / 2 with R = 1 (identity). It shipped
with R = 0.01 while Alg. 2's cost bound was the paper's 2, which left R = 1 segments too weak
to swing the pole over; the derived cost bound scales with R (4352 here against 43.6 at
R = 0.01), and with R = 1 20 of 20 seeded swing-ups are solved within 60 s
(docs/systems.md). Standard swing-up query: from hanging at the origin (0, 0, 0, 0) to
upright at the cart's origin (0, pi, 0, 0).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import sympy

from rrtcolearn.systems.parameters import with_parameters
from rrtcolearn.systems.symbolic import SymbolicSystem, build_system

POLE_LENGTH = 0.5  # m, as drawn


def geometry(x: np.ndarray) -> list[np.ndarray]:
    """The bodies of states x (K, 4) as polylines (K, P, 2) in metres: the cart and the
    pole (`rrtcolearn.animation`)."""
    p, th = x[:, 0], x[:, 1]
    w, h = 0.4, 0.2
    cart = np.stack([np.stack([p + a, np.full_like(p, b)], axis=1)
                     for a, b in ((-w, -h), (w, -h), (w, h), (-w, h), (-w, -h))], axis=1)
    tip = np.stack([p + POLE_LENGTH * np.sin(th), -POLE_LENGTH * np.cos(th)], axis=1)
    return [cart, np.stack([np.stack([p, 0 * p], axis=1), tip], axis=1)]


def make_cartpole(parameters: Mapping[str, float] | None = None) -> SymbolicSystem:
    """The cart-pole of Tedrake's notes (m_c = 10, m_p = 1, l = 0.5, g = 9.81);
    ``parameters`` replaces some by name (``{"m_c": 11.0}``)."""
    p, th, dp, dth, f = sympy.symbols("p theta dp dtheta f", real=True)
    mc, mp, ell, g = sympy.symbols("m_c m_p l g", positive=True)
    d = mc + mp * sympy.sin(th) ** 2
    drift = [dp, dth,
             mp * sympy.sin(th) * (ell * dth**2 + g * sympy.cos(th)) / d,
             (-mp * ell * dth**2 * sympy.cos(th) * sympy.sin(th)
              - (mc + mp) * g * sympy.sin(th)) / (ell * d)]
    input_matrix = [[0], [0], [1 / d], [-sympy.cos(th) / (ell * d)]]
    return build_system(
        "cartpole", states=[p, th, dp, dth], inputs=[f], drift=drift,
        input_matrix=input_matrix, input_weight=[[1.0]],
        parameters=with_parameters({mc: 10.0, mp: 1.0, ell: POLE_LENGTH, g: 9.81},
                                   parameters),
        state_low=[-2.0, -math.pi / 2, -4.0, -10.0],
        state_high=[2.0, 3 * math.pi / 2, 4.0, 10.0],
        angle_dims=[1], state_names=["p", "theta", "p_dot", "theta_dot"],
        input_names=["force"],
        description="Cart-pole swing-up (Tedrake: m_c 10, m_p 1, l 0.5), theta = 0 down",
        defaults={"start": [0.0, 0.0, 0.0, 0.0], "goal": [0.0, math.pi, 0.0, 0.0],
                  "geometry": "rrtcolearn.systems.cartpole:geometry"},
    )

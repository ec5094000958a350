"""Acrobot swing-up, x = (theta1, theta2, theta1', theta2'), built through `symbolic`.

Two-link arm actuated at the elbow, as in R. Tedrake, *Underactuated Robotics* (MIT course
notes), chapter "Acrobots, Cart-Poles, and Quadrotors" (after Spong 1995): theta1 is the
shoulder angle from hanging down, theta2 the elbow angle relative to the first link; with
the parameters of that chapter: m1 = m2 = 1 kg, l1 = 1 m, l2 = 2 m, lc1 = 0.5 m, lc2 = 1 m,
inertias about the centres of mass Ic1 = 0.083, Ic2 = 0.33 kg m^2 (I1 = Ic1 + m1 lc1^2 and
I2 = Ic2 + m2 lc2^2 about the joints), g = 9.81 m/s^2. The manipulator equations
M(q) q'' + C(q, q') q' = tau_g(q) + B u, B = (0, 1)^T, are solved for q'' symbolically,
which is input-affine in the elbow torque u. Standard swing-up query: from hanging
(0, 0, 0, 0) to upright (pi, 0, 0, 0).

The state box (ours; the notes state none) is theta1' in [-8, 8], theta2' in [-16, 16]
rad/s: upright lies 49 J above hanging, so the rigid arm passes the bottom on its way up at
|theta1'| = sqrt(2 * 49 / 4.66) = 4.6 rad/s (4.66 kg m^2 its inertia about the shoulder);
a box of +-4 and +-8 excluded that swing, and the extremals that end at the upright run
faster still (docs/systems.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import sympy

from rrtcolearn.systems.parameters import with_parameters
from rrtcolearn.systems.symbolic import SymbolicSystem, build_system

LINKS = (1.0, 2.0)  # m, l1 and l2 as drawn


def geometry(x: np.ndarray) -> list[np.ndarray]:
    """The arm of states x (K, 4) as one polyline (K, 3, 2) in metres, shoulder, elbow and
    tip, theta1 = 0 hanging down (`rrtcolearn.animation`)."""
    q1, q12 = x[:, 0], x[:, 0] + x[:, 1]
    elbow = np.stack([LINKS[0] * np.sin(q1), -LINKS[0] * np.cos(q1)], axis=1)
    tip = elbow + np.stack([LINKS[1] * np.sin(q12), -LINKS[1] * np.cos(q12)], axis=1)
    return [np.stack([np.zeros_like(elbow), elbow, tip], axis=1)]


def make_acrobot(parameters: Mapping[str, float] | None = None) -> SymbolicSystem:
    """The acrobot of Tedrake's notes (m 1, 1; l 1, 2; lc 0.5, 1; Ic 0.083, 0.33);
    ``parameters`` replaces some by name (``{"m1": 1.1}``; l2 enters only the drawing)."""
    q1, q2, dq1, dq2, u = sympy.symbols("theta1 theta2 dtheta1 dtheta2 u", real=True)
    m1, m2, l1, lc1, lc2, ic1, ic2, g = sympy.symbols("m1 m2 l1 lc1 lc2 Ic1 Ic2 g",
                                                       positive=True)
    # inertias about the joints, from those about the centres of mass (parallel axes)
    i1, i2 = ic1 + m1 * lc1**2, ic2 + m2 * lc2**2
    c2, s1, s2, s12 = sympy.cos(q2), sympy.sin(q1), sympy.sin(q2), sympy.sin(q1 + q2)
    mass = sympy.Matrix([
        [i1 + i2 + m2 * l1**2 + 2 * m2 * l1 * lc2 * c2, i2 + m2 * l1 * lc2 * c2],
        [i2 + m2 * l1 * lc2 * c2, i2]])
    coriolis = sympy.Matrix([
        [-2 * m2 * l1 * lc2 * s2 * dq2, -m2 * l1 * lc2 * s2 * dq2],
        [m2 * l1 * lc2 * s2 * dq1, 0]])
    gravity = sympy.Matrix([
        -m1 * g * lc1 * s1 - m2 * g * (l1 * s1 + lc2 * s12),
        -m2 * g * lc2 * s12])
    minv = mass.inv()
    accel = minv * (gravity - coriolis * sympy.Matrix([dq1, dq2]))
    b = minv * sympy.Matrix([0, 1])
    return build_system(
        "acrobot", states=[q1, q2, dq1, dq2], inputs=[u],
        drift=[dq1, dq2, accel[0], accel[1]],
        input_matrix=[[0], [0], [b[0]], [b[1]]], input_weight=[[1]],
        parameters=with_parameters({m1: 1.0, m2: 1.0, l1: LINKS[0], lc1: 0.5, lc2: 1.0,
                                    ic1: 0.083, ic2: 0.33, g: 9.81}, parameters),
        state_low=[-math.pi / 2, -math.pi, -8.0, -16.0],
        state_high=[3 * math.pi / 2, math.pi, 8.0, 16.0],
        angle_dims=[0, 1], state_names=["theta1", "theta2", "theta1_dot", "theta2_dot"],
        input_names=["elbow_torque"],
        description="Acrobot swing-up (Tedrake/Spong parameters), theta1 = 0 hanging down",
        defaults={"start": [0.0, 0.0, 0.0, 0.0], "goal": [math.pi, 0.0, 0.0, 0.0],
                  "geometry": "rrtcolearn.systems.acrobot:geometry"},
    )

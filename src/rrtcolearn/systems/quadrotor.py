"""Planar quadrotor, x = (x, z, theta, x', z', theta'), built through `symbolic`.

A rigid body in the vertical plane with two rotors at distance r either side of its centre, as
in R. Tedrake, *Underactuated Robotics* (MIT course notes), chapter "Acrobots, Cart-Poles, and
Quadrotors", section "The Planar Quadrotor": x horizontal, z up, theta the roll angle
(counter-clockwise, 0 level), f1 and f2 the thrusts of the two rotors along the body's
vertical axis, f1 on the body's +x side (f1 > f2 turns it counter-clockwise):

    m x''     = -(f1 + f2) sin(theta)
    m z''     =  (f1 + f2) cos(theta) - m g
    I theta'' =  r (f1 - f2)

which is input-affine in (f1, f2) with a(x) = (x', z', theta', 0, -g, 0). Parameters of the
notes' example (``underactuated/quadrotor2d.py``, after Bouadi, Bouchoucha and Tadjine 2007):
m = 0.486 kg, r = 0.25 m, I = 0.00383 kg m^2, g = 9.81 m/s^2.

Input limits (ours; the notes give none): each rotor pushes, never pulls, up to
f_max = m g = 4.768 N, so f1, f2 in [0, f_max] and hover f1 = f2 = m g / 2 = 2.384 N sits in
the middle of each range: the two rotors together lift at most 2 m g, i.e. the vehicle can
accelerate upwards at g and falls freely at worst. The optimal control saturates
(``build_system(input_low, input_high)``): u* = clip(-B^T lambda, 0, f_max). Running cost
w + (f1^2 + f2^2) / 2 (R = identity, thrusts in newtons; hovering alone costs
(m g)^2 / 4 = 5.7 per second besides the time weight).

State box (ours; the notes state none): x in [-2, 2] m and z in [-1, 2] m leave 1 m around
every end point of the standard queries, hover at (-1, 0) to hover at (1, 0) (the default)
and a climb of 1 m from (0, 0) to (0, 1) (the box also bounds the plans' paths). theta is an
angle, one full turn [-pi, pi) (flips included). x', z' in [-4, 4] m/s and theta' in
[-10, 10] rad/s contain the optimal manoeuvres of those queries with a margin; at w = 1 we
measured them by a direct transcription (piecewise-constant thrusts, SLSQP; not part of the
package): the sideways move takes 1.20 s at cost 10.46, tilts to |theta| = 0.75 rad, peaks
at |x'| = 2.8 m/s and |theta'| = 7.5 rad/s and stays within 4 cm of its height (80
intervals); the climb takes 0.75 s at cost 6.69, its thrust falling linearly from full to
none (saturated at both ends), peaking at z' = 2.0 m/s (40 intervals). The fastest the
vehicle can climb 1 m (bang-bang at +-g) peaks at sqrt(g) = 3.1 m/s. The rotors could spin
the body up at r f_max / I = 311 rad/s^2, but the thrust that costs keeps the optimal rates
to a few rad/s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import sympy

from rrtcolearn.systems.parameters import with_parameters
from rrtcolearn.systems.symbolic import SymbolicSystem, build_system

__all__ = ["ARM", "F_MAX", "GRAVITY", "HOVER_THRUST", "INERTIA", "MASS", "geometry",
           "make_quadrotor"]

MASS = 0.486  # kg
ARM = 0.25  # m, rotor distance from the centre of mass
INERTIA = 0.00383  # kg m^2
GRAVITY = 9.81  # m/s^2
F_MAX = MASS * GRAVITY  # N per rotor
HOVER_THRUST = MASS * GRAVITY / 2.0  # N per rotor


def geometry(x: np.ndarray) -> list[np.ndarray]:
    """The vehicle of states x (K, 6) as polylines (K, P, 2) in metres: the frame between
    the rotors and a rotor mast at each end (`rrtcolearn.animation`)."""
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    centre = x[:, :2]
    side = ARM * np.stack([c, s], axis=1)
    up = 0.08 * np.stack([-s, c], axis=1)
    return [np.stack([centre - side, centre + side], axis=1),
            np.stack([centre - side, centre - side + up], axis=1),
            np.stack([centre + side, centre + side + up], axis=1)]


def make_quadrotor(parameters: Mapping[str, float] | None = None) -> SymbolicSystem:
    """The planar quadrotor of Tedrake's notes (m 0.486, r 0.25, I 0.00383), thrusts in
    [0, m g]; ``parameters`` replaces some by name (m, r, I, g: ``{"m": 0.53}``), the
    thrust box staying that of the shipped mass."""
    x, z, th, dx, dz, dth = sympy.symbols("x z theta dx dz dtheta", real=True)
    f1, f2 = sympy.symbols("f1 f2", real=True)
    m, r, inertia, g = sympy.symbols("m r I g", positive=True)
    drift = [dx, dz, dth, 0, -g, 0]
    input_matrix = [[0, 0], [0, 0], [0, 0],
                    [-sympy.sin(th) / m, -sympy.sin(th) / m],
                    [sympy.cos(th) / m, sympy.cos(th) / m],
                    [r / inertia, -r / inertia]]
    return build_system(
        "quadrotor", states=[x, z, th, dx, dz, dth], inputs=[f1, f2], drift=drift,
        input_matrix=input_matrix, input_weight=[[1, 0], [0, 1]],
        parameters=with_parameters({m: MASS, r: ARM, inertia: INERTIA, g: GRAVITY}, parameters),
        input_low=[0.0, 0.0], input_high=[F_MAX, F_MAX],
        state_low=[-2.0, -1.0, -math.pi, -4.0, -4.0, -10.0],
        state_high=[2.0, 2.0, math.pi, 4.0, 4.0, 10.0],
        angle_dims=[2],
        state_names=["x", "z", "theta", "x_dot", "z_dot", "theta_dot"],
        input_names=["thrust_1", "thrust_2"],
        description="Planar quadrotor (Tedrake: m 0.486, r 0.25, I 0.00383), thrusts in "
                    "[0, m g], hover at half",
        defaults={"start": [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                  "goal": [1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                  "geometry": "rrtcolearn.systems.quadrotor:geometry"},
    )

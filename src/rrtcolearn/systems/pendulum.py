"""The pendulum swing-up of the paper (Section 3 and Experiments).

State x = (theta, omega), theta = 0 upright; dynamics f = (omega, sin(theta) + u); running cost
C = w + u^2/2. Pontryagin: u* = -lambda_omega, and with H* = w + l_th*omega + l_om*sin(theta)
- l_om^2/2 the state+costate ODEs are

    theta' = omega, omega' = sin(theta) - l_om, l_th' = -l_om*cos(theta), l_om' = -l_th.

These are derived and compiled by the generic path (`rrtcolearn.systems.symbolic`) from the
sympy definition in `make_pendulum`; only the costate parametrisation is written here.

Costate parametrisation on H* = 0 (the paper's printed formula is wrong for its own
Hamiltonian; solving H* = 0 for l_om gives):

    l_th = tan(phi),
    l_om = sin(theta) + sign(cos(phi)) * sqrt(sin(theta)^2 + 2 (w + l_th * omega)),

with phi in (-pi/2, 3pi/2); a negative square-root argument means no costate exists. This is
a line in costate space, (tan(phi), 0) + t (0, 1), with the larger root of H* = 0 along it
where cos(phi) >= 0 and the smaller one otherwise; given as that line, the same
parametrisation holds under a torque limit (the library solves the saturated H* = 0 along it,
`rrtcolearn.systems.symbolic.CostateParametrisation`). The inverse tells the roots apart by
the slope of H* along the line, dH*/dl_om = omega': <= 0 at the larger root.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from rrtcolearn.systems.symbolic import SymbolicSystem

__all__ = ["geometry", "make_pendulum", "phi_inverse", "phi_line"]


def phi_line(x, p):
    """The line of costates of phi (sympy): (tan(phi), 0) + t (0, 1), right root where
    cos(phi) >= 0."""
    import sympy

    return (sympy.tan(p[0]), 0), (0, 1), sympy.cos(p[0])


def phi_inverse(x, lam, xdot):
    """phi of a costate on H* = 0 (sympy): atan(l_th), plus pi on the smaller root, where
    omega' = dH*/dl_om > 0."""
    import sympy

    return (sympy.Piecewise((sympy.atan(lam[0]) + sympy.pi, xdot[1] > 0),
                            (sympy.atan(lam[0]), True)),)


def geometry(x: np.ndarray) -> list[np.ndarray]:
    """The pendulum of states x (K, 2) as one polyline (K, 2, 2), pivot to bob of unit
    length, theta = 0 upright (`rrtcolearn.animation`)."""
    bob = np.stack([np.sin(x[:, 0]), np.cos(x[:, 0])], axis=1)
    return [np.stack([np.zeros_like(bob), bob], axis=1)]


def make_pendulum(parameters: Mapping[str, float] | None = None) -> SymbolicSystem:
    """The paper's pendulum: theta0 ~ U(-3pi/2, pi/2), omega0 ~ U(-pi, pi),
    phi ~ U(-pi/2, 3pi/2). Its dynamics are the unit pendulum m l^2 theta'' = m g l
    sin(theta) + u with m = l = g = 1; ``parameters`` replaces some by name
    (``{"m": 1.1, "l": 1.1}``: theta'' = (g / l) sin(theta) + u / (m l^2))."""
    # imported on use: sympy takes a while to import, and the registry imports this module
    import sympy

    from rrtcolearn.systems.parameters import with_parameters
    from rrtcolearn.systems.symbolic import CostateParametrisation, build_system

    theta, omega, u = sympy.symbols("theta omega u", real=True)
    mass, length, g = sympy.symbols("m l g", positive=True)
    # whole numbers by default: the expressions reduce to the paper's exactly
    values = with_parameters({mass: 1, length: 1, g: 1}, parameters)
    accel = (g / length * sympy.sin(theta)).subs(values)
    gain = (1 / (mass * length**2)).subs(values)
    phi = CostateParametrisation(
        names=("phi",),
        low=(-0.5 * np.pi,),
        high=(1.5 * np.pi,),
        circular=(True,),
        line=phi_line,
        inverse=phi_inverse,
    )
    return build_system(
        "pendulum",
        states=[theta, omega],
        inputs=[u],
        drift=[omega, accel],
        input_matrix=[[0], [gain]],
        input_weight=[[1]],
        state_low=[-1.5 * np.pi, -np.pi],
        state_high=[0.5 * np.pi, np.pi],
        angle_dims=[0],
        state_names=("theta", "omega"),
        input_names=("torque",),
        description="Pendulum swing-up, x = (theta, omega), f = (omega, sin(theta) + u)",
        defaults={"start": [-math.pi, 0.0], "goal": [0.0, 0.0],
                  "geometry": "rrtcolearn.systems.pendulum:geometry"},
        costate_parametrisation=phi,
    )

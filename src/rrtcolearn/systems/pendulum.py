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

with phi in (-pi/2, 3pi/2); a negative square-root argument means no costate exists.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numba
import numpy as np

if TYPE_CHECKING:
    from rrtcolearn.systems.symbolic import SymbolicSystem

__all__ = ["costate_from_params", "costate_from_params_jit", "make_pendulum",
           "phi_from_costate"]


def phi_from_costate(x: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """phi (N, 1) of costates (N, 2) on H* = 0: the inverse of `costate_from_params`.

    l_th = tan(phi) and sign(cos(phi)) = sign(l_om - sin(theta)), so phi = atan(l_th), or that
    plus pi on the branch where cos(phi) < 0; phi lies in [-pi/2, 3pi/2).
    """
    phi = np.arctan(lam[:, 0])
    phi = np.where(lam[:, 1] - np.sin(x[:, 0]) >= 0.0, phi, phi + np.pi)
    return phi[:, None]


def costate_from_params(x: np.ndarray, p: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
    """Costates (N, 2) on H* = 0 from states (N, 2) and phi (N, 1); also the (N,) valid mask."""
    theta, omega, phi = x[:, 0], x[:, 1], p[:, 0]
    s = np.sin(theta)
    l_th = np.tan(phi)
    arg = s * s + 2.0 * (w + l_th * omega)
    valid = np.isfinite(arg) & (arg >= 0.0)
    root = np.sqrt(np.where(valid, arg, 0.0))
    l_om = s + np.where(np.cos(phi) >= 0.0, 1.0, -1.0) * root
    return np.stack([l_th, l_om], axis=1), valid


@numba.njit(cache=True)
def costate_from_params_jit(x, p, w, out):
    """Scalar `costate_from_params` for one state: writes ``out`` (2,), False if none exists."""
    s = math.sin(x[0])
    l_th = math.tan(p[0])
    arg = s * s + 2.0 * (w + l_th * x[1])
    if not (arg >= 0.0) or not math.isfinite(arg):
        return False
    out[0] = l_th
    out[1] = s + (1.0 if math.cos(p[0]) >= 0.0 else -1.0) * math.sqrt(arg)
    return True


def make_pendulum() -> SymbolicSystem:
    """The paper's pendulum: theta0 ~ U(-3pi/2, pi/2), omega0 ~ U(-pi, pi),
    phi ~ U(-pi/2, 3pi/2)."""
    # imported on use: sympy takes a while to import, and the registry imports this module
    import sympy

    from rrtcolearn.systems.symbolic import CostateParametrisation, build_system

    theta, omega, u = sympy.symbols("theta omega u", real=True)
    phi = CostateParametrisation(
        names=("phi",),
        low=(-0.5 * np.pi,),
        high=(1.5 * np.pi,),
        circular=(True,),
        from_params=costate_from_params,
        from_params_jit=costate_from_params_jit,
        to_params=phi_from_costate,
    )
    return build_system(
        "pendulum",
        states=[theta, omega],
        inputs=[u],
        drift=[omega, sympy.sin(theta)],
        input_matrix=[[0], [1]],
        input_weight=[[1]],
        state_low=[-1.5 * np.pi, -np.pi],
        state_high=[0.5 * np.pi, np.pi],
        angle_dims=[0],
        state_names=("theta", "omega"),
        input_names=("torque",),
        description="Pendulum swing-up, x = (theta, omega), f = (omega, sin(theta) + u)",
        defaults={"start": [-math.pi, 0.0], "goal": [0.0, 0.0]},
        costate_parametrisation=phi,
    )

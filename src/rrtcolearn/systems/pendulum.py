"""The pendulum swing-up of the paper (Section 3 and Experiments).

State x = (theta, omega), theta = 0 upright; dynamics f = (omega, sin(theta) + u); running cost
C = w + u^2/2. Pontryagin: u* = -lambda_omega, and with H* = w + l_th*omega + l_om*sin(theta)
- l_om^2/2 the state+costate ODEs are

    theta' = omega, omega' = sin(theta) - l_om, l_th' = -l_om*cos(theta), l_om' = -l_th.

Costate parametrisation on H* = 0 (the paper's printed formula is wrong for its own
Hamiltonian; solving H* = 0 for l_om gives):

    l_th = tan(phi),
    l_om = sin(theta) + sign(cos(phi)) * sqrt(sin(theta)^2 + 2 (w + l_th * omega)),

with phi in (-pi/2, 3pi/2); a negative square-root argument means no costate exists.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from rrtcolearn.integrate import define_kernels
from rrtcolearn.systems.base import System


@numba.njit(cache=True, fastmath=False)
def _rhs(z, w, out):
    theta, omega, l_th, l_om = z[0], z[1], z[2], z[3]
    out[0] = omega
    out[1] = math.sin(theta) - l_om
    out[2] = -l_om * math.cos(theta)
    out[3] = -l_th
    out[4] = w + 0.5 * l_om * l_om


@numba.njit(cache=True)
def input_max_abs(z):
    return abs(z[3])  # u* = -lambda_omega


rhs = _rhs
define_kernels(globals())  # rollout_jit, rollout_batch_jit


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
def _costate_from_params_jit(x, p, w, out):
    s = math.sin(x[0])
    l_th = math.tan(p[0])
    arg = s * s + 2.0 * (w + l_th * x[1])
    if not (arg >= 0.0) or not math.isfinite(arg):
        return False
    out[0] = l_th
    out[1] = s + (1.0 if math.cos(p[0]) >= 0.0 else -1.0) * math.sqrt(arg)
    return True


def optimal_control(x: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """u* = argmin_u H = -lambda_omega, shape (N, 1)."""
    return -lam[:, 1:2]


def hamiltonian(x: np.ndarray, lam: np.ndarray, u: np.ndarray, w: float) -> np.ndarray:
    """H = w + u^2/2 + l_th*omega + l_om*(sin(theta) + u), shape (N,)."""
    u0 = u[:, 0]
    return w + 0.5 * u0 * u0 + lam[:, 0] * x[:, 1] + lam[:, 1] * (np.sin(x[:, 0]) + u0)


def dynamics(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """f(x, u) = (omega, sin(theta) + u), shape (N, 2)."""
    return np.stack([x[:, 1], np.sin(x[:, 0]) + u[:, 0]], axis=1)


def make_pendulum() -> System:
    """The paper's pendulum: theta0 ~ U(-3pi/2, pi/2), omega0 ~ U(-pi, pi),
    phi ~ U(-pi/2, 3pi/2)."""
    return System(
        name="pendulum",
        state_names=("theta", "omega"),
        input_names=("torque",),
        state_low=np.array([-1.5 * np.pi, -np.pi]),
        state_high=np.array([0.5 * np.pi, np.pi]),
        angle_dims=(0,),
        param_names=("phi",),
        param_low=np.array([-0.5 * np.pi]),
        param_high=np.array([1.5 * np.pi]),
        param_circular=(True,),
        rhs=_rhs,
        rollout_jit=rollout_jit,  # noqa: F821 - defined by define_kernels
        rollout_batch_jit=rollout_batch_jit,  # noqa: F821
        input_max_abs_jit=input_max_abs,
        costate_from_params=costate_from_params,
        costate_from_params_jit=_costate_from_params_jit,
        optimal_control=optimal_control,
        hamiltonian=hamiltonian,
        dynamics=dynamics,
        description="Pendulum swing-up, x = (theta, omega), f = (omega, sin(theta) + u)",
        defaults={"start": [-math.pi, 0.0], "goal": [0.0, 0.0]},
    )

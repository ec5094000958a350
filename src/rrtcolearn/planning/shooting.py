"""Exact steering by shooting: Newton's method on Pontryagin's two-point boundary value problem.

OMPL's control planners can ``steer(from, to)`` exactly when a system provides it; here any
system can. The unknowns are the initial costate and the duration; the equations are
x(T) = target and H* = 0, so every solution is an extremal of the free-final-time problem,
like every data segment. The learned U gives the first guess. The planner uses it only for
the goal connection (``plan.goal_connect``): the last edge of a learned tree is where k-NN or
a network is least precise, and where precision is all that counts.

Each Newton iteration integrates the guess and one perturbation per costate coordinate in a
single batched RK4 call; the state at a duration between two RK4 steps is interpolated
linearly, so the residual is continuous in T. The result's duration is rounded to the RK4
grid, and the caller checks the edge by integrating it as any other edge.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rrtcolearn.integrate import rollout_batch
from rrtcolearn.systems.base import System

_EPS = 1e-6  # relative finite-difference step of the costate coordinates
_STEP_SIZES = (1.0, 0.5, 0.25, 0.1)  # backtracking line search, evaluated in one batch


@dataclass(frozen=True)
class ShootingResult:
    """Steering parameters (k,) and duration (a whole number of RK4 steps) whose edge ends
    ``residual`` away from the target, after ``iterations`` Newton steps."""

    params: np.ndarray
    steps: int
    residual: float
    iterations: int


def _endpoints(system: System, x0: np.ndarray, v: np.ndarray, w: float, dt: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """States at duration v[:, -1] (B, n) from costates v[:, :-1], interpolated between RK4
    steps, and their time derivative (B, n); NaN rows where the integration fails."""
    n, b = len(x0), len(v)
    k = np.floor(v[:, -1] / dt).astype(np.int64)
    frac = v[:, -1] / dt - k
    z0 = np.empty((b, 2 * n + 1))
    z0[:, :n] = x0
    z0[:, n : 2 * n] = v[:, :-1]
    z0[:, 2 * n] = 0.0
    states, _, lengths, _ = rollout_batch(system, z0, w, dt, int(k.max()) + 1, np.inf,
                                          np.inf, n)
    # step s of the batch is the state after s + 1 RK4 steps; index -1 means x0 itself
    rows = np.arange(b)
    before = np.where((k >= 1)[:, None], states[rows, np.maximum(k - 1, 0)], x0)
    after = states[rows, k]
    ok = lengths >= k + 1
    with np.errstate(all="ignore"):  # rows that blew up are masked below
        x = before + frac[:, None] * (after - before)
        rate = (after - before) / dt
    x[~ok] = np.nan
    rate[~ok] = np.nan
    return x, rate


def _hamiltonian(system: System, x0: np.ndarray, lam: np.ndarray, w: float) -> np.ndarray:
    """H*(x0, lambda) (B,) for costates (B, n)."""
    x = np.broadcast_to(x0, lam.shape)
    return system.hamiltonian(x, lam, system.optimal_control(x, lam), w)


def shoot(system: System, x0: np.ndarray, params0: np.ndarray, duration0: float,
          offset: Callable[[np.ndarray], np.ndarray], *, time_weight: float, dt: float,
          max_duration: float, tolerance: float, max_iterations: int = 20
          ) -> ShootingResult | None:
    """Steering parameters and duration that take ``x0`` (n,) to the target.

    ``offset(states (B, n)) -> (B, n)`` is the state minus the target (angles the short way
    round, if the goal test wraps them). Starts from the costate of ``params0`` (k,) and
    ``duration0`` (the learned U) and solves x(T) = target, H*(x0, lambda0) = 0 for
    (lambda0, T) by damped Newton steps with T kept in [dt, max_duration]: in costate space
    the equations are smooth, where a parametrisation of the H* = 0 surface has
    singularities. Stops once the state residual is below ``tolerance``; the parameters
    returned are the system's for the costate found. None when it does not get there within
    ``max_iterations`` or the system cannot map a costate back to its parameters.
    """
    w = float(time_weight)
    x0 = np.asarray(x0, dtype=np.float64)
    n = len(x0)
    lam0, valid = system.costate_from_params(x0[None], np.asarray(params0, dtype=np.float64)[None],
                                             w)
    if not valid[0] or system.params_from_costate is None:
        return None
    v = np.concatenate([lam0[0], [float(np.clip(duration0, dt, max_duration))]])

    def residual(vs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, rate = _endpoints(system, x0, vs, w, dt)
        with np.errstate(all="ignore"):
            h = _hamiltonian(system, x0, vs[:, :-1], w)
            return np.hstack([offset(x), h[:, None]]), rate

    r, rate = residual(v[None])
    r, rate = r[0], rate[0]
    norm = float(np.linalg.norm(r))
    for it in range(max_iterations + 1):
        if not np.isfinite(norm):
            return None
        if float(np.linalg.norm(r[:n])) <= tolerance and abs(r[n]) <= 1e-9 * (1 + abs(w)):
            steps = max(1, round(v[-1] / dt))
            params = system.params_from_costate(x0[None], v[None, :-1])[0]
            return ShootingResult(params, steps, float(np.linalg.norm(r[:n])), it)
        if it == max_iterations:
            return None
        # Jacobian: costates by forward differences (relative steps), duration from the
        # state's rate (H* does not depend on it)
        eps = _EPS * np.maximum(1.0, np.abs(v[:n]))
        probe = np.repeat(v[None], n, axis=0)
        probe[np.arange(n), np.arange(n)] += eps
        rp, _ = residual(probe)
        jac = np.empty((n + 1, n + 1))
        jac[:, :n] = ((rp - r) / eps[:, None]).T
        jac[:n, n] = rate
        jac[n, n] = 0.0
        if not np.isfinite(jac).all():
            return None
        step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        # trust region: the costate may change by at most its size (or 1), the duration by
        # half of itself (or 0.2 s); then a backtracking line search, evaluated in one batch
        shrink = max(1.0, float(np.linalg.norm(step[:n]))
                     / max(1.0, float(np.linalg.norm(v[:n]))),
                     abs(step[n]) / max(0.2, 0.5 * v[-1]))
        step = step / shrink
        cand = v[None] + np.asarray(_STEP_SIZES)[:, None] * step[None]
        cand[:, -1] = np.clip(cand[:, -1], dt, max_duration)
        rc, ratec = residual(cand)
        with np.errstate(all="ignore"):
            norms = np.linalg.norm(rc, axis=1)
        norms[~np.isfinite(norms)] = np.inf
        best = int(np.argmin(norms))
        if not norms[best] < norm:
            return None
        v, r, rate, norm = cand[best], rc[best], ratec[best], float(norms[best])
    return None

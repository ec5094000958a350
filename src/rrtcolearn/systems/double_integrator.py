"""The double integrator x = (q, v), q'' = u, cost w + u^2/2, and its exact cost-to-go.

Built through `rrtcolearn.systems.symbolic` (steering parameters: the costate direction
``(d_q, d_v)`` in [-1, 1]^2, see there). The start-state box is q in [-2, 2], v in [-2, 2]; no
coordinate is an angle.

The optimal cost-to-go of the fixed-final-state, free-final-time problem has a closed form
(Webb and van den Berg, "Kinodynamic RRT*", 2013): for a duration T the optimal cost is

    c(T) = w T + d(T)^T G(T)^{-1} d(T) / 2,   d(T) = x1 - e^{AT} x0,
    G(T) = [[T^3/3, T^2/2], [T^2/2, T]],

which for A = [[0, 1], [0, 0]], B = [0, 1]^T and dq = q1 - q0 expands to

    c(T) = w T + 6 dq^2 / T^3 - 6 dq (v0 + v1) / T^2 + 2 (v0^2 + v0 v1 + v1^2) / T.

c -> inf at T -> 0+ (unless x0 = x1 at rest) and T -> inf, so the optimum is a root of
dc/dT = 0, i.e. of the quartic ``w T^4 - 2 (v0^2 + v0 v1 + v1^2) T^2 + 12 dq (v0 + v1) T
- 18 dq^2``; all positive roots are tried and the cheapest kept. It serves as an oracle for
the learned cost-to-go and for checking the indirect (costate) method.
"""

from __future__ import annotations

import numpy as np
import sympy

from rrtcolearn.systems.symbolic import SymbolicSystem, build_system

__all__ = ["cost_for_duration", "make_double_integrator", "optimal_arrival", "optimal_cost"]


def make_double_integrator() -> SymbolicSystem:
    """The double integrator q'' = u with cost w + u^2/2 on the box [-2, 2]^2."""
    q, v, u = sympy.symbols("q v u", real=True)
    return build_system(
        "double_integrator",
        states=[q, v],
        inputs=[u],
        drift=[v, 0],
        input_matrix=[[0], [1]],
        input_weight=[[1]],
        state_low=[-2.0, -2.0],
        state_high=[2.0, 2.0],
        input_names=["acceleration"],
        description="Double integrator, x = (q, v), f = (v, u)",
        defaults={"start": [-1.0, 0.0], "goal": [1.0, 0.0]},
    )


def _split(x0: np.ndarray, x1: np.ndarray):
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    x1 = np.atleast_2d(np.asarray(x1, dtype=float))
    if x0.shape[-1] != 2 or x1.shape[-1] != 2:
        raise ValueError("states must have 2 columns (q, v)")
    x0, x1 = np.broadcast_arrays(x0, x1)
    dq = x1[:, 0] - x0[:, 0]
    v0, v1 = x0[:, 1], x1[:, 1]
    return dq, v0, v1


def _cost(dq, v0, v1, t, w):
    return (w * t + 6.0 * dq * dq / t**3 - 6.0 * dq * (v0 + v1) / t**2
            + 2.0 * (v0 * v0 + v0 * v1 + v1 * v1) / t)


def cost_for_duration(x0: np.ndarray, x1: np.ndarray, duration: np.ndarray | float,
                      w: float) -> np.ndarray:
    """c(T): the optimal cost (N,) from x0 (N, 2) to x1 (N, 2) in exactly T > 0."""
    dq, v0, v1 = _split(x0, x1)
    t = np.broadcast_to(np.asarray(duration, dtype=float), dq.shape)
    return _cost(dq, v0, v1, t, w)


def optimal_arrival(x0: np.ndarray, x1: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
    """Optimal durations T* (N,) and costs c(T*) (N,) from x0 (N, 2) to x1 (N, 2).

    ``x0 == x1`` at rest gives T* = 0 and cost 0; non-finite states give NaN.
    """
    if not w > 0:
        raise ValueError("the time weight w must be positive")
    dq, v0, v1 = _split(x0, x1)
    nrows = len(dq)
    # monic quartic T^4 + a2 T^2 + a1 T + a0 through its companion matrix, all rows at once
    a2 = -2.0 * (v0 * v0 + v0 * v1 + v1 * v1) / w
    a1 = 12.0 * dq * (v0 + v1) / w
    a0 = -18.0 * dq * dq / w
    finite = np.isfinite(a2) & np.isfinite(a1) & np.isfinite(a0)
    a2, a1, a0 = (np.where(finite, a, 0.0) for a in (a2, a1, a0))
    comp = np.zeros((nrows, 4, 4))
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    comp[:, 0, 3], comp[:, 1, 3], comp[:, 2, 3] = -a0, -a1, -a2
    roots = np.linalg.eigvals(comp) if nrows else np.zeros((0, 4), dtype=complex)
    t = roots.real
    ok = (np.abs(roots.imag) <= 1e-6 * (1.0 + np.abs(roots))) & (t > 0.0)
    t = np.where(ok, t, 1.0)
    for _ in range(3):  # Newton polish of the quartic's roots
        p = ((t * t + a2[:, None]) * t + a1[:, None]) * t + a0[:, None]
        dp = (4.0 * t * t + 2.0 * a2[:, None]) * t + a1[:, None]
        with np.errstate(all="ignore"):
            t_new = t - p / dp
        t = np.where(ok & np.isfinite(t_new) & (t_new > 0.0), t_new, t)
    with np.errstate(all="ignore"):
        c = _cost(dq[:, None], v0[:, None], v1[:, None], t, w)
    c = np.where(ok & np.isfinite(c), c, np.inf)
    best = np.argmin(c, axis=1)
    rows = np.arange(nrows)
    t_best, c_best = t[rows, best], c[rows, best]
    # no positive root only for x0 = x1 at rest (T^4 = 0)
    at_rest = finite & (dq == 0.0) & (v0 == 0.0) & (v1 == 0.0)
    t_best = np.where(at_rest, 0.0, np.where(finite, t_best, np.nan))
    c_best = np.where(at_rest, 0.0, np.where(finite & np.isfinite(c_best), c_best, np.nan))
    return t_best, c_best


def optimal_cost(x0: np.ndarray, x1: np.ndarray, w: float) -> np.ndarray:
    """The optimal free-final-time cost-to-go (N,) from x0 (N, 2) to x1 (N, 2)."""
    return optimal_arrival(x0, x1, w)[1]

"""Goal connection by LQR about an equilibrium at the goal (``plan.goal_lqr``).

Why: the planner's other goal connections need the learned functions to know the last
stretch (shooting starts from U's guess, the funnel from extremals of the data's length) or
need luck (a random control hits a ball of the goal tolerance). Where the goal is an
equilibrium (hover, upright), the linearisation about it gives a feedback law that brings
every state of its basin into the goal region, whatever the data. On the planar quadrotor's
standard query (six coordinates, tolerance 0.1) random controls and the learned steering
never get into the ball; this connection does so from the first nodes.

What, for any `System` (nothing here depends on the system's name or on one query):

* the equilibrium: (x_e, u_e) with f(x_e, u_e) = 0 next to (goal, the input box's centre),
  by Gauss-Newton with minimum-norm steps, u kept in the input box; used only when the
  goal test puts x_e within half the tolerance (so the loop can settle inside the region);
* the model: the exact RK4 step map of the planner's step ``dt`` (the planner's own
  integration, `rrtcolearn.integrate.propagate`) linearised at (x_e, u_e) by central
  differences;
* the weights, Bryson's rule from the problem's own boxes: Q_ii = dt / h_i^2 with h_i the
  state constraint box's half-width (an angle's: half its turn), R_jj = dt / g_j^2 with g_j
  the input box's half-width; an input without a finite limit is weighted by the plan's own
  running cost (the system's R_jj);
* the gain: the discrete Riccati equation (`scipy.linalg.solve_discrete_are`); the connection
  stays off when there is no equilibrium, no solution or the closed loop is unstable;
* the connection: u = clip(u_e - K (x - x_e)) recomputed and held for each RK4 step up to
  ``max_steps`` (the planner's `GoalLQR.horizon`), cut at the first state in the goal
  region; it fails at a state outside the constraint box or in an obstacle, and as soon as
  the Lyapunov value (x - x_e)' P (x - x_e) exceeds its value at the start (the state is not
  in the saturated loop's basin: aborting there keeps failed tries cheap).

Without finite input limits the input is not clipped (the plain LQR law) unless the problem
truncates it (``u_max``: |u_j| <= u_max), which then is the box.

The loop is compiled with the system's other kernels (`integrate.closed_loop_jit`, cached on
disk): it cost about 30 us per RK4 step in numpy around the one-step `propagate`, a third of
the acrobot's planning CPU went into it, against well under a microsecond compiled.

A cost-aware ladder of gentler gains (Bryson's input weight towards the running cost's, the
cheapest reaching chain kept; issue 31) was tried and removed: its cheap chains were slow
approaches to an unstable equilibrium that the planner's step ``dt`` does not resolve (the
same inputs re-integrated at dt/2 end outside the goal region), so its costs were not real
(docs/external_problems.md, "The LQR connection's cost").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rrtcolearn.integrate import propagate
from rrtcolearn.planning.problem import PlanningProblem

__all__ = ["LOOP_TIME_CONSTANTS", "LQ_TERMINAL", "GoalLQ", "GoalLQR", "LQRTry", "build_goal_lqr",
           "equilibrium", "step_jacobians"]

# The goal loop's horizon: this many time constants of the closed loop's slowest mode that
# it moves (`GoalLQR.horizon`; e^-5 < 1% of that mode's error left). It was a fixed 3 s,
# which stopped the sparse_rrt cart-pole's loop (time constant 1.87 s) short of the goal from
# most nodes; docs/ablation.md, "The LQR loop's horizon from its time constant".
LOOP_TIME_CONSTANTS = 5.0
# A mode whose closed-loop eigenvalue lies within this of the unit circle is one the loop
# does not move (the unicycle's sideways offset: |mu| = 1 - 1e-11; a time constant of 1e4 s
# or more at a 0.01 s step): it sets no horizon, and the loop reaches the goal only where
# that offset is already within the goal region.
_UNMOVED = 1e-6

_GN_ITERATIONS = 30
_EQ_TOL = 1e-9  # |f(x_e, u_e)| relative to 1 + |f(goal, u_0)|
_FD_STEP = 1e-6  # central differences, relative to 1 + |value|


def _jacobian(fun, z: np.ndarray) -> np.ndarray:
    """(k, len(z)) central-difference Jacobian of ``fun`` (rows (N, len(z)) -> (N, k)), all
    perturbed points in one call."""
    d = z.size
    h = _FD_STEP * (1.0 + np.abs(z))
    pts = np.repeat(z[None], 2 * d, axis=0)
    pts[np.arange(d), np.arange(d)] += h
    pts[d + np.arange(d), np.arange(d)] -= h
    vals = fun(pts)
    return ((vals[:d] - vals[d:]) / (2.0 * h[:, None])).T


def equilibrium(system, goal: np.ndarray, u_low: np.ndarray, u_high: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """(x_e, u_e, relative residual): Gauss-Newton on f(x, u) = 0 from (goal, the input box's
    centre; 0 where unbounded) with minimum-norm steps (least change of x and u), u clipped
    into [u_low, u_high] after each step."""
    n = system.n_states
    centre = 0.5 * (u_low + u_high)
    u = np.where(np.isfinite(centre), centre, np.clip(0.0, u_low, u_high))
    x = np.asarray(goal, dtype=np.float64).copy()

    def f(z: np.ndarray) -> np.ndarray:
        return system.dynamics(z[:, :n], z[:, n:])

    scale = 1.0 + float(np.linalg.norm(f(np.concatenate([x, u])[None])[0]))
    z = np.concatenate([x, u])
    r = f(z[None])[0]
    for _ in range(_GN_ITERATIONS):
        if not np.all(np.isfinite(r)) or np.linalg.norm(r) <= 1e-3 * _EQ_TOL * scale:
            break
        step = np.linalg.lstsq(_jacobian(f, z), -r, rcond=None)[0]
        z = z + step
        z[n:] = np.clip(z[n:], u_low, u_high)
        r = f(z[None])[0]
    res = float(np.linalg.norm(r)) / scale if np.all(np.isfinite(r)) else np.inf
    return z[:n], z[n:], res


def step_jacobians(system, x: np.ndarray, u: np.ndarray, dt: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(A (n, n), B (n, m)): the Jacobians of the RK4 step map x -> x(dt) under a held u
    (the planner's own integration) at (x, u), by central differences."""
    n = system.n_states

    def step(z: np.ndarray) -> np.ndarray:
        return np.array([propagate(system, r[:n], r[n:], dt, 1)[1] for r in z])

    jac = _jacobian(step, np.concatenate([x, u]))
    return jac[:, :n], jac[:, n:]


@dataclass(frozen=True)
class LQRTry:
    """One closed-loop run from a node: its states (k + 1, n) from the node's, the input held
    over each step (k, m), and how it ended: "reached" (its last state is in the goal
    region), "basin" (the Lyapunov value rose above its start value), "box" (it left the
    constraint box or overflowed), "obstacle" or "timeout" (``max_steps`` without reaching)."""

    states: np.ndarray
    inputs: np.ndarray
    end: str

    @property
    def reached(self) -> bool:
        return self.end == "reached"


@dataclass(frozen=True)
class GoalLQR:
    """The LQR feedback about the goal's equilibrium (`build_goal_lqr` makes it).

    x_e, u_e : the equilibrium; K (m, n) the gain, P (n, n) the Riccati solution (the
    Lyapunov function (x - x_e)' P (x - x_e)); u_low, u_high the clipping box (+-inf where
    free); ``spectral_radius`` that of the closed loop A - B K (A, B: the RK4 step map's
    Jacobians at the equilibrium); ``time_constant`` (s) that
    of its slowest mode the loop moves (`_UNMOVED`).
    """

    problem: PlanningProblem
    dt: float
    x_e: np.ndarray
    u_e: np.ndarray
    K: np.ndarray
    P: np.ndarray
    u_low: np.ndarray
    u_high: np.ndarray
    spectral_radius: float
    time_constant: float
    A: np.ndarray  # the linearisation: the RK4 step map's Jacobians at (x_e, u_e)
    B: np.ndarray

    @property
    def horizon(self) -> float:
        """The longest loop run (s): `LOOP_TIME_CONSTANTS` time constants."""
        return LOOP_TIME_CONSTANTS * self.time_constant

    def offset(self, x: np.ndarray) -> np.ndarray:
        """(N, n) x - x_e, angle coordinates as the goal test compares them (modulo a turn
        with ``wrap_goal``, else plain)."""
        e = np.atleast_2d(x) - self.x_e
        angles = list(self.problem.goal_angles)
        if angles:
            e[:, angles] = np.mod(e[:, angles] + np.pi, 2.0 * np.pi) - np.pi
        return e

    def value(self, x: np.ndarray) -> np.ndarray:
        """(N,) the Lyapunov value (x - x_e)' P (x - x_e) of states (N, n)."""
        e = self.offset(x)
        return np.einsum("ij,jk,ik->i", e, self.P, e)

    def run(self, x0: np.ndarray, max_steps: int, box: tuple[np.ndarray, np.ndarray],
            goal_mask, validity=None) -> LQRTry:
        """The closed loop from ``x0``: u = clip(u_e - K (x - x_e)) held for each RK4 step,
        until a state is in the goal region (``goal_mask``: states (N, n) -> (N,) bool, the
        planner's goal test), for at most ``max_steps`` steps. It stops unreached at a state
        outside ``box`` (the constraint box, +-inf where free) or not finite (that state
        dropped), once the Lyapunov value exceeds its start value, and at a state that
        ``validity`` (the obstacle checker: states -> (N,) bool) rejects. The loop runs
        compiled to its end (`integrate.closed_loop_jit`); the goal test and the obstacle
        check then run once on its states."""
        m = self.u_e.size
        return _loop(self, x0, self.K[None], np.zeros((1, m)), self.P, max_steps, box,
                     goal_mask, validity)


def _loop(lqr: GoalLQR, x0: np.ndarray, K: np.ndarray, k: np.ndarray, P: np.ndarray,
          max_steps: int, box: tuple[np.ndarray, np.ndarray], goal_mask, validity) -> LQRTry:
    """The law u = clip(u_e - K[t] (x - x_e) - k[t]) at step t (the last gain held beyond
    its rows) from ``x0`` by `integrate.closed_loop_jit` (compiled; `_closed_loop` for a
    System without), cut at the first state in the goal region, then checked for obstacles
    once: `GoalLQR.run` (one gain, the Lyapunov value's stop) and `GoalLQ.run` (a gain per
    step, ``P`` = 0: no such stop) both run it."""
    sys = lqr.problem.system
    low, high = box
    wrap = np.zeros(x0.size, bool)
    wrap[list(lqr.problem.goal_angles)] = True
    args = (np.ascontiguousarray(x0, dtype=np.float64), lqr.x_e, lqr.u_e,
            np.ascontiguousarray(K, dtype=np.float64), np.ascontiguousarray(k, dtype=np.float64),
            P, lqr.u_low, lqr.u_high, wrap, float(lqr.dt), int(max_steps), low, high)
    states, inputs, how = sys.closed_loop_jit(*args) if sys.closed_loop_jit is not None \
        else _closed_loop(sys, *args)
    hits = np.flatnonzero(goal_mask(states[1:])) if len(states) > 1 else _NO_HITS
    end = int(hits[0]) + 1 if hits.size else len(inputs)
    if validity and end and not validity(states[1 : end + 1]).all():
        return LQRTry(states[: end + 1], inputs[:end], "obstacle")
    if hits.size:
        return LQRTry(states[: end + 1], inputs[:end], "reached")
    return LQRTry(states, inputs, ("timeout", "box", "basin")[how])


_NO_HITS = np.empty(0, np.int64)


def _closed_loop(system, x0, x_e, u_e, K, k, P, u_low, u_high, wrap, dt, max_steps, low, high):
    """`integrate.closed_loop_jit` in numpy, for a System built by hand without compiled
    kernels (the same law and stops; `propagate` for the step)."""
    states = np.empty((max_steps + 1, x0.size))
    inputs = np.empty((max_steps, u_e.size))
    states[0] = x0

    def value(x: np.ndarray) -> tuple[float, np.ndarray]:
        e = x - x_e
        e[wrap] = np.mod(e[wrap] + np.pi, 2.0 * np.pi) - np.pi
        return float(e @ P @ e), e

    v0, e = value(x0)
    for s in range(max_steps):
        t = min(s, len(K) - 1)
        u = np.minimum(np.maximum(u_e - K[t] @ e - k[t], u_low), u_high)
        nxt = propagate(system, states[s], u, dt, 1)[1]
        if not (np.all(low <= nxt) and np.all(nxt <= high)):  # NaN fails too
            return states[: s + 1], inputs[:s], 1
        states[s + 1], inputs[s] = nxt, u
        v, e = value(nxt)
        if v > v0:
            return states[: s + 2], inputs[: s + 1], 2
    return states, inputs, 0


def input_box(problem: PlanningProblem) -> tuple[np.ndarray, np.ndarray]:
    """(m,) each the input box of ``problem``: the system's limits within ``u_max``
    (+-inf where an input is free)."""
    u_low, u_high = (np.array(b, dtype=np.float64) for b in problem.system.input_limits())
    if problem.u_max is not None:
        u_low, u_high = np.maximum(u_low, -problem.u_max), np.minimum(u_high, problem.u_max)
    return u_low, u_high


def bryson_weights(problem: PlanningProblem, dt: float, r_cost: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(Q (n, n), R (m, m)) by Bryson's rule from ``problem``'s boxes (module docstring) at
    the step ``dt``; ``r_cost`` (m,) weighs the inputs without finite limits."""
    half_x = 0.5 * (np.asarray(problem.state_high, float) - np.asarray(problem.state_low, float))
    half_x[list(problem.system.angle_dims)] = np.pi  # an angle: half a turn
    half_x = np.where(np.isfinite(half_x) & (half_x > 0), half_x, 1.0)
    u_low, u_high = input_box(problem)
    half_u = 0.5 * (u_high - u_low)
    r_diag = np.where(np.isfinite(half_u) & (half_u > 0), 1.0 / half_u**2,
                      np.where(r_cost > 0, r_cost, 1.0))
    return np.diag(dt / half_x**2), np.diag(dt * r_diag)


def build_goal_lqr(problem: PlanningProblem, dt: float, input_weight: np.ndarray | None = None
                   ) -> GoalLQR | str:
    """The LQR connection for ``problem`` at the planner's step ``dt``, or why there is none
    (a one-line reason). ``input_weight`` (m, m) is the running cost's R, the weight of
    inputs without finite limits (identity if not given)."""
    sys = problem.system
    m = sys.n_inputs
    u_low, u_high = input_box(problem)
    with np.errstate(all="ignore"):
        x_e, u_e, res = equilibrium(sys, problem.goal, u_low, u_high)
    if not res <= _EQ_TOL:
        return (f"the goal is no equilibrium for inputs in the box (|f(x, u)| >= "
                f"{res:.2g} relative, at best)")
    d_e = float(problem.goal_distance(x_e[None])[0])
    if not d_e <= 0.5 * problem.goal_tolerance:
        return (f"the goal is no equilibrium: the nearest equilibrium found lies {d_e:.3g} "
                "from the goal region, more than half the tolerance")
    with np.errstate(all="ignore"):
        A, B = step_jacobians(sys, x_e, u_e, dt)
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        return "the linearisation at the equilibrium is not finite"
    Q, R = bryson_weights(problem, dt, np.diag(np.eye(m) if input_weight is None
                                               else input_weight))
    try:
        with np.errstate(all="ignore"):
            from scipy.linalg import solve_discrete_are  # (on first use)

            P = solve_discrete_are(A, B, Q, R)
            K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return f"no LQR solution at the equilibrium ({exc})"
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(K))):
        return "no LQR solution at the equilibrium"
    mu = np.abs(np.linalg.eigvals(A - B @ K))
    rho = float(mu.max())
    if not rho < 1.0:
        return f"the LQR closed loop is unstable (spectral radius {rho:.4g})"
    moved = mu[mu < 1.0 - _UNMOVED]
    if not len(moved):
        return "the LQR closed loop moves no mode (every eigenvalue within 1e-6 of 1)"
    tau = -float(dt) / float(np.log(moved.max())) if moved.max() > 0.0 else float(dt)
    return GoalLQR(problem, float(dt), x_e, u_e, K, 0.5 * (P + P.T), u_low, u_high, rho, tau,
                   A, B)


# `GoalLQ`'s terminal weight, as a multiple of Bryson's state weight per second (1 / h_i^2,
# h_i the state box's half-width): large enough to act as the constraint "end at the
# equilibrium" (a miss of 1% of a half-width costs 1e5), finite so that the backward pass
# stays a plain Riccati recursion
LQ_TERMINAL = 1e9


class GoalLQ:
    """The finite-horizon linear-quadratic law into the goal's equilibrium with the plan's
    own running cost (``plan.goal_lqr``'s linearisation, the cost w + u^T R u / 2 instead
    of Bryson's weights): for each horizon of j steps, the inputs that minimise the cost of
    the linearised step map's path from x to the equilibrium (a soft terminal constraint,
    `LQ_TERMINAL`), as a time-varying feedback u = u_e - K_j e - k_j on the offset
    e = x - x_e, and the path's predicted cost (the value ``e' P_j e / 2 + p_j' e + c_j``).

    Why: the LQR connection's gains come from the boxes (Bryson's rule), so its chains are
    fast and dear; a transfer whose optimum lies in the linearisation's reach (sparse_rrt's
    cart-pole, the pole held inverted for 37 s) costs a hundred times its optimum along
    them. The horizon is the free final time: the predicted cost over j is w j dt plus the
    effort, least at the optimum's duration in the linear model (goal shortcuts:
    `planning.improve.goal.goal_shortcuts`).

    The tables grow backwards from the horizon 0 as far as asked (`extend`); each step
    costs a few (n, n) products, and the gains are kept for every horizon (the law of a run
    of j steps uses K_j, K_(j-1), ..., K_1)."""

    def __init__(self, lqr: GoalLQR, input_weight: np.ndarray, time_weight: float):
        prob, dt = lqr.problem, lqr.dt
        self.lqr, self.dt, self.w = lqr, dt, float(time_weight)
        self.A, self.B = lqr.A, lqr.B
        self.R = np.asarray(input_weight, dtype=np.float64)
        Q, _ = bryson_weights(prob, dt, np.diag(self.R))
        n, m = self.B.shape
        self.P = [LQ_TERMINAL * Q / dt]  # the value's (n, n) per horizon, 0 first
        self.p, self.c = [np.zeros(n)], [0.0]
        self.K: list[np.ndarray] = [np.zeros((m, n))]  # K[j]: the first step's of horizon j
        self.k: list[np.ndarray] = [np.zeros(m)]

    def extend(self, steps: int) -> None:
        """The tables up to the horizon ``steps``."""
        A, B, dt, ue = self.A, self.B, self.dt, self.lqr.u_e
        rd = dt * self.R
        stage = self.w * dt + 0.5 * dt * float(ue @ self.R @ ue)
        P, p, c = self.P[-1], self.p[-1], self.c[-1]
        for _ in range(len(self.P) - 1, steps):
            quu = rd + B.T @ P @ B
            qux = B.T @ P @ A
            qu = rd @ ue + B.T @ p
            K, k = np.linalg.solve(quu, qux), np.linalg.solve(quu, qu)
            P = A.T @ P @ A - qux.T @ K
            P = 0.5 * (P + P.T)
            p = A.T @ p - qux.T @ k
            c = c + stage - 0.5 * float(qu @ k)
            self.P.append(P)
            self.p.append(p)
            self.c.append(c)
            self.K.append(K)
            self.k.append(k)

    def predicted(self, x0: np.ndarray, steps: int) -> np.ndarray:
        """(steps + 1,) the linear model's cost from ``x0`` (n,) into the equilibrium in
        j = 0 .. ``steps`` steps (j = 0: inf); for states (N, n) one row each, (N, steps + 1)
        (the quadratic forms of every state and horizon as one matrix product)."""
        self.extend(steps)
        e = self.lqr.offset(x0)
        ee = (e[:, :, None] * e[:, None, :]).reshape(len(e), -1)  # e e' of each state, flat
        P = np.asarray(self.P[: steps + 1]).reshape(steps + 1, -1)
        out = 0.5 * ee @ P.T + e @ np.asarray(self.p[: steps + 1]).T \
            + np.asarray(self.c[: steps + 1])
        out[:, 0] = np.inf
        return out[0] if np.ndim(x0) == 1 else out

    def run(self, x0: np.ndarray, steps: int, box: tuple[np.ndarray, np.ndarray],
            goal_mask, validity=None) -> LQRTry:
        """The law of the horizon ``steps`` from ``x0`` on the system (its RK4 step; the
        step i's gain K_(steps - i)), cut at the first state in the goal region; ends as
        `GoalLQR.run`'s ("reached", "box", "obstacle", "timeout"), compiled likewise."""
        if steps < 1:
            raise ValueError(f"a horizon of at least one step, not {steps}")
        self.extend(steps)
        n = self.A.shape[0]
        order = slice(steps, 0, -1)
        return _loop(self.lqr, x0, np.asarray(self.K[order]), np.asarray(self.k[order]),
                     np.zeros((n, n)), steps, box, goal_mask, validity)

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
  ``max_steps`` (the planner's ``funnel_duration``), cut at the first state in the goal
  region; it fails at a state outside the constraint box or in an obstacle, and as soon as
  the Lyapunov value (x - x_e)' P (x - x_e) exceeds its value at the start (the state is not
  in the saturated loop's basin: aborting there keeps failed tries cheap).

The cost-aware ladder (`GoalLQR.cheapest`, issue 31). Bryson's R prices an input by its box:
where the running cost w + u^T R u / 2 prices it far dearer (sparse_rrt's cart-pole: |F| <= 300,
R = 1, 9e4 times Bryson's weight), the loop spends the whole box to settle fast and its chain
costs thousands of times what a slower motion would. So `build_goal_lqr` also solves the
Riccati equation for gentler input weights, geometrically from Bryson's R towards dt R / w
(the running cost's, in rungs of at most ``LADDER_STEP``; inputs the running cost prices no
dearer stay), and `GoalLQR.cheapest` runs each (Bryson's for ``max_steps``, each gentler one
for up to ``HORIZON_TIME_CONSTANTS`` of its closed loop's slowest time constant, never
longer than the cheapest reaching chain so far could pay for in time, w T) and keeps the
cheapest chain that reaches the goal region. On the cart-pole's start (40 m, at rest) the
running cost's gain reaches the goal in 65 s for 71.1, 1.48x the collocation optimum, where
Bryson's loop times out. `GoalLQR.cost_to_go`, w e' P e with the running cost's P, ordered
the connection's cost-aware tries. Not adopted (docs/external_problems.md, "The LQR
connection's cost" and its follow-up: 40991cd took 2.5x the CPU to the first solution and
overran anytime budgets; with held inputs and a bounded interior search the CPU is within
1.1x, but the shipped cart-pole's swing-up no longer replays open-loop):
``build_goal_lqr(..., ladder=True)`` builds the ladder, and the planner asks for it only
while `connections.LQR_LADDER` is on (off by default). Each rung also has a held version
(`held_gain`: its input held for ``HOLD_FRACTION`` of its fastest time constant), which
`cheapest` runs for the rung it chooses, so the chain has one edge per hold (260 instead
of 6 487 on the cart-pole).

Without finite input limits the input is not clipped (the plain LQR law) unless the problem
truncates it (``u_max``: |u_j| <= u_max), which then is the box.

The loop is compiled with the system's other kernels (`integrate.closed_loop_jit`, cached on
disk): it cost about 30 us per RK4 step in numpy around the one-step `propagate`, a third of
the acrobot's planning CPU went into it, against well under a microsecond compiled.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rrtcolearn.integrate import propagate
from rrtcolearn.planning.problem import PlanningProblem

__all__ = ["Gain", "GoalLQR", "LQRTry", "build_goal_lqr", "equilibrium", "held_gain",
           "step_jacobians"]

_GN_ITERATIONS = 30
# the gentler gains' horizon: this many of the closed loop's slowest time constants (the
# slowest mode's offset falls to e^-4, 2%, of its start)
HORIZON_TIME_CONSTANTS = 4.0
# the ladder's rungs: the input weight grows by at most this factor from one to the next
LADDER_STEP = 10.0
# a gentler gain's input is held for this fraction of its (dt-designed) closed loop's
# fastest time constant (whole RK4 steps, at least one), its gain designed for that hold
# (`held_gain`): one edge per hold instead of one per step
HOLD_FRACTION = 0.5
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
class Gain:
    """One LQR gain about the goal's equilibrium: K (m, n), the Riccati solution P (n, n),
    the closed loop's spectral radius and the input weight R (m,) it was solved with."""

    K: np.ndarray
    P: np.ndarray
    spectral_radius: float
    input_weight: np.ndarray
    # the input is held for ``hold`` RK4 steps (K, P and the spectral radius are those of
    # the sampled loop at hold dt); ``held``: the same weights designed for a longer hold
    # (`held_gain`), which `GoalLQR.cheapest` runs instead
    hold: int = 1
    held: Gain | None = None

    def time_constant(self, dt: float) -> float:
        """The closed loop's slowest time constant, -hold dt / ln(spectral radius) (s)."""
        period = self.hold * dt
        return -period / float(np.log(self.spectral_radius)) if self.spectral_radius > 0 \
            else period

    def fastest_time_constant(self, A: np.ndarray, B: np.ndarray, dt: float) -> float:
        """The closed loop A - B K's fastest time constant (s) (A, B: the step map's
        Jacobians at the sampling time hold dt)."""
        rho = float(np.abs(np.linalg.eigvals(A - B @ self.K)).min())
        return -self.hold * dt / float(np.log(rho)) if 0.0 < rho < 1.0 else 0.0


@dataclass(frozen=True)
class GoalLQR:
    """The LQR feedback about the goal's equilibrium (`build_goal_lqr` makes it).

    x_e, u_e : the equilibrium; K (m, n) the gain, P (n, n) the Riccati solution (the
    Lyapunov function (x - x_e)' P (x - x_e)); u_low, u_high the clipping box (+-inf where
    free); ``spectral_radius`` that of the closed loop A - B K.
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
    # the cost-aware ladder (`cheapest`): gains with gentler input weights, Bryson's towards
    # the running cost's, and the running cost's w and R (m, m) that price their chains
    gentler: tuple[Gain, ...] = ()
    time_weight: float = 0.0
    cost_weight: np.ndarray | None = None

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
            goal_mask, validity=None, gain: Gain | None = None) -> LQRTry:
        """The closed loop from ``x0``: u = clip(u_e - K (x - x_e)) held for each RK4 step,
        until a state is in the goal region (``goal_mask``: states (N, n) -> (N,) bool, the
        planner's goal test), for at most ``max_steps`` steps; ``gain``: one of `gentler`
        instead of (K, P). It stops unreached at a state
        outside ``box`` (the constraint box, +-inf where free) or not finite (that state
        dropped), once the Lyapunov value exceeds its start value, and at a state that
        ``validity`` (the obstacle checker: states -> (N,) bool) rejects. The loop runs
        compiled to its end (`integrate.closed_loop_jit`); the goal test and the obstacle
        check then run once on its states."""
        sys = self.problem.system
        low, high = box
        wrap = np.zeros(x0.size, bool)
        wrap[list(self.problem.goal_angles)] = True
        K, P = (self.K, self.P) if gain is None else (gain.K, gain.P)
        if gain is not None and gain.hold > 1:
            return _held_loop(self, x0, gain, int(max_steps), box, goal_mask, validity, wrap)
        args = (np.ascontiguousarray(x0, dtype=np.float64), self.x_e, self.u_e, K,
                P, self.u_low, self.u_high, wrap, float(self.dt), int(max_steps),
                low, high)
        states, inputs, how = sys.closed_loop_jit(*args) if sys.closed_loop_jit is not None \
            else _closed_loop(sys, *args)
        hits = np.flatnonzero(goal_mask(states[1:])) if len(states) > 1 else _NO_HITS
        end = int(hits[0]) + 1 if hits.size else len(inputs)
        if validity and end and not validity(states[1 : end + 1]).all():
            return LQRTry(states[: end + 1], inputs[:end], "obstacle")
        if hits.size:
            return LQRTry(states[: end + 1], inputs[:end], "reached")
        return LQRTry(states, inputs, ("timeout", "box", "basin")[how])

    def cost_to_go(self, x: np.ndarray) -> np.ndarray:
        """(N,) an estimate of the running cost from states (N, n) to the goal: w (x - x_e)'
        P (x - x_e) with the P of the gentlest gain (the last of `gentler`, else (K, P)),
        the LQR cost whose input weight is the running cost's (per unit of w)."""
        P = self.gentler[-1].P if self.gentler else self.P
        e = self.offset(x)
        w = self.time_weight if self.time_weight > 0 else 1.0
        return w * np.einsum("ij,jk,ik->i", e, P, e)

    def chain_cost(self, inputs: np.ndarray) -> float:
        """The running cost of holding ``inputs`` (k, m) for a step each: the sum of
        dt (w + u^T R u / 2) (what the planner's edges cost)."""
        R = np.eye(self.u_e.size) if self.cost_weight is None else self.cost_weight
        effort = 0.5 * np.einsum("ki,ij,kj->k", inputs, R, inputs)
        return float(np.sum(self.dt * (self.time_weight + effort)))

    def cheapest(self, x0: np.ndarray, max_steps: int, box: tuple[np.ndarray, np.ndarray],
                 goal_mask, validity=None) -> tuple[LQRTry, int]:
        """The cheapest closed loop from ``x0`` that reaches the goal region among the gain
        (K, P) run for ``max_steps`` steps and each of `gentler` run for at least as long
        and up to ``HORIZON_TIME_CONSTANTS`` of its slowest time constant, but never longer
        than the cheapest reaching loop so far could pay for in time alone (w T); ties go
        to the earlier, more aggressive gain. (the loop, its gain: 0 for (K, P), k for
        ``gentler[k - 1]``); unreached, the (K, P) loop's outcome.

        The rungs are compared by their one-step loops (compiled); the chosen rung then
        runs again with its input held (`Gain.held`, one input per hold: a chain of
        hundreds of edges, not thousands), over the same horizon, and that loop is returned
        where it reaches the goal region and still undercuts Bryson's (else the one-step
        loop). The held loop runs in numpy, about 10 times the CPU of the compiled one a
        try: running it only for the chosen rung keeps the failed tries compiled."""
        first = self.run(x0, max_steps, box, goal_mask, validity)
        best, best_k, best_steps = first, 0, max_steps
        bryson = cost = self.chain_cost(first.inputs) if first.reached else np.inf
        for k, gain in enumerate(self.gentler, 1):
            steps = max(max_steps, int(np.ceil(HORIZON_TIME_CONSTANTS
                                               * gain.time_constant(self.dt) / self.dt)))
            if self.time_weight > 0 and np.isfinite(cost):
                steps = min(steps, int(cost / (self.time_weight * self.dt)))
            if steps < 1:
                break
            out = self.run(x0, steps, box, goal_mask, validity, gain)
            if out.reached and (c := self.chain_cost(out.inputs)) < cost:
                best, best_k, best_steps, cost = out, k, steps, c
        held = self.gentler[best_k - 1].held if best_k else None
        if held is not None:
            out = self.run(x0, best_steps, box, goal_mask, validity, held)
            if out.reached and self.chain_cost(out.inputs) < bryson:
                return out, best_k
        return best, best_k


_NO_HITS = np.empty(0, np.int64)


def _held_loop(lqr: GoalLQR, x0: np.ndarray, gain: Gain, max_steps: int,
               box: tuple[np.ndarray, np.ndarray], goal_mask, validity, wrap: np.ndarray
               ) -> LQRTry:
    """`GoalLQR.run` for a gain whose input is held for ``gain.hold`` RK4 steps: u =
    clip(u_e - K (x - x_e)) at the start of each hold, held by `propagate` (the planner's
    own RK4, as an edge is re-simulated) for ``hold`` steps (fewer at ``max_steps``). Stops
    as `run`: at the first state in the goal region ("reached"), at a state outside
    ``box`` or not finite (dropped, "box"), when the Lyapunov value at the end of a hold
    (the sampled loop's) exceeds the start's ("basin"), at ``max_steps`` ("timeout"); the
    obstacle check then runs once on the states kept."""
    low, high = box
    sys = lqr.problem.system

    def value(x: np.ndarray) -> tuple[float, np.ndarray]:
        e = x - lqr.x_e
        e[wrap] = np.mod(e[wrap] + np.pi, 2.0 * np.pi) - np.pi
        return float(e @ gain.P @ e), e

    v0, e = value(np.asarray(x0, dtype=np.float64))
    states, inputs = [np.asarray(x0, dtype=np.float64)[None]], []
    done, end = 0, "timeout"
    while done < max_steps:
        steps = min(gain.hold, max_steps - done)
        u = np.minimum(np.maximum(lqr.u_e - gain.K @ e, lqr.u_low), lqr.u_high)
        seg = propagate(sys, states[-1][-1], u, lqr.dt, steps, low, high)[1:]
        inside = np.all((low <= seg) & (seg <= high), axis=1)
        hits = np.flatnonzero(goal_mask(seg[: int(np.argmin(inside)) if not inside.all()
                                            else len(seg)]))
        if hits.size:
            seg, end = seg[: hits[0] + 1], "reached"
        elif not inside.all():
            seg, end = seg[: int(np.argmin(inside))], "box"
        states.append(seg)
        inputs.append(np.repeat(u[None], len(seg), axis=0))
        done += len(seg)
        if end != "timeout":
            break
        v, e = value(seg[-1])
        if v > v0:
            end = "basin"
            break
    out = LQRTry(np.concatenate(states), np.concatenate(inputs) if inputs else
                 np.empty((0, lqr.u_e.size)), end)
    if validity and len(out.inputs) and not validity(out.states[1:]).all():
        return LQRTry(out.states, out.inputs, "obstacle")
    return out


def held_gain(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, hold: int
              ) -> Gain | None:
    """The gain for the weights (Q, R) (per step dt) with the input held for ``hold``
    steps: the discrete Riccati equation of the sampled system (A^hold, sum_i<hold A^i B)
    with the weights hold Q, hold R; None where it has no stabilising solution."""
    Ah, Bh, term = np.eye(len(A)), np.zeros_like(B), np.eye(len(A))
    for _ in range(hold):
        Bh = Bh + term @ B
        term = term @ A
    Ah = term
    try:
        K, P = _riccati(Ah, Bh, hold * Q, hold * R)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(K))):
        return None
    rho = float(np.abs(np.linalg.eigvals(Ah - Bh @ K)).max())
    return Gain(K, 0.5 * (P + P.T), rho, np.diag(R).copy(), hold) if rho < 1.0 else None


def _closed_loop(system, x0, x_e, u_e, K, P, u_low, u_high, wrap, dt, max_steps, low, high):
    """`integrate.closed_loop_jit` in numpy, for a System built by hand without compiled
    kernels (the same stops; `propagate` for the step)."""
    states = np.empty((max_steps + 1, x0.size))
    inputs = np.empty((max_steps, u_e.size))
    states[0] = x0

    def value(x: np.ndarray) -> tuple[float, np.ndarray]:
        e = x - x_e
        e[wrap] = np.mod(e[wrap] + np.pi, 2.0 * np.pi) - np.pi
        return float(e @ P @ e), e

    v0, e = value(x0)
    for k in range(max_steps):
        u = np.minimum(np.maximum(u_e - K @ e, u_low), u_high)
        nxt = propagate(system, states[k], u, dt, 1)[1]
        if not (np.all(low <= nxt) and np.all(nxt <= high)):  # NaN fails too
            return states[: k + 1], inputs[:k], 1
        states[k + 1], inputs[k] = nxt, u
        v, e = value(nxt)
        if v > v0:
            return states[: k + 2], inputs[: k + 1], 2
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


def _riccati(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """(K, P): the discrete Riccati solution P for (A, B, Q, R) and its gain."""
    from scipy.linalg import solve_discrete_are  # (on first use)

    with np.errstate(all="ignore"):
        P = solve_discrete_are(A, B, Q, R)
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    return K, P


def ladder_weights(bryson_r: np.ndarray, cost_r: np.ndarray) -> list[np.ndarray]:
    """The gentler gains' input weights (each (m,)): from Bryson's ``bryson_r`` (m,) towards
    the running cost's ``cost_r`` (m,) (both at the step dt), geometrically, in rungs that
    grow by at most ``LADDER_STEP``, the last the running cost's; only inputs the running
    cost prices dearer than Bryson's rule move. Empty where none does."""
    end = np.maximum(bryson_r, cost_r)
    ratio = float(np.max(end / bryson_r))
    if not (np.isfinite(ratio) and ratio > 1.0):
        return []
    rungs = int(np.ceil(np.log(ratio) / np.log(LADDER_STEP) - 1e-9))
    return [bryson_r * (end / bryson_r) ** (k / rungs) for k in range(1, rungs + 1)]


def build_goal_lqr(problem: PlanningProblem, dt: float, input_weight: np.ndarray | None = None,
                   time_weight: float = 0.0, ladder: bool = False) -> GoalLQR | str:
    """The LQR connection for ``problem`` at the planner's step ``dt``, or why there is none
    (a one-line reason). ``input_weight`` (m, m) is the running cost's R, the weight of
    inputs without finite limits (identity if not given), and with ``time_weight`` (w) what
    prices the chains `GoalLQR.cheapest` compares; the gentler gains' input weights are
    `ladder_weights` from Bryson's to dt R / w (an unstable or failed rung is left out),
    solved only with ``ladder`` (the planner's LQR connection asks for it only while
    `connections.LQR_LADDER` is on, off by default; docs/external_problems.md)."""
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
    cost_r = np.eye(m) if input_weight is None else np.asarray(input_weight, dtype=float)
    Q, R = bryson_weights(problem, dt, np.diag(cost_r))
    try:
        K, P = _riccati(A, B, Q, R)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return f"no LQR solution at the equilibrium ({exc})"
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(K))):
        return "no LQR solution at the equilibrium"
    rho = float(np.abs(np.linalg.eigvals(A - B @ K)).max())
    if not rho < 1.0:
        return f"the LQR closed loop is unstable (spectral radius {rho:.4g})"
    gentler = []
    # the running cost w + u'Ru/2 per unit of w: input weight dt R / w beside Bryson's Q
    per_w = time_weight if time_weight > 0 else 1.0
    for r in ladder_weights(np.diag(R), dt * np.diag(cost_r) / per_w) if ladder else []:
        try:
            Kr, Pr = _riccati(A, B, Q, np.diag(r))
        except (ValueError, np.linalg.LinAlgError):
            continue
        if not (np.all(np.isfinite(Pr)) and np.all(np.isfinite(Kr))):
            continue
        rho_r = float(np.abs(np.linalg.eigvals(A - B @ Kr)).max())
        if rho_r < 1.0:
            gain = Gain(Kr, 0.5 * (Pr + Pr.T), rho_r, r)
            hold = int(HOLD_FRACTION * gain.fastest_time_constant(A, B, dt) / dt)
            held = held_gain(A, B, Q, np.diag(r), hold) if hold > 1 else None
            gentler.append(gain if held is None else replace(gain, held=held))
    return GoalLQR(problem, float(dt), x_e, u_e, K, 0.5 * (P + P.T), u_low, u_high, rho,
                   tuple(gentler), float(time_weight), cost_r)

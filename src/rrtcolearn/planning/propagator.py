"""How the planner's edges are made and checked (OMPL's StatePropagator and validity checks
in one): extremals integrated from their costates, cut and checked against the state
constraints, obstacles, the input limit and the goal region; the running cost of a held
input; the goal test. Every strategy builds its edges through one `Propagator`, so an edge
passes the same checks whichever strategy drew it.
"""

from __future__ import annotations

import numba
import numpy as np

from rrtcolearn.integrate import rollout_draws
from rrtcolearn.planning.contracts import Edge
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.settings import PlannerSettings

# `_summarise_draws`' codes as rejection reasons (0: kept); 1-3 are `integrate.rollout_draws`'
_DRAW_REASONS = (None, "state_box", "nonfinite", "input_limit", "input_limit", "obstacle")


@numba.njit(cache=True)
def _summarise_draws(traj, starts, steps, codes, u_all, goal_hit, valid, u_max, cut,
                     obstacles, aim, weight, directed):
    """`Propagator.extremal_edges`' edges of its draws (`integrate.rollout_draws`),
    compiled: per draw, where it is cut (its first invalid state, with ``cut`` its first
    |u*| above ``u_max``, its first state in the goal region: ``valid`` and ``goal_hit`` per
    row), its steps, whether it reached the goal and its largest |u*|; draws rejected get
    code 4 (an input above the limit) or 5 (an obstacle at the first step). ``directed``:
    for a draw that does not reach the goal also its state nearest ``aim`` (weighted
    distance squared, the first least), and the largest |u*| up to that state. Returns
    (codes, steps, hit, u_abs, nearest index, its distance squared, u_abs to it)."""
    count = codes.shape[0]
    n = aim.shape[0]
    codes = codes.copy()
    out_steps = np.zeros(count, np.int64)
    hit = np.zeros(count, np.bool_)
    u_abs = np.zeros(count)
    near = np.zeros(count, np.int64)
    near_d2 = np.full(count, np.inf)
    near_u = np.zeros(count)
    for c in range(count):
        if codes[c] != 0:
            continue
        r0 = starts[c] + 1  # the row of the draw's first state after its start
        end = steps[c]
        for p in range(steps[c]):
            if not valid[r0 + p]:
                end = p
                break
        if cut and u_max > 0.0:
            for p in range(steps[c]):
                if u_all[r0 + p] > u_max:
                    end = min(end, p)
                    break
        for p in range(end):
            if goal_hit[r0 + p]:
                end = p + 1
                hit[c] = True
                break
        if end == 0:
            codes[c] = 5 if obstacles else 4
            continue
        k = min(steps[c], end)
        top = 0.0
        for p in range(k + 1):
            top = max(top, u_all[r0 - 1 + p])
        if u_max > 0.0 and top > u_max:
            codes[c] = 4
            continue
        out_steps[c] = k
        u_abs[c] = top
        if directed and not hit[c]:
            best, at = np.inf, 0
            for p in range(k):
                d2 = 0.0
                for j in range(n):
                    v = (traj[r0 + p, j] - aim[j]) * weight[j]
                    d2 += v * v
                if d2 < best:
                    best, at = d2, p
            near[c] = at
            near_d2[c] = best
            top = 0.0
            for p in range(at + 2):
                top = max(top, u_all[r0 - 1 + p])
            near_u[c] = top
    return codes, out_steps, hit, u_abs, near, near_d2, near_u


class Propagator:
    """The edges of one problem under one set of settings (`settings.PlannerSettings`).

    box : the state constraints edges stop at (none with ``enforce_bounds`` false).
    ball : the goal ball as the compiled choices take it (goal, weights, wrapped angles,
        tolerance squared); None for a user goal function.
    control_box : the box random-control edges draw their inputs from (the system's input
        limits, or the truncation bound); None without limits.
    input_weight : R of the running cost w + u^T R u / 2 (None without a control box and
        with the LQR connection off).
    rejected : why the last edge asked for was not made (`contracts.OUTCOMES`).
    """

    def __init__(self, problem: PlanningProblem, settings: PlannerSettings):
        self.problem, self.settings = problem, settings
        sys = problem.system
        self.rejected = "no_costate"
        self.control_box = None
        if sys.input_limited and np.isfinite(sys.input_limits()).all():
            self.control_box = sys.input_limits()
        elif problem.u_max is not None:
            self.control_box = (np.full(sys.n_inputs, -problem.u_max),
                                np.full(sys.n_inputs, problem.u_max))
        # propagation stops at the state constraints (non-angle coordinates)
        self.box = problem.constraint_box if settings.enforce_bounds else \
            (np.full(sys.n_states, -np.inf), np.full(sys.n_states, np.inf))
        self.ball = None
        if problem.goal_fn is None:
            angles = np.zeros(sys.n_states, dtype=np.bool_)
            angles[list(problem.goal_angles)] = True
            weights = np.ones(sys.n_states) if problem.goal_weights is None else \
                np.asarray(problem.goal_weights, dtype=np.float64)
            self.ball = (np.asarray(problem.goal, dtype=np.float64), weights, angles,
                         float(problem.goal_tolerance) ** 2)
        self.input_weight = None
        if self.control_box is not None or settings.goal_lqr is not False:
            # the running cost w + u^T R u / 2 of a held input is H at lambda = 0; R read off
            # the system's H once (polarisation), so an edge's cost needs no call into it
            # (random-control edges, the LQR connection's edges)
            m, w = sys.n_inputs, settings.time_weight
            pairs = [(i, j) for i in range(m) for j in range(i + 1, m)]
            eye = np.eye(m)
            units = np.vstack([eye, *(eye[i] + eye[j] for i, j in pairs)])
            x = np.broadcast_to(problem.start, (len(units), sys.n_states))
            q = 2.0 * (sys.hamiltonian(x, np.zeros_like(x), units, w) - w)
            r = np.diag(q[:m])
            for row, (i, j) in enumerate(pairs):
                r[i, j] = r[j, i] = 0.5 * (q[m + row] - q[i] - q[j])
            self.input_weight = r

    def extremal_edges(self, x0: np.ndarray, params: np.ndarray, costates: np.ndarray,
                       aim: np.ndarray | None = None, weight: np.ndarray | None = None
                       ) -> Edge | None:
        """The edge the learned steering keeps of its draws' parameters and costates: all
        integrated in one compiled call (`integrate.rollout_draws`), the obstacles and the
        goal region asked once for all their states, each cut and checked
        (`_summarise_draws`); then the first that reaches the goal region, else (OMPL's
        directed control sampling) the draw passing nearest ``aim`` (weighted by
        ``weight``), cut at its state nearest it; without ``aim`` the first draw that gives
        an edge. None (and ``rejected`` the last rejected draw's reason) when no draw gives
        an edge."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        n = sys.n_states
        steps = np.maximum(1, np.rint(params[:, -1] / s.dt)).astype(np.int64)
        traj, u_all, starts, codes = rollout_draws(sys, x0, costates, steps, s.time_weight,
                                                   s.dt, *self.box, prob.u_max)
        valid = np.ones(len(traj), dtype=bool)
        if self.ball is not None and not prob.validity:
            # a goal ball and nothing else to ask: one pass over every row (those of draws
            # rejected, or of states before a draw's first, are never read)
            with np.errstate(all="ignore"):
                goal_hit = self.goal_mask(traj[:, :n])
        else:
            kept = np.flatnonzero(codes == 0)
            rows = np.concatenate([np.arange(starts[c] + 1, starts[c] + 1 + steps[c])
                                   for c in kept]) if kept.size else np.empty(0, np.int64)
            goal_hit = np.zeros(len(traj), dtype=bool)
            if rows.size:
                goal_hit[rows] = self.goal_mask(traj[rows, :n])
                if prob.validity:
                    valid[rows] = prob.validity(traj[rows, :n])
        directed = aim is not None
        if not directed:
            aim = weight = np.zeros(n)
        codes, steps_c, hit, u_abs, near, near_d2, near_u = _summarise_draws(
            traj, starts, steps, codes, u_all, goal_hit, valid,
            -1.0 if prob.u_max is None else float(prob.u_max), s.input_limit == "cut",
            bool(prob.validity), np.asarray(aim, dtype=np.float64), weight, directed)
        rejected = np.flatnonzero(codes)
        if rejected.size:
            self.rejected = _DRAW_REASONS[codes[rejected[-1]]]
        best, edge_of = np.inf, None
        for c in np.flatnonzero(codes == 0).tolist():
            if not directed or hit[c]:  # the whole (cut) draw
                edge_of = (c, int(steps_c[c]), bool(hit[c]), float(u_abs[c]),
                           steps_c[c] < steps[c])
                break
            if near_d2[c] < best:  # up to its state nearest the aim
                best = near_d2[c]
                edge_of = (c, int(near[c]) + 1, False, float(near_u[c]), True)
        if edge_of is None:
            return None
        c, k, reached, top, shortened = edge_of
        edge_traj = traj[starts[c] : starts[c] + k + 1].copy()
        edge_params = params[c].copy()
        if shortened:
            edge_params[-1] = k * s.dt
        return Edge(edge_traj, k, float(edge_traj[-1, 2 * n]), top, reached, edge_params,
                    costates[c].copy())

    def within_limit(self, z0: np.ndarray) -> bool:
        """False (and the outcome noted) when the input at the edge's start already breaks
        the truncation limit."""
        u_max = self.problem.u_max
        if u_max is not None and self.problem.system.input_max_abs_jit(z0) > u_max:
            self.rejected = "input_limit"
            return False
        return True

    def start_extremal(self, x0: np.ndarray, params: np.ndarray, lam: np.ndarray,
                    z0: np.ndarray) -> bool:
        """Fill ``lam`` and ``z0`` for an edge from ``x0``; False when the parameters give no
        costate or an input beyond the limit at the start."""
        sys, s = self.problem.system, self.settings
        n = sys.n_states
        z0[:n], z0[2 * n] = x0, 0.0
        if not sys.costate_from_params_jit(x0, params[:-1], s.time_weight, lam):
            return False
        z0[n : 2 * n] = lam
        return self.within_limit(z0)

    def goal_extremal(self, x0: np.ndarray, params: np.ndarray, lam: np.ndarray,
                   z0: np.ndarray):
        """The edge of ``params`` (steering parameters and duration) from ``x0``, checked
        like every edge; None unless it reaches the goal region."""
        if not self.start_extremal(x0, params, lam, z0):
            return None
        edge = self.extremal_edges(x0, params[None], lam[None])
        return edge if edge is not None and edge.hit else None

    def goal_mask(self, states: np.ndarray) -> np.ndarray:
        """(N,) True for the states (N, n) inside the goal region."""
        prob = self.problem
        if prob.goal_fn is None:
            gd = prob.goal_residual(states)
            return np.einsum("ij,ij->i", gd, gd) <= prob.goal_tolerance**2
        return prob.goal_distance(states) <= prob.goal_tolerance

    def hold_rate(self, u: np.ndarray) -> float:
        """The running cost w + u^T R u / 2 of a held input ``u`` (random-control and LQR
        edges; `integrate.explore_jit` computes it in the same order)."""
        return self.settings.time_weight + 0.5 * float(u @ self.input_weight @ u)

    def end_goal_distance(self, state: np.ndarray) -> float | None:
        """A plan's ``end_goal_distance``: the goal test's distance of its end ``state`` to a
        goal region (a user function or weighted coordinates); None for a plain ball."""
        prob = self.problem
        if prob.goal_fn is None and prob.goal_weights is None:
            return None
        return float(prob.goal_distance(state)[0])

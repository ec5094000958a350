"""The direct-method learning RRT of Bharatheesha et al. (2014), the predecessor of RRT-CoLearn.

Offline, optimal trajectories between sampled pairs (x0, x1) of the pendulum are solved by
direct collocation (CasADi + IPOPT); a k-NN cost-to-go J and validity classifier V are fitted
on the pairs. Online, an RRT expands the tree node with the least predicted J among those V
accepts, exactly like RRT-CoLearn, but its local planner is the same collocation problem solved
numerically from the node to the (truncated) target.

The optimal control problem: x = (theta, omega), theta = 0 upright, f = (omega, sin(theta) + u),
minimise the integral of w + u^2/2 over a free final time T with x(0) = x0, x(T) = x1 and,
optionally, |u| <= u_max. It is transcribed once by compressed Hermite-Simpson collocation on
N equal intervals (states at the N + 1 nodes, controls at the nodes and the N midpoints, u(t)
the quadratic through them on each interval) and solved by IPOPT with exact Hessians. The
boundary states enter as bounds of the fixed node variables, the time weight as the NLP
parameter, and the control and duration bounds as call arguments, so one solver serves every
pair and every problem variant.

Executed paths: a collocation solution holds for a duration T that is not a multiple of the
0.01 s propagation step. An edge is executed as K = round(T / dt) steps whose constant input
is the collocation control at the step's (time-scaled) midpoint, re-simulated with RK4; the
tree stores the re-simulated end state, never the collocation-claimed one, so gaps cannot
accumulate along a path. Edges aimed at the goal are "polished": re-solved with T fixed to
K * dt (warm-started), which shrinks the execution gap from ~1e-2 to ~1e-5.

Measured here (N = 20, 6000 sampled pairs per problem, 2-core shared machine): ~4 ms CPU
per IPOPT solve unbounded (all converge, a third cost <= 2: ~13 ms per kept pair), 6-7 ms
with a torque limit (most pairs are then infeasible: ~27 ms per kept pair). The summed 3-NN
distance of held-out pairs is ~1.1 (median) for ~2000 kept pairs, so the indirect data's
V threshold does not transfer; ``validity_threshold="auto"`` takes the 0.75 quantile of
leave-one-solve-out distances (1.27 there, which accepts 72 % of held-out cheap pairs,
85 % of the pairs it accepts being cheap).

``import casadi`` happens inside functions only: the package is the optional extra ``direct``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from rrtcolearn.integrate import propagate_controls
from rrtcolearn.learn.models import CostToGoRegressor, ValidityClassifier
from rrtcolearn.learn.neighbours import NeighbourIndex
from rrtcolearn.systems.pendulum import make_pendulum

DIRECT_DATASET_FORMAT = "rrtcolearn.direct-dataset"
N_INTERVALS = 20
T_MIN = 0.05
MAX_COST = 2.0
MAX_OFFSET = 1.5
_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def casadi_available() -> bool:
    """True when the optional ``casadi`` package can be imported."""
    try:
        import casadi  # noqa: F401
    except ImportError:
        return False
    return True


def default_t_max(time_weight: float, max_cost: float = MAX_COST) -> float:
    """Upper bound of the free final time: 1.5 times the longest duration the cost bound
    allows (cost >= w T), capped at 10 s (3 s for w = 1)."""
    return float(min(10.0, 1.5 * max_cost / time_weight))


# ----------------------------------------------------------------------------------------------
# collocation


@dataclass
class CollocationSolution:
    """One solved (or failed) two-point problem; arrays are the collocation variables."""

    success: bool
    status: str
    cost: float
    duration: float
    x0: np.ndarray  # (2,)
    x1: np.ndarray  # (2,)
    states: np.ndarray  # (N+1, 2) at the nodes
    controls: np.ndarray  # (N+1,) at the nodes
    mid_controls: np.ndarray  # (N,) at the interval midpoints
    iterations: int  # IPOPT iterations over all attempts
    attempts: int
    z: np.ndarray = field(repr=False)  # raw NLP solution, for warm starts

    def control_at(self, t: np.ndarray) -> np.ndarray:
        """u(t): the quadratic through (u_k, u_k+1/2, u_k+1) on each interval."""
        n = len(self.mid_controls)
        s = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration) * (n / self.duration)
        k = np.minimum(np.floor(s).astype(np.int64), n - 1)
        tau = s - k
        u0, um, u1 = self.controls[k], self.mid_controls[k], self.controls[k + 1]
        return (u0 * (2 * tau - 1) * (tau - 1) + um * 4 * tau * (1 - tau)
                + u1 * tau * (2 * tau - 1))

    def node_costs(self, time_weight: float) -> np.ndarray:
        """(N+1,) cost accumulated up to each node (Simpson's rule, as in the NLP)."""
        return _node_costs(self.controls[None], self.mid_controls[None],
                           np.array([self.duration]), time_weight)[0]


def _node_costs(u: np.ndarray, um: np.ndarray, duration: np.ndarray, w: float) -> np.ndarray:
    """Cumulative cost (P, N+1) at the nodes of P solutions, vectorised."""
    h = duration[:, None] / um.shape[1]
    seg = w * h + h / 6.0 * (0.5 * u[:, :-1] ** 2 + 2.0 * um**2 + 0.5 * u[:, 1:] ** 2)
    return np.concatenate([np.zeros((len(u), 1)), np.cumsum(seg, axis=1)], axis=1)


class CollocationSolver:
    """The pendulum's free-final-time problem, transcribed and handed to IPOPT once.

    Decision vector z = (T, X[:, 0..N] column by column, U[0..N], Um[0..N-1]). The CasADi
    calls: ``SX.sym`` for the variables and the parameter w, ``nlpsol("direct", "ipopt",
    {"x": z, "p": w, "f": J, "g": defects}, opts)``; each solve is one call
    ``solver(x0=guess, p=w, lbx=..., ubx=..., lbg=0, ubg=0)`` with x0 and x1 fixed via lbx = ubx.
    """

    def __init__(self, n_intervals: int = N_INTERVALS, max_iter: int = 200):
        import casadi as ca

        n = int(n_intervals)
        if n < 2:
            raise ValueError("n_intervals must be at least 2")
        self.n_intervals = n
        T = ca.SX.sym("T")
        X = ca.SX.sym("X", 2, n + 1)
        U = ca.SX.sym("U", 1, n + 1)
        Um = ca.SX.sym("Um", 1, n)
        w = ca.SX.sym("w")
        h = T / n

        def f(x, u):
            return ca.vertcat(x[1, :], ca.sin(x[0, :]) + u)

        F = f(X, U)
        Xm = 0.5 * (X[:, :-1] + X[:, 1:]) + h / 8.0 * (F[:, :-1] - F[:, 1:])
        defects = X[:, 1:] - X[:, :-1] - h / 6.0 * (F[:, :-1] + 4.0 * f(Xm, Um) + F[:, 1:])
        L = 0.5 * U**2
        J = w * T + h / 6.0 * ca.sum2(L[:, :-1] + 2.0 * Um**2 + L[:, 1:])
        z = ca.vertcat(T, ca.vec(X), ca.vec(U), ca.vec(Um))
        opts = {"print_time": 0, "ipopt.print_level": 0, "ipopt.sb": "yes",
                "ipopt.max_iter": int(max_iter)}
        self._solver = ca.nlpsol("direct", "ipopt",
                                 {"x": z, "p": w, "f": J, "g": ca.vec(defects)}, opts)
        self.n_vars = int(z.numel())
        self._iu = 1 + 2 * (n + 1)  # first control variable
        self._ium = self._iu + n + 1
        self._grid = np.linspace(0.0, 1.0, n + 1)

    def _bounds(self, x0, x1, u_max, t_bounds):
        n = self.n_intervals
        lbx = np.full(self.n_vars, -np.inf)
        ubx = np.full(self.n_vars, np.inf)
        lbx[0], ubx[0] = t_bounds
        lbx[1:3] = ubx[1:3] = x0
        lbx[1 + 2 * n : 3 + 2 * n] = ubx[1 + 2 * n : 3 + 2 * n] = x1
        if u_max is not None:
            lbx[self._iu :] = -u_max
            ubx[self._iu :] = u_max
        return lbx, ubx

    def guess(self, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """Straight line in the state space, zero control, T = max(0.3, |x1 - x0|)."""
        xs = x0[None, :] + (x1 - x0)[None, :] * self._grid[:, None]
        t0 = max(0.3, float(np.linalg.norm(x1 - x0)))
        return np.concatenate([[t0], xs.ravel(), np.zeros(2 * self.n_intervals + 1)])

    def solve(self, x0, x1, *, time_weight: float = 1.0, u_max: float | None = None,
              t_max: float | None = None, duration: float | None = None,
              guess: np.ndarray | None = None, retry_durations: Sequence[float] = ()
              ) -> CollocationSolution:
        """Solve from x0 to x1; ``duration`` fixes T (otherwise free in [T_MIN, t_max]).

        If IPOPT fails from the first guess, the straight-line guess is retried with each
        initial T of ``retry_durations`` in turn (IPOPT's "infeasible" verdicts from the
        straight-line guess are often local, especially for small w with a torque limit).
        """
        x0 = np.asarray(x0, dtype=np.float64)
        x1 = np.asarray(x1, dtype=np.float64)
        t_max = default_t_max(time_weight) if t_max is None else float(t_max)
        tb = (duration, duration) if duration is not None else (T_MIN, t_max)
        lbx, ubx = self._bounds(x0, x1, u_max, tb)
        guesses = [self.guess(x0, x1) if guess is None else np.array(guess, dtype=np.float64)]
        for t0 in retry_durations:
            g = self.guess(x0, x1)
            g[0] = t0
            guesses.append(g)
        iterations = attempts = 0
        for z0 in guesses:
            attempts += 1
            z0[0] = np.clip(z0[0], *tb)
            if u_max is not None:
                z0[self._iu :] = np.clip(z0[self._iu :], -u_max, u_max)
            res = self._solver(x0=z0, p=time_weight, lbx=lbx, ubx=ubx, lbg=0.0, ubg=0.0)
            stats = self._solver.stats()
            iterations += int(stats["iter_count"])
            z = np.asarray(res["x"], dtype=np.float64).ravel()
            status = str(stats["return_status"])
            cost = float(res["f"])
            ok = status in _SUCCESS and np.isfinite(cost) and np.isfinite(z).all()
            if ok:
                break
        n = self.n_intervals
        return CollocationSolution(
            success=bool(ok), status=status, cost=cost, duration=float(z[0]), x0=x0, x1=x1,
            states=z[1 : 3 + 2 * n].reshape(n + 1, 2), controls=z[self._iu : self._ium].copy(),
            mid_controls=z[self._ium :].copy(), iterations=iterations, attempts=attempts, z=z)


@lru_cache(maxsize=4)
def get_solver(n_intervals: int = N_INTERVALS) -> CollocationSolver:
    """The solver for ``n_intervals``, built once per process."""
    return CollocationSolver(n_intervals)


# ----------------------------------------------------------------------------------------------
# execution of a collocation solution as piecewise-constant inputs


@lru_cache(maxsize=1)
def _pendulum():
    """The pendulum, built once per process (its dynamics execute every edge)."""
    return make_pendulum()


def execute_controls(x0: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """States (K, 2) after each RK4 step of ``dt`` under the inputs u (K,), each held for one
    step (`rrtcolearn.integrate.propagate_controls` on the pendulum's own dynamics)."""
    return propagate_controls(_pendulum(), x0, np.asarray(u)[:, None],
                              np.ones(len(u), dtype=np.int64), dt)[1:]


def executed_controls(sol: CollocationSolution, dt: float = 0.01,
                      u_max: float | None = None) -> np.ndarray:
    """(K,) inputs held for dt each, K = round(T / dt): u at the time-scaled step midpoints."""
    k = max(1, round(sol.duration / dt))
    u = sol.control_at(sol.duration * (np.arange(k) + 0.5) / k)
    return u if u_max is None else np.clip(u, -u_max, u_max)


def execute(sol: CollocationSolution, dt: float = 0.01, u_max: float | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Executed inputs (K,) and the RK4 states (K, 2) after each step, from ``sol.x0``."""
    u = executed_controls(sol, dt, u_max)
    return u, execute_controls(sol.x0, u, dt)


def polish(solver: CollocationSolver, sol: CollocationSolution, *, time_weight: float,
           u_max: float | None, dt: float = 0.01) -> CollocationSolution:
    """Re-solve with T fixed to the nearest multiple of dt, warm-started; ``sol`` if it fails."""
    fixed = max(1, round(sol.duration / dt)) * dt
    if abs(fixed - sol.duration) < 1e-12:
        return sol
    again = solver.solve(sol.x0, sol.x1, time_weight=time_weight, u_max=u_max,
                         duration=fixed, guess=sol.z)
    return again if again.success else sol


# ----------------------------------------------------------------------------------------------
# offline: dataset and learned functions


def sample_pairs(rng: np.random.Generator, n: int, max_offset: float = MAX_OFFSET
                 ) -> tuple[np.ndarray, np.ndarray]:
    """x0 uniform in the pendulum's box, x1 = x0 + an offset uniform in the disc of radius
    ``max_offset``."""
    sys = make_pendulum()
    x0 = rng.uniform(sys.state_low, sys.state_high, size=(n, 2))
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    radius = max_offset * np.sqrt(rng.random(n))
    return x0, x0 + radius[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)


def generate_direct_dataset(n_pairs: int, seed: int, *, time_weight: float = 1.0,
                            u_max: float | None = None, max_cost: float = MAX_COST,
                            n_intervals: int = N_INTERVALS, t_max: float | None = None,
                            max_offset: float = MAX_OFFSET,
                            retry_fractions: Sequence[float] = ()) -> tuple[dict, dict]:
    """Solve ``n_pairs`` sampled pairs; keep converged solutions with cost <= ``max_cost``.

    Returns (dataset, stats). The dataset holds per kept pair ``x0``, ``x1`` (P, 2), ``cost``,
    ``duration`` (P,), ``controls`` (P, N+1), ``mid_controls`` (P, N), ``states`` (P, N+1, 2)
    and ``node_cost`` (P, N+1), plus the settings as 0-d arrays (``u_max`` inf if unbounded).
    CPU times are ``time.process_time`` of this process. ``retry_fractions``: after a failed
    solve, retry with initial durations at these fractions of ``t_max`` (e.g. (1/3, 2/3, 1)).
    """
    if n_pairs < 1:
        raise ValueError("n_pairs must be positive")
    t_max = default_t_max(time_weight, max_cost) if t_max is None else float(t_max)
    cpu0 = time.process_time()
    solver = get_solver(n_intervals)
    build_cpu = time.process_time() - cpu0
    rng = np.random.default_rng(seed)
    x0s, x1s = sample_pairs(rng, n_pairs, max_offset)
    retry = tuple(f * t_max for f in retry_fractions)
    solve_cpu = np.empty(n_pairs)
    sols = []
    converged = attempts = 0
    for i in range(n_pairs):
        t = time.process_time()
        sol = solver.solve(x0s[i], x1s[i], time_weight=time_weight, u_max=u_max, t_max=t_max,
                           retry_durations=retry)
        solve_cpu[i] = time.process_time() - t
        converged += sol.success
        attempts += sol.attempts
        if sol.success and sol.cost <= max_cost:
            sols.append(sol)
    n = n_intervals
    p = len(sols)
    u = np.array([s.controls for s in sols]).reshape(p, n + 1)
    um = np.array([s.mid_controls for s in sols]).reshape(p, n)
    duration = np.array([s.duration for s in sols], dtype=np.float64)
    data = {
        "x0": np.array([s.x0 for s in sols]).reshape(p, 2),
        "x1": np.array([s.x1 for s in sols]).reshape(p, 2),
        "cost": np.array([s.cost for s in sols], dtype=np.float64),
        "duration": duration,
        "controls": u,
        "mid_controls": um,
        "states": np.array([s.states for s in sols]).reshape(p, n + 1, 2),
        "node_cost": _node_costs(u, um, duration, time_weight),
        "time_weight": np.array(float(time_weight)),
        "u_max": np.array(np.inf if u_max is None else float(u_max)),
        "max_cost": np.array(float(max_cost)),
        "t_max": np.array(t_max),
        "n_intervals": np.array(n, dtype=np.int64),
    }
    cpu = time.process_time() - cpu0
    stats = {
        "pairs": int(n_pairs),
        "converged": int(converged),
        "solved": p,
        "success_rate": converged / n_pairs,
        "kept_rate": p / n_pairs,
        "cpu_s": cpu,
        "build_cpu_s": build_cpu,
        "attempts": int(attempts),
        "retry_fractions": list(retry_fractions),
        "cpu_s_per_solve": float(solve_cpu.mean()),  # per pair, retries included
        "cpu_s_per_ipopt_call": float(solve_cpu.sum() / max(attempts, 1)),
        "cpu_s_per_solve_median": float(np.median(solve_cpu)),
        "cpu_s_per_point": cpu / max(p, 1),
        "cpu_s_per_point_intermediate": cpu / max(p * n, 1),
        "seed": int(seed),
        "time_weight": float(time_weight),
        "u_max": u_max,
        "max_cost": float(max_cost),
        "t_max": t_max,
        "n_intervals": n,
    }
    return data, stats


def save_direct_dataset(path, data: dict, stats: dict) -> str:
    """Store a dataset with `rrtcolearn.data.store.save_arrays` (stats in the header)."""
    from rrtcolearn.data.store import save_arrays

    return save_arrays(path, DIRECT_DATASET_FORMAT,
                       {k: np.asarray(v) for k, v in data.items()}, {"stats": stats})


def load_direct_dataset(path) -> dict:
    """The dataset dict written by `save_direct_dataset` (checked; stats under "stats")."""
    from rrtcolearn.data.store import load_arrays

    arrays, meta = load_arrays(path, DIRECT_DATASET_FORMAT)
    arrays["stats"] = meta.get("stats", {})
    return arrays


def dataset_points(dataset: dict, intermediate: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Learning inputs (Q, 4) = (x0, x1), costs (Q,) and the solve each point comes from (Q,).

    With ``intermediate`` every collocation node k >= 1 of a solution gives a point
    (x0, x(t_k)) with the cost accumulated to it: by the principle of optimality a prefix of
    an optimal free-time trajectory is optimal to its own end, so these come for free.
    """
    x0 = np.asarray(dataset["x0"], dtype=np.float64)
    if not intermediate:
        X = np.concatenate([x0, np.asarray(dataset["x1"], dtype=np.float64)], axis=1)
        return X, np.asarray(dataset["cost"], dtype=np.float64), np.arange(len(x0))
    states = np.asarray(dataset["states"], dtype=np.float64)[:, 1:]  # (P, N, 2)
    n = states.shape[1]
    X = np.concatenate([np.repeat(x0[:, None], n, axis=1), states], axis=2).reshape(-1, 4)
    return (X, np.asarray(dataset["node_cost"], dtype=np.float64)[:, 1:].reshape(-1),
            np.repeat(np.arange(len(x0)), n))


def auto_validity_threshold(X: np.ndarray, group: np.ndarray, n_neighbors: int = 3, *,
                            quantile: float = 0.75, max_queries: int = 2000,
                            index: NeighbourIndex | None = None) -> float:
    """Quantile of the summed distance to the m nearest points of other solves.

    Each (subsampled) training point is queried against the points of every other solve, an
    estimate of the summed k-NN distance of an unseen in-distribution pair; the 0.75 quantile
    accepts about three quarters of such pairs (measured on held-out pairs: see the report).
    """
    index = index if index is not None else NeighbourIndex(X)
    rows = np.arange(len(X))
    if len(rows) > max_queries:  # fixed subsample: deterministic for a given dataset
        rows = np.linspace(0, len(X) - 1, max_queries).astype(np.int64)
    per_group = int(np.bincount(group).max())
    k = min(len(X), n_neighbors + per_group)
    dist, idx = index.query(X[rows], k)
    other = group[np.minimum(idx, len(X) - 1)] != group[rows][:, None]
    order = np.argsort(~other, axis=1, kind="stable")[:, :n_neighbors]
    ok = np.take_along_axis(other, order, axis=1).all(axis=1)
    summed = np.take_along_axis(dist, order, axis=1).sum(axis=1)[ok]
    if summed.size == 0:
        raise ValueError("too few solves to choose a validity threshold")
    return float(np.quantile(summed, quantile))


@dataclass
class DirectModel:
    """k-NN J and V on (x0, x1) pairs of one collocation dataset, and its settings."""

    cost_to_go: CostToGoRegressor
    validity: ValidityClassifier
    time_weight: float
    u_max: float | None
    max_cost: float
    t_max: float
    n_intervals: int
    n_points: int

    @property
    def n_neighbors(self) -> int:
        return self.cost_to_go.n_neighbors

    def query_valid(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of X (Q, 4) that V accepts, and their J."""
        rows = np.flatnonzero(self.validity.may_be_valid(X))
        dist, idx = self.cost_to_go.index_.query(X[rows], self.n_neighbors,
                                                 max_distance=self.validity.threshold)
        ok = dist.sum(axis=1) <= self.validity.threshold
        return rows[ok], self.cost_to_go.predict_from_neighbours(dist[ok], idx[ok])


def fit_direct_model(dataset: dict, n_neighbors: int = 3,
                     validity_threshold: float | str = "auto", *,
                     intermediate: bool = False) -> DirectModel:
    """Fit `CostToGoRegressor` and `ValidityClassifier` (one shared index) on the pairs.

    ``validity_threshold="auto"`` picks `auto_validity_threshold` for this dataset: the
    direct data are far sparser than the indirect data, so no fixed value suits every size.
    """
    X, y, group = dataset_points(dataset, intermediate)
    index = NeighbourIndex(X)
    if isinstance(validity_threshold, str):
        if validity_threshold != "auto":
            raise ValueError(f"validity_threshold must be a number or 'auto', "
                             f"got {validity_threshold!r}")
        validity_threshold = auto_validity_threshold(X, group, n_neighbors, index=index)
    u_max = float(dataset.get("u_max", np.inf))
    w = float(dataset.get("time_weight", 1.0))
    max_cost = float(dataset.get("max_cost", MAX_COST))
    return DirectModel(
        CostToGoRegressor(n_neighbors).fit(X, y, index),
        ValidityClassifier(n_neighbors, validity_threshold).fit(X, None, index),
        time_weight=w,
        u_max=None if not np.isfinite(u_max) else u_max,
        max_cost=max_cost,
        t_max=float(dataset.get("t_max", default_t_max(w, max_cost))),
        n_intervals=int(dataset.get("n_intervals", N_INTERVALS)),
        n_points=len(X),
    )


# ----------------------------------------------------------------------------------------------
# online: the RRT with a collocation local planner


def pendulum_reason(system) -> str | None:
    """None if ``system`` has the pendulum's dynamics f = (omega, sin(theta) + u), which the
    collocation problem is written for; else why the direct method cannot plan on it."""
    if system.n_states != 2 or system.n_inputs != 1:
        return (f"the direct method's collocation is written for the pendulum; system "
                f"{system.name!r} has {system.n_states} states and {system.n_inputs} inputs")
    x = np.array([[-np.pi, 0.0], [0.3, -1.2], [2.0, 0.7]])
    u = np.array([[0.0], [1.5], [-0.4]])
    want = np.stack([x[:, 1], np.sin(x[:, 0]) + u[:, 0]], axis=1)
    if not np.allclose(system.dynamics(x, u), want, rtol=1e-12, atol=1e-12):
        return (f"the direct method's collocation is written for the pendulum's dynamics "
                f"(omega, sin(theta) + u); system {system.name!r} has others")
    return None


def symmetric_bound(problem) -> float | None:
    """The single torque bound |u| <= u_max of ``problem`` (its u_max, within the system's
    limits), None if unbounded; ValueError for limits the collocation cannot take."""
    bound = problem.u_max
    if problem.system.input_limited:
        low, high = problem.system.input_limits()
        if not (np.isfinite(high[0]) and low[0] == -high[0]):
            raise ValueError("the direct method takes a symmetric torque limit |u| <= u_max "
                             f"only, got [{low[0]:g}, {high[0]:g}]")
        bound = float(high[0]) if bound is None else min(bound, float(high[0]))
    return bound


class DirectPlanner:
    """The direct-method learning RRT as a `rrtcolearn.planners.Planner`, with a fitted
    ``model`` (`fit_direct_model`); the other arguments are those of `solve_direct_rrt`.
    Pendulum problems only (`pendulum_reason`), and it needs casadi."""

    name = "direct"

    def __init__(self, model: DirectModel | None = None, *, time_weight: float = 1.0,
                 goal_bias: float = 0.2, max_step: float = MAX_OFFSET,
                 max_edge_cost: float | None = None, polish_edges: str = "goal",
                 dt: float = 0.01):
        if polish_edges not in ("goal", "all", "none"):
            raise ValueError(f"polish_edges must be 'goal', 'all' or 'none', got "
                             f"{polish_edges!r}")
        self.model = model
        self.time_weight = time_weight
        self.goal_bias = goal_bias
        self.max_step = max_step
        self.max_edge_cost = max_edge_cost
        self.polish_edges = polish_edges
        self.dt = dt

    def supports(self, problem) -> str | None:
        """None, or why the planner cannot run on ``problem``."""
        if not casadi_available():
            return "the casadi package is not installed (extra 'direct')"
        reason = pendulum_reason(problem.system)
        if reason is None:
            try:
                symmetric_bound(problem)
            except ValueError as exc:
                reason = str(exc)
        return reason

    def solve(self, problem, termination, seed: int = 0):
        """Plan ``problem`` (`solve_direct_rrt`)."""
        if self.model is None:
            raise ValueError("the direct planner needs a fitted model (fit_direct_model)")
        return solve_direct_rrt(self.model, problem, termination, seed,
                                time_weight=self.time_weight, goal_bias=self.goal_bias,
                                max_step=self.max_step, max_edge_cost=self.max_edge_cost,
                                polish_edges=self.polish_edges, dt=self.dt)


def solve_direct_rrt(model: DirectModel, problem, termination, seed: int = 0, *,
                     time_weight: float = 1.0, goal_bias: float = 0.2,
                     max_step: float = MAX_OFFSET, max_edge_cost: float | None = None,
                     polish_edges: str = "goal", dt: float = 0.01):
    """Plan the pendulum ``problem`` (a `PlanningProblem`) until its goal region is reached or
    ``termination`` (a `TerminationCondition`) says stop; returns a `Plan`.

    Each iteration samples a target (a goal state with probability ``goal_bias``, else
    uniform in the state box), expands the node with the least J among those V accepts
    (queries shifted by whole turns like RRT-CoLearn's), truncates the target to ``max_step``
    from it and solves the collocation problem there. A failed solve, a cost above
    ``max_edge_cost`` (default: the dataset's bound) or a re-simulated edge that leaves the
    state constraints or hits an obstacle wastes the iteration. The new node is the
    re-simulated end state; an edge is cut at its first state inside the goal region.
    ``polish_edges``: "goal" (edges aimed at the goal), "all" or "none" are re-solved with T
    a multiple of dt. The plan's tree holds the path, one control edge per step of ``dt``
    (``graph_states``: the direct tree's nodes).
    """
    from rrtcolearn.baselines.base import control_plan, in_goal

    if polish_edges not in ("goal", "all", "none"):
        raise ValueError(f"polish_edges must be 'goal', 'all' or 'none', got {polish_edges!r}")
    reason = pendulum_reason(problem.system)
    if reason is not None:
        raise ValueError(reason)
    sys, prob = problem.system, problem
    u_max = symmetric_bound(problem)
    max_edge_cost = model.max_cost if max_edge_cost is None else float(max_edge_cost)
    t_max = default_t_max(time_weight, max_edge_cost)
    solver = get_solver(model.n_intervals)
    rng = np.random.default_rng(seed)
    check = bool(prob.validity)

    states = np.empty((256, 2))
    shifts = np.empty((256, 2))
    states[0] = prob.start
    shifts[0] = sys.wrap_shift(prob.start[None])[0]
    parents = [-1]
    edge_u: list[np.ndarray] = [np.zeros(0)]
    edge_info: list[dict] = [{}]
    count = 1
    goal_node = 0 if in_goal(prob, prob.start[None])[0] else -1
    counters = {"no_valid_node": 0, "solve_failed": 0, "too_costly": 0, "out_of_bounds": 0,
                "collision": 0, "polished": 0, "solves": 0}
    iterations = 0
    solve_cpu = 0.0
    cpu0 = time.process_time()
    termination.start()
    while goal_node < 0 and not termination(iterations):
        iterations += 1
        to_goal = rng.random() < goal_bias
        target = prob.sample_goal(rng) if to_goal else rng.uniform(sys.state_low,
                                                                   sys.state_high)
        sh = shifts[:count]
        query = np.concatenate([states[:count] + sh, target + sh], axis=1)
        rows, cost = model.query_valid(query)
        if rows.size == 0:
            counters["no_valid_node"] += 1
            continue
        parent = int(rows[np.argmin(cost)])
        x_near = states[parent]
        delta = target - x_near
        dist = float(np.linalg.norm(delta))
        if dist > max_step:
            target = x_near + delta * (max_step / dist)
            to_goal = False
        t = time.process_time()
        sol = solver.solve(x_near, target, time_weight=time_weight, u_max=u_max, t_max=t_max)
        counters["solves"] += 1
        if sol.success and sol.cost <= max_edge_cost and (
                polish_edges == "all" or (polish_edges == "goal" and to_goal)):
            polished = polish(solver, sol, time_weight=time_weight, u_max=u_max, dt=dt)
            counters["polished"] += polished is not sol
            sol = polished
        solve_cpu += time.process_time() - t
        if not sol.success:
            counters["solve_failed"] += 1
            continue
        if sol.cost > max_edge_cost:
            counters["too_costly"] += 1
            continue
        u, path = execute(sol, dt, u_max)
        if not np.isfinite(path[-1]).all() or not prob.within_bounds(path).all():
            counters["out_of_bounds"] += 1
            continue
        if check and not prob.validity(path).all():
            counters["collision"] += 1
            continue
        hit = np.flatnonzero(in_goal(prob, path))
        end = int(hit[0]) + 1 if hit.size else len(u)
        if count == len(states):
            states = np.concatenate([states, np.empty_like(states)])
            shifts = np.concatenate([shifts, np.empty_like(shifts)])
        states[count] = path[end - 1]
        shifts[count] = sys.wrap_shift(path[end - 1 : end])[0]
        parents.append(parent)
        edge_u.append(u[:end])
        edge_info.append({"claimed_end": sol.x1.copy(), "resim_end": path[-1].copy(),
                          "gap": float(np.linalg.norm(path[-1] - sol.x1)),
                          "collocation_cost": sol.cost, "to_goal": to_goal})
        if hit.size:
            goal_node = count
        count += 1
    cpu, wall = time.process_time() - cpu0, termination.elapsed()

    if goal_node >= 0:
        last = goal_node
    else:
        last = int(np.argmin(prob.goal_distance(states[:count])))
    chain = []
    node = last
    while node > 0:
        chain.append(node)
        node = parents[node]
    chain.reverse()
    controls = np.concatenate([edge_u[i] for i in chain]) if chain else np.zeros(0)
    gaps = [edge_info[i]["gap"] for i in range(1, count)]
    final = edge_info[chain[-1]] if chain else {}
    extra = {
        "planner": "direct", "goal_bias": goal_bias, "max_step": max_step,
        "max_edge_cost": max_edge_cost, "collocation_u_max": u_max,
        "polish_edges": polish_edges, "validity_threshold": model.validity.threshold,
        "data_points": model.n_points, "model_time_weight": model.time_weight,
        "model_u_max": model.u_max, "solve_cpu_s": solve_cpu, "edges_in_path": len(chain),
        "claimed_end": None if not chain else final["claimed_end"].tolist(),
        "resim_end_of_last_edge": None if not chain else final["resim_end"].tolist(),
        "resim_gap": final.get("gap"),
        "edge_gap_median": float(np.median(gaps)) if gaps else None,
        "edge_gap_max": float(np.max(gaps)) if gaps else None,
        "path_gaps": [edge_info[i]["gap"] for i in chain],
        **counters,
    }
    return control_plan(prob, controls.reshape(-1, 1), np.ones(len(controls), dtype=np.int64),
                        dt=dt, time_weight=time_weight, cpu_s=cpu, wall_s=wall,
                        iterations=iterations, graph_states=count, extra=extra)

"""RRT-CoLearn (Alg. 1): learned cost-to-go as distance, learned costate as steering."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace
from itertools import pairwise
from typing import NamedTuple

import numba
import numpy as np
from scipy.special import ndtr, ndtri

from rrtcolearn import derive
from rrtcolearn.config import Config, GenerateConfig, PlanConfig, SystemConfig
from rrtcolearn.errors import ConfigError
from rrtcolearn.integrate import propagate_draws, rollout_draws
from rrtcolearn.learn.models import LearnedFunctions, best_valid
from rrtcolearn.planning.funnel import GoalFunnel
from rrtcolearn.planning.lqr import GoalLQR, build_goal_lqr
from rrtcolearn.planning.nearest import NodeIndex
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.shooting import shoot
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan, PlannerData
from rrtcolearn.systems.base import System


def _default(section: type, name: str):
    """The configuration's default for ``name`` in ``section``: its one definition."""
    return section.model_fields[name].default


@dataclass(frozen=True)
class PlannerSettings:
    """The planner's settings: the plan section of the configuration (`config.PlanConfig`)
    plus what the planner takes from the data.

    A field that shares its name with a `PlanConfig` field means what that field's
    description says and has its default (one definition, there). None where the
    configuration derives a value is derived here from the problem by the same rules
    (`rrtcolearn.derive`, `resolved`). `from_config` builds the settings from a whole
    configuration.

    time_weight, dt : w of the running cost and the integration step (``system.time_weight``,
        ``generate.dt``).
    max_duration : upper bound of the duration's truncated normal (the data's longest
        segment; by default ``generate.max_duration``).
    data_reach : the data's longest weighted excursion (``generate.max_state_distance``):
        bounds V's reach (`reach`), ``connect_reach`` and the derived ``extend_distance``.
    funnel_max_cost : the funnel's extremals end at this cost (``generate.max_cost``).
    metric_scale : weights of the state coordinates in planner distances (none: the
        system's ``metric_scale``).
    max_resample : steering draws per candidate when a draw gives no costate.
    enforce_bounds : edges stop at the state constraints (the bounds OMPL planners are
        given too).
    """

    time_weight: float = _default(SystemConfig, "time_weight")
    dt: float = _default(GenerateConfig, "dt")
    max_duration: float = _default(GenerateConfig, "max_duration")
    data_reach: float = _default(GenerateConfig, "max_state_distance")
    funnel_max_cost: float = np.inf
    metric_scale: np.ndarray | None = None
    max_resample: int = 10
    enforce_bounds: bool = True
    goal_bias: float = _default(PlanConfig, "goal_bias")
    sigma: float | None = _default(PlanConfig, "sigma")
    sigma_goal: float | None = _default(PlanConfig, "sigma_goal")
    decimals: int = _default(PlanConfig, "decimals")
    input_limit: str = _default(PlanConfig, "input_limit")
    extend_distance: float | None = _default(PlanConfig, "extend_distance")
    control_samples: int | None = _default(PlanConfig, "control_samples")
    max_candidates: int | None = _default(PlanConfig, "max_candidates")
    goal_connect: bool | None = _default(PlanConfig, "goal_connect")
    connect_reach: float | None = _default(PlanConfig, "connect_reach")
    goal_funnel: int | None = _default(PlanConfig, "goal_funnel")
    funnel_radius: float = _default(PlanConfig, "funnel_radius")
    funnel_duration: float = _default(PlanConfig, "funnel_duration")
    funnel_min_duration: float = _default(PlanConfig, "funnel_min_duration")
    stall_iterations: int = _default(PlanConfig, "stall_iterations")
    control_edges: bool | None = _default(PlanConfig, "control_edges")
    goal_lqr: bool | None = _default(PlanConfig, "goal_lqr")

    @classmethod
    def from_config(cls, config: Config, **data) -> PlannerSettings:
        """The settings of ``config`` (its plan section, w, dt and cost bound), with
        ``data`` (e.g. ``max_duration``, ``data_reach``) from the fitted model."""
        plan = {f.name: getattr(config.plan, f.name) for f in fields(cls)
                if f.name in PlanConfig.model_fields}
        g = config.generate
        own = {"time_weight": config.system.time_weight, "dt": g.dt,
               "max_duration": g.max_duration, "data_reach": g.max_state_distance,
               "funnel_max_cost": np.inf if g.max_cost is None else g.max_cost}
        return cls(**{**own, **plan, **data})

    def resolved(self, system: System) -> PlannerSettings:
        """Every None that the configuration leaves to the library, derived for ``system``
        (`derive.plan_choices`, the rules the run records in ``config.derived``)."""
        derived = {c.key.split(".")[1]: c.value
                   for c in derive.plan_choices(self, system, self.data_reach)}
        if self.connect_reach is None:
            derived["connect_reach"] = self.data_reach
        if self.metric_scale is None:
            derived["metric_scale"] = system.metric_scale
        return replace(self, **derived)


# what became of an iteration: no node within reach of the target, V rejected every
# (node, target) query, or the draw gave no edge (why), or an edge was added
OUTCOMES = ("added", "out_of_reach", "invalid_query", "no_costate", "input_limit",
            "state_box", "obstacle", "nonfinite")

_ADVICE = {
    "out_of_reach": "random targets lie beyond the data's reach of every node: widen "
                    "generate.max_state_distance or set plan.extend_distance",
    "invalid_query": "the validity model V rejects the queries from the tree (the data do "
                     "not cover these states): check that the start lies in the sampling box, "
                     "generate more simulations or raise learn.validity_threshold",
    "no_costate": "the steering parameters drawn around U's prediction give no costate on "
                  "H* = 0 (with tight input limits many directions have none): raise "
                  "plan.sigma or generate more data near the start",
    "input_limit": "edges break the input limit",
    "state_box": "edges leave the state constraints in a non-angle coordinate: widen them "
                 "(plan.state_low/state_high, default the sampling box generate.state_low/"
                 "state_high) so that they hold the motion",
    "obstacle": "edges run into obstacles at once: the start is boxed in, or the obstacles "
                "are thicker than the data's segments are long",
    "nonfinite": "integration overflowed: the dynamics blow up in the box, lower generate.dt",
}


def diagnose(outcomes: dict, stalled: bool, nodes: int, truncating: bool,
             progress: tuple[float, float] | None = None) -> str:
    """One line: why an unsolved plan stopped, what most often rejected a candidate and, with
    ``progress`` (the start's and the nearest node's distance to the goal region), how far
    the tree got toward the goal."""
    failed = {k: v for k, v in outcomes.items() if k != "added" and v}
    total = sum(outcomes.values())
    if not total:
        return "no iteration ran: raise the time or iteration limit"
    nodes_s = f"{nodes} node{'s' if nodes != 1 else ''}"
    if stalled:
        head = (f"the tree stopped growing ({nodes_s}, no new node for "
                "plan.stall_iterations iterations)")
    else:
        head = f"limit reached after {total} iteration{'s' if total != 1 else ''} with {nodes_s}"
    # targets out of reach are the normal lot of a small tree: name them only when nothing
    # else failed
    named = {k: v for k, v in failed.items() if k != "out_of_reach"} or failed
    worst = max(named, key=named.get) if named else None
    added = outcomes.get("added", 0)
    if worst is None or (not stalled and (2 * added >= total or 2 * failed[worst] < total)):
        # the limit stopped a tree that most iterations still grew, or that no one rejection
        # held back: the limit is to blame
        line = (f"{head}; {added / total:.0%} of the iterations added a node"
                + (": the tree was still growing" if 2 * added >= total else "")
                + " — raise the time or iteration limit")
        if worst is not None:
            line += (f" (most common rejection: {worst.replace('_', ' ')}, in "
                     f"{failed[worst]})")
    else:
        advice = _ADVICE[worst]
        if truncating and worst in ("invalid_query", "input_limit"):
            advice += _TRUNCATION_ADVICE
        line = (f"{head}; {failed[worst] / total:.0%} of the iterations: "
                f"{worst.replace('_', ' ')} — {advice}")
    if progress is not None:
        start, best = progress
        # (the goal test's distance: to the goal state for a ball, the user's to a region)
        line += (f"; nearest node {best:.3g} from the goal (the start: {start:.3g})"
                 + (": no progress toward the goal" if best >= 0.99 * start else ""))
    return line


# where limits are met by truncating unconstrained extremals, that is the likely cause
_TRUNCATION_ADVICE = (" (with limit_mode 'truncate', extremals that break the limit at once "
                      "leave no data: use 'saturate', where the optimal control rides the "
                      "limit)")

# automatic goal connection (goal_connect / goal_funnel / goal_lqr None): shooting from the
# nearest nodes (and the LQR connection, also while random controls explore) once this many
# goal-biased iterations in a row brought no node nearer the goal, and a funnel of
# AUTO_FUNNEL extremals once shooting has failed from FUNNEL_AFTER nodes
CONNECT_AFTER = 50
# random-control edges (control_edges None) once this many iterations in a row brought no
# node nearer the goal. 30, not 100: measured side by side on every problem with an input
# box (docs/derived_settings.md), the earlier switch cut the median CPU on the sparse_rrt
# acrobot and cart-pole and the quadrotor by 2-7x and on the torque-limited pendulum rows by
# 0.67-0.81x, at up to 15% higher first-path cost on the pendulum; a switch at once (1) was
# faster still there but raised that cost by 54%
CONTROLS_AFTER = 30
FUNNEL_AFTER = 20
AUTO_FUNNEL = 20_000

_FUNNEL_POINTS = 3  # funnel states tried per node (each on its own extremal, nearest first)
_FUNNEL_STRETCH = 1.5  # a funnel connection may last this times the funnel's duration


class Edge(NamedTuple):
    """One tree edge from its parent's state.

    traj : (steps + 1, .) the integrated states from the parent's (columns 0..n-1); an
        extremal's rows also hold its costate (n..2n-1) and its cost so far (2n).
    steps, cost, u_abs : its RK4 steps, its cost and its largest |u_i|.
    hit : it ends in the goal region.
    params, costate : an extremal's steering parameters (with its duration last) and its
        costate at the start; None for a random-control edge.
    control : a random-control edge's held input; None for an extremal.
    end_distance : the end's distance to the goal region, where known.
    """

    traj: np.ndarray
    steps: int
    cost: float
    u_abs: float
    hit: bool
    params: np.ndarray | None = None
    costate: np.ndarray | None = None
    control: np.ndarray | None = None
    end_distance: float | None = None


# `integrate.propagate_draws`' stop codes as rejection reasons
_STOP_REASONS = np.array([None, "state_box", "nonfinite"], dtype=object)


@numba.njit(cache=True)
def _pick_state(flat, counts, stops, goal, weights, angles, tol2, plain):
    """`RRTCoLearn._control_edge`'s choice among its draws' states, compiled, for a goal
    ball (no user goal function, no obstacles). ``flat`` (total, n) holds every draw's
    states (`integrate.propagate_draws`); a stopped draw's last state is dropped. Returns
    (draw c, its first row in ``flat``, the chosen state's index k within the draw, hit, the
    chosen state's goal distance), or c = -1 (and row 0: the first draw, whose stop says
    why) when no draw kept a state. The choice: the first state in the goal ball, else
    (``plain``) the last state, else the state nearest the goal. Distances as
    `PlanningProblem.goal_distance` computes them (angles of ``angles`` the short way round,
    times ``weights``, Euclidean)."""
    n = goal.shape[0]
    best_c, best_row, best_k, best_d = -1, 0, 0, np.inf
    last_c, last_row, last_k, last_d = -1, 0, 0, np.inf
    row = 0
    for c in range(counts.shape[0]):
        kept = counts[c] - (1 if stops[c] > 0 else 0)
        for k in range(kept):
            d2 = 0.0
            for i in range(n):
                v = flat[row + k, i] - goal[i]
                if angles[i]:
                    v = np.mod(v + np.pi, 2.0 * np.pi) - np.pi
                v *= weights[i]
                d2 += v * v
            if d2 <= tol2:
                return c, row, k, True, np.sqrt(d2)
            d = np.sqrt(d2)
            if d < best_d:
                best_c, best_row, best_k, best_d = c, row, k, d
            last_c, last_row, last_k, last_d = c, row, k, d
        row += counts[c]
    if last_c < 0:  # no draw kept a state: every one is empty, the first says why
        return -1, 0, 0, False, np.inf
    if plain:
        return last_c, last_row, last_k, False, last_d
    return best_c, best_row, best_k, False, best_d



# `_summarise_draws`' codes as rejection reasons (0: kept); 1-3 are `integrate.rollout_draws`'
_DRAW_REASONS = (None, "state_box", "nonfinite", "input_limit", "input_limit", "obstacle")


@numba.njit(cache=True)
def _summarise_draws(traj, starts, steps, codes, u_all, goal_hit, valid, u_max, cut,
                     obstacles, aim, weight, directed):
    """`RRTCoLearn._learned_iteration`'s edges of its draws (`integrate.rollout_draws`),
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


@dataclass
class _FunnelSearch:
    """Per tree node: its nearest funnel states (distances and indices, rows filled up to
    ``queried``) and whether the funnel connection has started from it."""

    funnel: GoalFunnel
    dist: np.ndarray
    index: np.ndarray
    tried: np.ndarray
    queried: int = 0

    def grow(self, m: int) -> None:
        self.dist = _grown(self.dist, m, np.inf)
        self.index = _grown(self.index, m, 0)
        self.tried = _grown(self.tried, m, False)


@dataclass
class _LQRSearch:
    """The LQR goal connection of one run: the controller, or why there is none (``off``), and
    per tree node its Lyapunov value (rows filled up to ``queried``) and whether the
    connection has started from it; ``tries`` counts the closed loops run."""

    lqr: GoalLQR | None
    off: str | None = None
    value: np.ndarray = field(default_factory=lambda: np.full(256, np.inf))
    tried: np.ndarray = field(default_factory=lambda: np.zeros(256, dtype=bool))
    queried: int = 0
    tries: int = 0
    # the least value from which the loop ran out of time (funnel_duration) without reaching
    # the goal: only nodes below it are tried (from farther in V the loop takes longer)
    ceiling: float = np.inf

    def grow(self, m: int) -> None:
        self.value = _grown(self.value, m, np.inf)
        self.tried = _grown(self.tried, m, False)


class _ExploreConsts(NamedTuple):
    """What `integrate.explore_jit` takes that does not change during a solve."""

    longest: int  # the most RK4 steps an input is held
    floats: np.ndarray  # dt, goal bias, the goal ball's tolerance squared, time weight
    boxes: np.ndarray  # (8, max(n, m)): the rows `integrate.explore_jit` names
    goal: np.ndarray  # (3, n): the ball's goal, weights and angle coordinates (1.0)
    index_consts: np.ndarray  # (indices, 4, n): each node index's weight, low, period, angles


# the most iterations a compiled batch (`RRTCoLearn._explore`) runs before the termination
# condition is asked again: a time limit is overrun by at most that many iterations (about
# 13 ms at the sparse_rrt cart-pole's dearest, 0.2 ms each), while a batch's call costs
# about 30 us (most batches end sooner, at the next goal-biased iteration)
_BATCH = 64


@dataclass
class _Run:
    """What one `RRTCoLearn.solve` keeps between iterations."""

    tree: PlannerData
    weight: np.ndarray  # the planner metric's coordinate weights
    plain: NodeIndex  # tree nodes by weighted distance
    wrapped: NodeIndex  # ... with angles modulo a turn
    shifts: np.ndarray  # per node: whole turns that take its state into the box
    lam: np.ndarray  # scratch: a costate
    z0: np.ndarray  # scratch: an extremal's initial state, costate and cost
    controls: bool  # random-control edges possible (an input box)
    exploring: bool  # random-control edges on
    connecting: bool  # shooting to the goal on
    auto_connect: bool  # the planner may switch shooting on
    auto_funnel: bool  # ... and the funnel
    auto_lqr: bool  # ... and the LQR connection
    search: _FunnelSearch | None  # the goal funnel, once built
    lqr: _LQRSearch | None  # the LQR connection, once switched on (maybe off: no equilibrium)
    best_goal: float  # the nearest any node came to the goal region
    iterations: int = 0
    goal_node: int = -1
    connection: str | None = None  # which connection made the last edge, if one did
    since_nearer: int = 0  # goal-biased iterations since a node came nearer the goal
    since_growth_nearer: int = 0  # iterations since a node came nearer the goal
    failed_shots: int = 0
    last_growth: int = 0  # the iteration that last added a node
    stalled: bool = False
    explore: _ExploreConsts | None = None  # the compiled iterations' constants, if they run
    directed: int = -1  # the parent of a goal-biased control expansion left to `_explore`
    tried: np.ndarray = field(default_factory=lambda: np.zeros(256, dtype=bool))
    switched: dict = field(default_factory=dict)  # when connections were switched on
    edges_by: dict = field(default_factory=lambda: {"learned": 0, "control": 0})
    outcomes: dict = field(default_factory=lambda: dict.fromkeys(OUTCOMES, 0))


def _grown(a: np.ndarray, m: int, fill) -> np.ndarray:
    """``a`` with at least ``m`` rows: new rows (as many as it had plus ``m``) set to ``fill``."""
    if a.shape[0] >= m:
        return a
    return np.concatenate([a, np.full((a.shape[0] + m, *a.shape[1:]), fill, dtype=a.dtype)])


def _truncnorm(rng: np.random.Generator, mean: float, sigma: float, lo: float, hi: float) -> float:
    """One draw of N(mean, sigma) truncated to [lo, hi] by inverting the CDF."""
    a, b = ndtr((lo - mean) / sigma), ndtr((hi - mean) / sigma)
    if b - a < 1e-12:  # mean far outside the bounds: the nearest bound is the limit
        return lo if mean < lo else hi
    return float(np.clip(mean + sigma * ndtri(a + (b - a) * rng.random()), lo, hi))


def _truncnorm_inverse(u, mean, sigma: float, lo, hi, a, b):
    """N(mean, sigma) truncated to [lo, hi] at uniforms ``u``, where a and b are the CDF at the
    bounds (elementwise)."""
    return np.clip(mean + sigma * ndtri(a + (b - a) * u), lo, hi)


def _truncnorm_vec(rng: np.random.Generator, mean: np.ndarray, sigma: float, lo: np.ndarray,
                   hi: np.ndarray) -> np.ndarray:
    """`_truncnorm` elementwise; it draws a uniform for each coordinate that needs one, in
    order, so the draws and the generator's state are those of calling it coordinate by
    coordinate."""
    a, b = ndtr((lo - mean) / sigma), ndtr((hi - mean) / sigma)
    out = np.where(mean < lo, lo, hi)  # the nearest bound, where the mass is negligible
    draw = b - a >= 1e-12
    u = rng.random(int(draw.sum()))
    out[draw] = _truncnorm_inverse(u, mean[draw], sigma, lo[draw], hi[draw], a[draw], b[draw])
    return out


class RRTCoLearn:
    """Alg. 1 with the learned J, U, V; needs no local planner.

    Each iteration samples a target (the goal with probability ``goal_bias``, else uniform in
    the system's state box), keeps the tree nodes whose query (node, target) is valid under V,
    expands the one with the least predicted cost-to-go J, draws steering parameters around
    U's prediction and integrates the state+costate ODEs. An edge is cut at its first state
    inside the goal region, or before its first state that the problem's validity checker
    rejects (obstacles); it is rejected when it leaves the state box in a non-angle
    coordinate or when its input exceeds the problem's ``u_max`` anywhere.

    Beyond the paper, for a system with an input box: once the learned steering stalls, the
    tree also grows by random-control edges (``control_edges``, `_control_edge`), and the
    learned steering is kept for goal targets within the data's reach.
    """

    def __init__(self, problem: PlanningProblem, model: LearnedFunctions,
                 settings: PlannerSettings | None = None):
        self.problem = problem
        self.model = model
        sys = problem.system
        self.settings = (settings or PlannerSettings()).resolved(sys)
        # a query (x0, x1) farther apart than this cannot have m neighbours within V's
        # threshold, since every data pair is at most data_reach apart (weighted; a weighted
        # distance r is at most r / min(weight) raw)
        self._reach = np.inf if model is None else float(
            (self.settings.data_reach + np.sqrt(2.0) * model.validity_.threshold
             / model.n_neighbors) / float(np.min(self.settings.metric_scale)))
        self._rejected = "no_costate"  # why the last draw gave no edge (OUTCOMES)
        self._indices: tuple[NodeIndex, ...] = ()  # kept up to date by _add_edge
        explicit = self.settings.goal_connect is True or bool(self.settings.goal_funnel)
        if explicit and sys.params_from_costate is None:
            raise ConfigError(f"system {sys.name!r} has no params_from_costate: the goal "
                              "connection and the goal funnel need it (plan.goal_connect, "
                              "plan.goal_funnel)")
        self._circular = np.zeros(sys.n_params, dtype=bool)
        self._circular[: len(sys.param_circular)] = sys.param_circular
        # the steering parameters' and the duration's bounds
        self._bounds = (np.append(sys.param_low, self.settings.dt),
                        np.append(sys.param_high, self.settings.max_duration))
        # the box random-control edges draw their inputs from: the system's input limits, or
        # the truncation bound; none without limits (then learned steering only)
        self._control_box = None
        if sys.input_limited and np.isfinite(sys.input_limits()).all():
            self._control_box = sys.input_limits()
        elif problem.u_max is not None:
            self._control_box = (np.full(sys.n_inputs, -problem.u_max),
                                 np.full(sys.n_inputs, problem.u_max))
        if model is None and (self._control_box is None or self.settings.control_edges is False
                              or self.settings.goal_connect is True):
            raise ConfigError("without learned functions the planner grows by random-control "
                              "edges only: it needs an input box (input limits or u_max), "
                              "plan.control_edges not false and plan.goal_connect not true")
        # propagation stops at the state constraints (non-angle coordinates)
        self._box = problem.constraint_box if self.settings.enforce_bounds else \
            (np.full(sys.n_states, -np.inf), np.full(sys.n_states, np.inf))
        # a goal ball as `_pick_state` takes it (goal, weights, wrapped angles, tolerance^2);
        # None for a user goal function
        self._ball = None
        if problem.goal_fn is None:
            angles = np.zeros(sys.n_states, dtype=np.bool_)
            angles[list(problem.goal_angles)] = True
            weights = np.ones(sys.n_states) if problem.goal_weights is None else \
                np.asarray(problem.goal_weights, dtype=np.float64)
            self._ball = (np.asarray(problem.goal, dtype=np.float64), weights, angles,
                          float(problem.goal_tolerance) ** 2)
        if self._control_box is not None or self.settings.goal_lqr is not False:
            # the running cost w + u^T R u / 2 of a held input is H at lambda = 0; R read off
            # the system's H once (polarisation), so an edge's cost needs no call into it
            # (random-control edges, the LQR connection's edges)
            m, w = sys.n_inputs, self.settings.time_weight
            pairs = [(i, j) for i in range(m) for j in range(i + 1, m)]
            eye = np.eye(m)
            units = np.vstack([eye, *(eye[i] + eye[j] for i, j in pairs)])
            x = np.broadcast_to(problem.start, (len(units), sys.n_states))
            q = 2.0 * (sys.hamiltonian(x, np.zeros_like(x), units, w) - w)
            r = np.diag(q[:m])
            for row, (i, j) in enumerate(pairs):
                r[i, j] = r[j, i] = 0.5 * (q[m + row] - q[i] - q[j])
            self._input_weight = r

    def _sample_params(self, rng, prediction: np.ndarray, sigma: float) -> np.ndarray:
        sys, s = self.problem.system, self.settings
        k = sys.n_params
        if not self._circular.any():
            # every coordinate a truncated normal: one vector of uniforms, the same numbers
            # (and so the same draws) as the coordinate-by-coordinate loop below
            return np.round(_truncnorm_vec(rng, prediction[: k + 1], sigma, *self._bounds),
                            s.decimals)
        out = np.empty(k + 1)
        for j in range(k):
            lo, hi = sys.param_low[j], sys.param_high[j]
            if self._circular[j]:
                v = prediction[j] + sigma * rng.standard_normal()
                v = np.round(v, s.decimals)
                out[j] = lo + np.mod(v - lo, hi - lo)
            else:
                out[j] = np.round(_truncnorm(rng, prediction[j], sigma, lo, hi), s.decimals)
        out[k] = np.round(_truncnorm(rng, prediction[k], sigma, s.dt, s.max_duration), s.decimals)
        return out

    def _nearest(self, states: np.ndarray, target: np.ndarray, weight: np.ndarray,
                 wrapped: NodeIndex) -> tuple[int, np.ndarray, float]:
        """The tree node nearest ``target`` (weighted, angles modulo a turn): its index, the
        offset to the target (angles the short way round) and the weighted distance."""
        i = int(wrapped.nearest(target, 1)[0])
        diff = target - states[i]
        angles = list(self.problem.system.angle_dims)
        if angles:
            diff[angles] = np.mod(diff[angles] + np.pi, 2.0 * np.pi) - np.pi
        wd = diff * weight
        return i, diff, float(np.sqrt(wd @ wd))

    def _extend(self, states: np.ndarray, target: np.ndarray, weight: np.ndarray,
                wrapped: NodeIndex) -> np.ndarray:
        """``target`` moved to within ``extend_distance`` of its nearest node (weighted, angles
        modulo a turn)."""
        i, diff, dist = self._nearest(states, target, weight, wrapped)
        factor = min(1.0, self.settings.extend_distance / dist) if dist > 0 else 1.0
        return states[i] + factor * diff

    def _edge(self, rng, x0: np.ndarray, prediction: np.ndarray, sigma: float,
              lam: np.ndarray, z0: np.ndarray):
        """One edge from ``x0``: steering parameters drawn around ``prediction``, integrated,
        checked and cut; None when the draw gives no edge."""
        # redraw parameters whose costate does not exist or whose input already breaks
        # the limit at the start: such an edge would be rejected without integrating it
        self._rejected = "no_costate"
        for _ in range(self.settings.max_resample):
            params = self._sample_params(rng, prediction, sigma)
            if self._start_edge(x0, params, lam, z0):
                return self._draw_edges(x0, params[None], lam[None])
        return None

    def _draws(self, rng, x0: np.ndarray, prediction: np.ndarray, sigma: float, count: int
               ) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``count`` steering draws around ``prediction`` that have a costate, drawn in
        blocks (parameters and costates vectorised): (parameters (c, k+1), costates (c, n))."""
        sys, s = self.problem.system, self.settings
        lo, hi = self._bounds
        mean = np.broadcast_to(prediction[: lo.size], (2 * count, lo.size))
        a, b = ndtr((lo - mean) / sigma), ndtr((hi - mean) / sigma)
        kept_p, kept_l, have = [], [], 0
        for _ in range(s.max_resample):
            u = rng.random(mean.shape)
            p = np.where(b - a < 1e-12, np.where(mean < lo, lo, hi),
                         _truncnorm_inverse(u, mean, sigma, lo, hi, a, b))
            p = np.round(p, s.decimals)
            with np.errstate(invalid="ignore"):  # rows without a costate are NaN
                lam, valid = sys.costate_from_params(
                    np.broadcast_to(x0, (len(p), x0.size)), p[:, :-1], s.time_weight)
            kept_p.append(p[valid])
            kept_l.append(lam[valid])
            have += int(valid.sum())
            if have >= count:
                break
        self._rejected = "no_costate"
        return np.concatenate(kept_p)[:count], np.concatenate(kept_l)[:count]

    def _draw_edges(self, x0: np.ndarray, params: np.ndarray, costates: np.ndarray,
                    aim: np.ndarray | None = None, weight: np.ndarray | None = None
                    ) -> Edge | None:
        """The edge `_learned_iteration` keeps of `_draws`' parameters and costates: all
        integrated in one compiled call (`integrate.rollout_draws`), the obstacles and the
        goal region asked once for all their states, each cut and checked
        (`_summarise_draws`); then the first that reaches the goal region, else (OMPL's
        directed control sampling) the draw passing nearest ``aim`` (weighted by
        ``weight``), cut at its state nearest it; without ``aim`` the first draw that gives
        an edge. None (and ``_rejected`` the last rejected draw's reason) when no draw gives
        an edge."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        n = sys.n_states
        steps = np.maximum(1, np.rint(params[:, -1] / s.dt)).astype(np.int64)
        traj, u_all, starts, codes = rollout_draws(sys, x0, costates, steps, s.time_weight,
                                                   s.dt, *self._box, prob.u_max)
        kept = np.flatnonzero(codes == 0)
        rows = np.concatenate([np.arange(starts[c] + 1, starts[c] + 1 + steps[c])
                               for c in kept]) if kept.size else np.empty(0, np.int64)
        goal_hit = np.zeros(len(traj), dtype=bool)
        valid = np.ones(len(traj), dtype=bool)
        if rows.size:
            goal_hit[rows] = self._goal_mask(traj[rows, :n])
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
            self._rejected = _DRAW_REASONS[codes[rejected[-1]]]
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

    def _within_limit(self, z0: np.ndarray) -> bool:
        """False (and the outcome noted) when the input at the edge's start already breaks
        the truncation limit."""
        u_max = self.problem.u_max
        if u_max is not None and self.problem.system.input_max_abs_jit(z0) > u_max:
            self._rejected = "input_limit"
            return False
        return True

    def _start_edge(self, x0: np.ndarray, params: np.ndarray, lam: np.ndarray,
                    z0: np.ndarray) -> bool:
        """Fill ``lam`` and ``z0`` for an edge from ``x0``; False when the parameters give no
        costate or an input beyond the limit at the start."""
        sys, s = self.problem.system, self.settings
        n = sys.n_states
        z0[:n], z0[2 * n] = x0, 0.0
        if not sys.costate_from_params_jit(x0, params[:-1], s.time_weight, lam):
            return False
        z0[n : 2 * n] = lam
        return self._within_limit(z0)

    def _connect_goal(self, tree: PlannerData, shifts: np.ndarray, tried: np.ndarray,
                      weight: np.ndarray, lam: np.ndarray, z0: np.ndarray):
        """An edge from the nearest untried node to the goal by shooting, or None.

        The first guesses are U's prediction for (node, goal) with its duration and with
        2, 4 and 8 times it: U's duration is the least reliable part of its guess far from the
        data, and Newton's method on the duration alone would not cross the long stretches
        where the residual grows before it falls.
        """
        prob, s = self.problem, self.settings
        m = tree.n_nodes
        states = tree.states[:m]
        offset = prob.goal_offset(states)
        wd = prob.goal_residual(states) * weight
        d2 = np.einsum("ij,ij->i", wd, wd)
        d2[tried[:m] | (d2 > s.connect_reach**2)] = np.inf
        node = int(np.argmin(d2))
        if not np.isfinite(d2[node]):
            return None
        tried[node] = True
        x0 = states[node]
        guess = self.model.query(self._goal_query(x0, shifts[node], offset[node]))[1][0]
        for factor in (1.0, 2.0, 4.0, 8.0):
            duration = min(max(guess[-1], s.dt) * factor, s.max_duration)
            edge = self._shoot_edge(x0, guess[:-1], duration, s.max_duration, lam, z0)
            if edge is not None:
                return node, edge
            if duration >= s.max_duration:
                break
        return None

    def _goal_query(self, x0: np.ndarray, shift: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """The learning query (1, 2n) from ``x0`` to the goal: both ends shifted by whole
        turns (``shift``) into the box, the goal as ``x0 - offset`` (angles the short way)."""
        return np.concatenate([x0 + shift, x0 - offset + shift])[None]

    def _end_goal_distance(self, state: np.ndarray) -> float | None:
        """A plan's ``end_goal_distance``: the goal test's distance of its end ``state`` to a
        goal region (a user function or weighted coordinates); None for a plain ball."""
        prob = self.problem
        if prob.goal_fn is None and prob.goal_weights is None:
            return None
        return float(prob.goal_distance(state)[0])

    def _shoot_edge(self, x0: np.ndarray, params: np.ndarray, duration: float,
                    max_duration: float, lam: np.ndarray, z0: np.ndarray):
        """The edge to the goal that shooting finds from ``x0`` starting at ``params`` and
        ``duration``, checked like every edge; None unless it reaches the goal region."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        res = shoot(sys, x0, params, duration, prob.goal_residual, time_weight=s.time_weight,
                    dt=s.dt, max_duration=max_duration,
                    tolerance=0.25 * prob.goal_tolerance, max_iterations=20)
        if res is None:
            return None
        return self._goal_edge(x0, np.append(res.params, res.steps * s.dt), lam, z0)

    def _goal_edge(self, x0: np.ndarray, params: np.ndarray, lam: np.ndarray,
                   z0: np.ndarray):
        """The edge of ``params`` (steering parameters and duration) from ``x0``, checked
        like every edge; None unless it reaches the goal region."""
        if not self._start_edge(x0, params, lam, z0):
            return None
        edge = self._draw_edges(x0, params[None], lam[None])
        return edge if edge is not None and edge.hit else None

    def _connect_funnel(self, tree: PlannerData, search: _FunnelSearch, lam: np.ndarray,
                        z0: np.ndarray):
        """An edge to the goal from the untried node nearest a funnel state, or None: the
        funnel extremal's solution moved to the node (`GoalFunnel.steer`), then polished by
        a forward solve from the node."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        m = tree.n_nodes
        search.grow(m)
        if search.queried < m:
            offsets = prob.goal_offset(tree.states[search.queried : m])
            d, i = search.funnel.nearest(offsets, _FUNNEL_POINTS, s.funnel_radius)
            search.dist[search.queried : m], search.index[search.queried : m] = d, i
            search.queried = m
        best = np.where(search.tried[:m], np.inf, search.dist[:m, 0])
        node = int(np.argmin(best))
        if not best[node] <= s.funnel_radius:
            return None
        search.tried[node] = True
        x0 = tree.states[node]
        offset = prob.goal_offset(x0)[0]
        # the node may be farther from the goal than the funnel state it starts from
        longest = _FUNNEL_STRETCH * s.funnel_duration
        for q in range(_FUNNEL_POINTS):
            if not search.dist[node, q] <= s.funnel_radius:
                break
            guess = search.funnel.steer(offset, int(search.index[node, q]), longest)
            if guess is None:
                continue
            params = sys.params_from_costate(x0[None], guess[0][None])[0]
            # the continuation's extremal as it is (exact up to the interpolation between
            # RK4 steps), else polished by a forward solve
            edge = self._goal_edge(
                x0, np.append(params, max(1, round(guess[1] / s.dt)) * s.dt), lam, z0) \
                or self._shoot_edge(x0, params, guess[1], longest, lam, z0)
            if edge is not None:
                return node, edge
        return None

    def _build_funnel(self, rng: np.random.Generator, weight: np.ndarray,
                      n_simulations: int) -> _FunnelSearch:
        """The goal funnel of ``n_simulations`` extremals and its per-node search state
        (built inside the timed region: its CPU time counts as planning time)."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        funnel = GoalFunnel.build(
            sys, prob.goal, prob.goal_offset, rng, n_simulations=n_simulations,
            time_weight=s.time_weight, dt=s.dt, max_duration=s.funnel_duration,
            max_cost=s.funnel_max_cost, scale=weight,
            # the funnel drops its states within this plain distance of the goal; a goal
            # region's tolerance is in its own units, so there every state is kept
            tolerance=prob.goal_tolerance if prob.goal_fn is None and
            prob.goal_weights is None else 0.0,
            min_duration=s.funnel_min_duration, box=(prob.state_low, prob.state_high))
        return _FunnelSearch(funnel, np.full((256, _FUNNEL_POINTS), np.inf),
                             np.zeros((256, _FUNNEL_POINTS), int), np.zeros(256, bool))

    def _learned_iteration(self, rng, states: np.ndarray, target: np.ndarray,
                           to_goal: bool, weight: np.ndarray, plain: NodeIndex,
                           wrapped: NodeIndex, shifts: np.ndarray, lam: np.ndarray,
                           z0: np.ndarray, extend: bool, bounded: bool, reach2: float):
        """Alg. 1's expansion: the parent with the least predicted J among the valid queries,
        steered by U. (parent, edge, "learned"); the edge is None (and ``_rejected`` says
        why) when no node is within reach, V rejects every query or no draw gives an edge."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        n, m = sys.n_states, len(states)
        none = (-1, None, "learned")
        if extend and not to_goal:
            target = self._extend(states, target, weight, wrapped)
        aim_images = to_goal and prob.wrap_goal
        if bounded:
            # the nearest (weighted) nodes only, from the index: the iteration's cost does
            # not grow with the tree
            near = (wrapped if aim_images else plain).nearest(target, s.max_candidates)
        else:  # the paper's planner: every node within reach
            near = np.arange(m)
        # each node aims at the goal's image nearest to it (angles modulo a turn)
        aims = states[near] - prob.offset_to(states[near], target) if aim_images \
            else target
        diff = states[near] - aims
        within = np.einsum("ij,ij->i", diff, diff) <= reach2
        near = near[within]
        if near.size == 0:
            self._rejected = "out_of_reach"
            return none
        order = np.argsort(near)  # candidates in node order, as the paper's planner has them
        near = near[order]
        if aim_images:
            aims = aims[within][order]
        sh = shifts[near]
        query = np.concatenate([states[near] + sh, aims + sh], axis=1)
        row, neighbours = best_valid(self.model, query)
        if row < 0:
            self._rejected = "invalid_query"
            return none
        parent = int(near[row])
        prediction = self.model.steer(query[row : row + 1],
                                      None if neighbours is None else neighbours[None])[0]
        x0 = states[parent]
        aim = aims[row] if aim_images else target
        sigma = s.sigma_goal if to_goal else s.sigma
        if s.control_samples > 1 and not self._circular.any():
            draws = self._draws(rng, x0, prediction, sigma, s.control_samples)
            return parent, self._draw_edges(x0, *draws, aim, weight), "learned"
        # one draw at a time (the paper's planner)
        cands = (self._edge(rng, x0, prediction, sigma, lam, z0)
                 for _ in range(s.control_samples))
        edge, best_d2 = None, np.inf
        for cand in cands:
            if cand is None:
                continue
            if s.control_samples == 1 or cand.hit:  # the paper's single draw, or a goal hit
                edge = cand
                break
            # OMPL's directed control sampling: keep the draw ending nearest the target,
            # cut at its state nearest the target
            wd = (cand.traj[1:, :n] - aim) * weight
            d2 = np.einsum("ij,ij->i", wd, wd)
            k = int(np.argmin(d2))
            if d2[k] < best_d2:
                best_d2 = float(d2[k])
                traj_c, params_c = cand.traj[: k + 2], cand.params.copy()
                params_c[-1] = (k + 1) * s.dt
                u_c = float(np.abs(sys.optimal_control(
                    traj_c[:, :n], traj_c[:, n : 2 * n])).max())
                edge = Edge(traj_c, k + 1, float(traj_c[-1, 2 * n]), u_c, False, params_c,
                            cand.costate)
        return parent, edge, "learned"

    def _control_edge(self, rng: np.random.Generator, x0: np.ndarray, directed: bool):
        """A random-control edge from ``x0`` (the expansion of sampling-based kinodynamic
        planners, OMPL's RRT and sparse_rrt's SST): an input uniform in the control box held
        for a uniform number of steps up to the data's longest segment, cut before its first
        state outside the state constraints or in an obstacle (OMPL's propagateWhileValid)
        and at its first state in the goal region. ``directed`` (goal-biased iterations):
        ``control_samples`` draws, and the one passing nearest the goal region (in the goal
        test's own distance) is kept, cut there (OMPL's directed control sampling), unless a
        draw reaches the region. None when no draw has even one valid step."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        count = max(1, s.control_samples) if directed else 1
        longest = self._longest_hold()
        inputs = rng.uniform(*self._control_box, size=(count, sys.n_inputs))
        lengths = rng.integers(1, longest + 1, size=count)
        # one compiled call for every draw; a draw's state outside the constraints (or not
        # finite) is its last, and is dropped
        flat, counts, stops = propagate_draws(sys, x0, inputs, lengths, s.dt, *self._box)
        if self._ball is not None and not prob.validity:
            # a goal ball and no obstacles: the choice below in one compiled pass
            c, begin, k, hit, d = _pick_state(flat, counts, stops, *self._ball, count == 1)
            if c < 0:
                self._rejected = _STOP_REASONS[stops[begin]]
                return None
            u = inputs[c]
            traj = np.empty((k + 2, x0.size))
            traj[0] = x0
            traj[1:] = flat[begin : begin + k + 1]
            rate = self._hold_rate(u)
            return Edge(traj, k + 1, (k + 1) * s.dt * rate, float(np.abs(u).max()), hit,
                        control=u, end_distance=float(d))
        reasons = _STOP_REASONS[stops]  # a copy: "obstacle" may replace one below
        if stops.any():
            keep = np.ones(len(flat), bool)
            keep[np.cumsum(counts)[stops > 0] - 1] = False
            flat, counts = flat[keep], counts - (stops > 0)
        if prob.validity and len(flat):  # obstacles need every state: cut each draw there
            ok = prob.validity(flat)
            if not ok.all():
                parts, begin = [], 0
                for c, k in enumerate(counts.tolist()):
                    part = flat[begin : begin + k]
                    begin += k
                    bad = np.flatnonzero(~ok[begin - k : begin])
                    if bad.size:
                        part, reasons[c] = part[: bad[0]], "obstacle"
                    parts.append(part)
                counts = np.array([len(p) for p in parts])
                flat = np.concatenate(parts)
        if not counts.any():
            self._rejected = reasons[int(np.flatnonzero(counts == 0)[0])]
            return None
        ends = np.cumsum(counts)
        # a user's goal function is called once per edge: its distances serve the goal test,
        # the directed choice and the end's distance (the planner's progress)
        dist = prob.goal_distance(flat) if prob.goal_fn is not None else None
        hits = np.flatnonzero(dist <= prob.goal_tolerance if dist is not None
                              else self._goal_mask(flat))
        hit = bool(hits.size)
        if hit:  # the first draw's first state in the goal region
            j = int(hits[0])
        elif count == 1:  # the plain random control: its whole valid prefix
            j = len(flat) - 1
        else:  # directed: the state nearest the goal region
            j = int(np.argmin(prob.goal_distance(flat) if dist is None else dist))
        c = int(np.searchsorted(ends, j, side="right"))
        begin = int(ends[c - 1]) if c else 0
        k = j - begin
        u = inputs[c]
        traj = np.vstack([x0[None], flat[begin : j + 1]])
        rate = self._hold_rate(u)
        end_distance = float(dist[j]) if dist is not None else \
            float(prob.goal_distance(traj[-1:])[0])
        return Edge(traj, k + 1, (k + 1) * s.dt * rate, float(np.abs(u).max()), hit,
                    control=u, end_distance=end_distance)

    def _goal_mask(self, states: np.ndarray) -> np.ndarray:
        """(N,) True for the states (N, n) inside the goal region."""
        prob = self.problem
        if prob.goal_fn is None:
            gd = prob.goal_residual(states)
            return np.einsum("ij,ij->i", gd, gd) <= prob.goal_tolerance**2
        return prob.goal_distance(states) <= prob.goal_tolerance

    def _add_edge(self, tree: PlannerData, parent: int, edge: Edge) -> int:
        """Add the node at the end of ``edge`` below ``parent``."""
        sys = self.problem.system
        n = sys.n_states
        end = edge.traj[-1, :n]
        for index in self._indices:
            index.add(end)
        if edge.control is not None:
            return tree.add(end, parent, np.full(n, np.nan), np.full(sys.n_params, np.nan),
                            edge.steps * self.settings.dt, edge.cost, edge.traj, edge.u_abs,
                            control=edge.control)
        return tree.add(end, parent, edge.costate, edge.params[:-1],
                        edge.steps * self.settings.dt, edge.cost, edge.traj[:, :n],
                        edge.u_abs)

    def solve(self, termination: TerminationCondition, seed: int | np.random.SeedSequence = 0
              ) -> Plan:
        """Grow the tree until a node reaches the goal region or ``termination`` says stop."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        # compiled code this solve may call and no earlier one loaded: before the clock
        load_kernels(sys, explore=self._control_box is not None and
                     s.control_edges is not False and self._explore_consts() is not None,
                     lqr=s.goal_lqr is not False)
        rng = np.random.default_rng(seed)
        cpu0 = time.thread_time()
        termination.start()
        run = self._start(rng)  # a goal funnel asked for is built here: it counts as planning
        if run.best_goal <= prob.goal_tolerance:
            run.goal_node = 0
        while run.goal_node < 0 and not termination(run.iterations):
            if run.exploring and run.explore is not None:
                # the iterations up to the next goal-biased one, compiled
                budget = _BATCH if termination.max_iterations is None else \
                    min(_BATCH, termination.max_iterations - run.iterations)
                if not self._explore(rng, run, budget):
                    continue
                to_goal = True  # the batch ended at a goal-biased iteration: its rest here
            else:
                if s.stall_iterations and \
                        run.iterations - run.last_growth >= s.stall_iterations:
                    run.stalled = True
                    break
                run.iterations += 1
                run.since_growth_nearer += 1
                if run.controls and not run.exploring and \
                        run.since_growth_nearer >= CONTROLS_AFTER:
                    # the learned steering stalls: explore with random controls
                    run.exploring = True
                    run.switched["controls"] = run.iterations
                to_goal = rng.random() < s.goal_bias
            target = prob.sample_goal(rng) if to_goal else \
                rng.uniform(sys.state_low, sys.state_high)
            if to_goal and self._connect(rng, run):
                break
            self._expand(rng, run, target, to_goal)
        if run.directed >= 0:  # the last iteration's expansion, left to a compiled batch
            self._explore(rng, run, 0)
        return self._result(run, time.thread_time() - cpu0, termination.elapsed())

    def _explore(self, rng: np.random.Generator, run: _Run, budget: int) -> bool:
        """Up to ``budget`` iterations compiled (`integrate.explore_jit`): the random-control
        iterations that are not goal-biased, exactly as `solve` runs them (the same draws,
        nodes and counts), after the directed control expansion of the goal-biased iteration
        before them if `_expand` left it here (``run.directed``). Returns True when the last
        iteration drew the goal bias: its goal target, connections and expansion are
        `solve`'s to run. Sets ``run.goal_node`` when a node reached the goal region and
        ``run.stalled`` when the tree stalled."""
        prob, s = self.problem, self.settings
        tree, ex = run.tree, run.explore
        size = tree.n_nodes
        tree.reserve(budget + 1)  # (+ 1: a goal-biased iteration's expansion first)
        points = [index.reserve(budget + 1) for index in self._indices]
        if run.shifts.shape[0] < size + budget + 1:
            run.shifts = _grown(run.shifts, size + budget + 1, 0.0)
        ints = np.array([budget, run.iterations, run.last_growth, s.stall_iterations,
                         ex.longest, self._ball is not None, len(points),
                         len(points) - 1, size, run.directed, max(1, s.control_samples)],
                        dtype=np.int64)
        run.directed = -1
        code, iterations, nodes, traj, starts, node_it, ends, reasons = \
            prob.system.explore_jit(rng, ints, ex.floats, ex.boxes, ex.goal, ex.index_consts,
                                    points[0], points[-1], tree.states, tree.parents,
                                    tree.controls, tree.durations, tree.costs,
                                    tree.max_abs_u, run.shifts, self._input_weight)
        first_it = run.iterations
        run.iterations = int(iterations)
        added = nodes - size
        if added and self._ball is None:  # the user's goal function on the new states
            code, added, ends = self._deferred_goal(run, size, added, traj, starts, node_it,
                                                    code)
            if code == 3:  # the batch ends at that edge's iteration
                run.iterations = int(node_it[added - 1])
                reasons = reasons[: run.iterations - first_it]
        run.since_growth_nearer += run.iterations - first_it
        if added:  # (costates and parameters of new rows are NaN: PlannerData.reserve)
            bounds = starts[: added + 1].tolist()
            tree.trajectories.extend(traj[a:b] for a, b in pairwise(bounds))
            tree.n_nodes = size + added
            its = node_it[:added].tolist()
            run.last_growth = its[-1]
            for it, d in zip(its, ends[:added].tolist(), strict=True):
                if d < run.best_goal:  # as `_expand` records a node nearer the goal
                    run.best_goal, run.since_nearer = d, 0
                    run.since_growth_nearer = run.iterations - it
        for index in self._indices:
            index.commit(size + added)
        reasons = reasons.tolist()
        run.outcomes["added"] += reasons.count(0)
        run.outcomes["state_box"] += reasons.count(1)
        run.outcomes["nonfinite"] += reasons.count(2)
        run.edges_by["control"] += reasons.count(0)
        if code == 3:
            run.goal_node = size + added - 1
        elif code == 2:
            run.stalled = True
        return code == 1

    def _deferred_goal(self, run: _Run, size: int, added: int, traj: np.ndarray,
                       starts: np.ndarray, node_it: np.ndarray, code: int):
        """The goal test of a compiled batch under the user's goal function: one call on
        every new state; the batch is cut at the first edge that reaches the goal region
        (that edge cut at its first state there, as `_control_edge` cuts it). Returns the
        batch's code (3 when cut), how many of its nodes stay and their ends' distances."""
        prob, s = self.problem, self.settings
        n = prob.system.n_states
        first = np.zeros(len(traj), dtype=bool)
        first[starts[:-1]] = True  # each edge's first row is its parent's state
        rows = np.flatnonzero(~first)
        dist = prob.goal_distance(traj[rows])
        hits = np.flatnonzero(dist <= prob.goal_tolerance)
        last = starts[1 : added + 1] - 1  # each edge's last row
        ends = dist[np.searchsorted(rows, last)]
        if not hits.size:
            return code, added, ends
        row = int(rows[hits[0]])
        e = int(np.searchsorted(starts, row, side="right")) - 1  # the edge of that row
        steps = row - int(starts[e])
        node = size + e
        tree = run.tree
        x = traj[row]
        u = tree.controls[node]
        tree.states[node] = x
        tree.durations[node] = steps * s.dt
        tree.costs[node] = steps * s.dt * self._hold_rate(u)
        for index in self._indices:
            index.set(node, x[:n])
        run.shifts[node] = prob.system.wrap_shift(x[None])[0]
        starts[e + 1] = row + 1
        ends = ends[: e + 1].copy()
        ends[e] = dist[hits[0]]
        return 3, e + 1, ends

    def _start(self, rng: np.random.Generator) -> _Run:
        """The state of a new `solve`: the tree at the start, its node indices, the goal
        connections as the settings have them."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        n = sys.n_states
        weight = np.asarray(s.metric_scale, dtype=np.float64)
        # tree nodes in nearest-neighbour structures: candidate parents by plain (weighted)
        # distance, and by distance with angles modulo a turn (extend, the wrapped goal)
        angle_low = np.full(n, np.nan)
        angle_low[list(sys.angle_dims)] = sys.state_low[list(sys.angle_dims)]
        plain = NodeIndex(weight)
        wrapped = NodeIndex(weight, angle_low) if sys.angle_dims else plain
        self._indices = (plain, wrapped) if wrapped is not plain else (plain,)
        for index in self._indices:
            index.add(prob.start)
        # learning-query start of every node: its state shifted by whole turns into the box
        shifts = np.empty((256, n))
        shifts[0] = sys.wrap_shift(prob.start[None])[0]
        # random-control expansions (`_control_edge`): only with a box to draw inputs from
        controls = self._control_box is not None and s.control_edges is not False
        # shooting starts from U's guess: not without learned functions
        can_connect = sys.params_from_costate is not None and self.model is not None
        return _Run(
            explore=self._explore_consts() if controls else None,
            tree=PlannerData(prob.start, sys.n_params, n_inputs=sys.n_inputs), weight=weight,
            plain=plain, wrapped=wrapped, shifts=shifts, lam=np.empty(n),
            z0=np.empty(2 * n + 1), controls=controls,
            exploring=controls and (s.control_edges is True or self.model is None),
            connecting=s.goal_connect is True,
            auto_connect=s.goal_connect is None and can_connect,
            auto_funnel=s.goal_funnel is None and can_connect,
            auto_lqr=s.goal_lqr is None,
            search=self._build_funnel(rng, weight, s.goal_funnel) if s.goal_funnel else None,
            lqr=self._build_lqr() if s.goal_lqr else None,
            best_goal=float(prob.goal_distance(prob.start)[0]))

    def _explore_consts(self) -> _ExploreConsts | None:
        """`_explore`'s constants, or None where its iterations stay in Python: a system
        without compiled kernels, or obstacles (the validity checker is Python)."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        if sys.explore_jit is None or prob.validity:
            return None
        n, m = sys.n_states, sys.n_inputs
        boxes = np.zeros((8, max(n, m)))
        boxes[0, :n], boxes[1, :n] = sys.state_low, sys.state_high
        boxes[2, :n], boxes[3, :n] = self._box
        boxes[4, :m], boxes[5, :m] = self._control_box
        boxes[6, :n] = sys.state_low
        boxes[7, list(sys.angle_dims)] = 1.0
        goal, tol2 = np.zeros((3, n)), 0.0
        if self._ball is not None:
            goal[0], goal[1], goal[2], tol2 = self._ball
        consts = np.array([[index.weight, index._low, index._period,
                            np.isin(np.arange(n), index._angles)] for index in self._indices],
                          dtype=np.float64)
        floats = np.array([s.dt, s.goal_bias, tol2, s.time_weight])
        return _ExploreConsts(self._longest_hold(), floats, boxes, goal, consts)

    def _hold_rate(self, u: np.ndarray) -> float:
        """The running cost w + u^T R u / 2 of a held input ``u`` (random-control and LQR
        edges; `integrate.explore_jit` computes it in the same order)."""
        return self.settings.time_weight + 0.5 * float(u @ self._input_weight @ u)

    def _longest_hold(self) -> int:
        """The most RK4 steps a random-control edge holds its input: the data's longest
        segment."""
        return max(1, round(self.settings.max_duration / self.settings.dt))

    def _connect(self, rng: np.random.Generator, run: _Run) -> bool:
        """A goal-biased iteration's exact connections (shooting, the funnel, the LQR
        connection), switched on here when the tree stalls near the goal; True when one
        reached it."""
        run.since_nearer += 1
        if run.auto_lqr and run.lqr is None and run.since_nearer >= CONNECT_AFTER:
            # (also while random controls explore: where it works, it is what gets the
            # random-control tree into a small goal region)
            run.lqr = self._build_lqr()
            run.switched["lqr"] = run.iterations
        # (not while random controls explore: in the external problems the connections
        # never reached the goal then, and took up to a third of the CPU)
        if run.auto_connect and not run.connecting and not run.exploring \
                and run.since_nearer >= CONNECT_AFTER:
            run.connecting = True
            run.switched["shooting"] = run.iterations
        m = run.tree.n_nodes
        if run.connecting:
            run.tried = _grown(run.tried, m, False)
            before = int(run.tried[:m].sum())
            found = self._connect_goal(run.tree, run.shifts, run.tried, run.weight, run.lam,
                                       run.z0)
            if found is not None:
                run.goal_node, run.connection = self._add_edge(run.tree, *found), "shooting"
                return True
            run.failed_shots += int(run.tried[:m].sum()) - before
            if run.auto_funnel and run.search is None and run.failed_shots >= FUNNEL_AFTER:
                # shooting does not get into the goal: continuation along a funnel
                run.search = self._build_funnel(rng, run.weight, AUTO_FUNNEL)
                run.switched["funnel"] = run.iterations
        if run.search is not None:
            found = self._connect_funnel(run.tree, run.search, run.lam, run.z0)
            if found is not None:
                run.goal_node, run.connection = self._add_edge(run.tree, *found), "funnel"
                return True
        # last, so that the tree is the one without it until it connects
        if run.lqr is not None and run.lqr.lqr is not None:
            found = self._connect_lqr(run.tree, run.lqr)
            if found is not None:
                parent, chain = found
                for edge in chain:
                    parent = self._add_node(run, parent, edge)
                run.goal_node, run.connection = parent, "lqr"
                return True
        return False

    def _build_lqr(self) -> _LQRSearch:
        """The LQR connection's search state: the controller about the goal's equilibrium, or
        none and why (`lqr.build_goal_lqr`); built inside the timed region."""
        built = build_goal_lqr(self.problem, self.settings.dt,
                               getattr(self, "_input_weight", None))
        return _LQRSearch(None, built) if isinstance(built, str) else _LQRSearch(built)

    def _connect_lqr(self, tree: PlannerData, search: _LQRSearch):
        """The LQR closed loop to the goal from the untried node with the least Lyapunov
        value, as a chain of constant-input edges (consecutive equal inputs, e.g. saturated,
        merged into one); (node, edges) or None when it does not reach the goal region
        within ``funnel_duration``, leaves the constraints, meets an obstacle or leaves the
        loop's basin (`GoalLQR.run`). Once a loop runs out of time, only nodes with a lower
        value than its start are tried."""
        lqr = search.lqr
        m = tree.n_nodes
        search.grow(m)
        if search.queried < m:
            search.value[search.queried : m] = lqr.value(tree.states[search.queried : m])
            search.queried = m
        value = np.where(search.tried[:m], np.inf, search.value[:m])
        node = int(np.argmin(value))
        if not value[node] < search.ceiling:
            return None
        search.tried[node] = True
        search.tries += 1
        chain, end = self._lqr_chain(lqr, tree.states[node])
        if end == "timeout":
            search.ceiling = float(value[node])
        return None if chain is None else (node, chain)

    def _lqr_chain(self, lqr: GoalLQR, x0: np.ndarray) -> tuple[list[Edge] | None, str]:
        """The LQR closed loop from ``x0`` as a chain of constant-input edges (consecutive
        equal inputs merged into one) if it reaches the goal region within
        ``funnel_duration``, and how the loop ended (`GoalLQR.run`)."""
        prob, s = self.problem, self.settings
        out = lqr.run(x0, max(1, round(s.funnel_duration / s.dt)), self._box,
                      self._goal_mask, prob.validity if prob.validity else None)
        if not out.reached:
            return None, out.end
        us = out.inputs
        breaks = [0, *np.flatnonzero(np.any(us[1:] != us[:-1], axis=1)) + 1, len(us)]
        chain = []
        for a, b in pairwise(breaks):
            u = us[a].copy()
            rate = self._hold_rate(u)
            last = b == len(us)
            chain.append(Edge(out.states[a : b + 1].copy(), b - a, (b - a) * s.dt * rate,
                              float(np.abs(u).max()), last, control=u,
                              end_distance=float(prob.goal_distance(out.states[b])[0])
                              if last else None))
        return chain, out.end

    def _expand(self, rng: np.random.Generator, run: _Run, target: np.ndarray,
                to_goal: bool) -> None:
        """One expansion toward ``target``: the learned steering, or while exploring a random
        control (also where the learned steering adds nothing); its outcome recorded."""
        prob, s = self.problem, self.settings
        n = prob.system.n_states
        states = run.tree.states[: run.tree.n_nodes]
        nearest = -1  # the node nearest the target (weighted, angles modulo a turn)
        if run.exploring and self.model is not None and to_goal:
            # the learned steering for goal targets within the data's reach, where U has
            # seen segments that long
            nearest, _, dist = self._nearest(states, target, run.weight, run.wrapped)
        if run.exploring and (nearest < 0 or dist > self.settings.connect_reach):
            parent, edge, kind = -1, None, "control"
        else:
            parent, edge, kind = self._learned_iteration(
                rng, states, target, to_goal, run.weight, run.plain, run.wrapped, run.shifts,
                run.lam, run.z0, bool(s.extend_distance), s.max_candidates is not None,
                self._reach * self._reach)
        if edge is None and run.exploring:
            parent = nearest if nearest >= 0 else int(run.wrapped.nearest(target, 1)[0])
            if to_goal and run.explore is not None and self._ball is not None:
                run.directed = parent  # the next compiled batch begins with it
                return
            edge = self._control_edge(rng, states[parent], to_goal)
            kind = "control"
        if edge is None:
            run.outcomes[self._rejected] += 1
            return
        run.outcomes["added"] += 1
        run.edges_by[kind] += 1
        run.last_growth = run.iterations
        node = self._add_node(run, parent, edge)
        end = edge.traj[-1:, :n]
        d_goal = edge.end_distance if edge.end_distance is not None else \
            float(prob.goal_distance(end)[0])
        if d_goal < run.best_goal:
            run.best_goal, run.since_nearer, run.since_growth_nearer = d_goal, 0, 0
        if edge.hit:
            run.goal_node = node

    def _add_node(self, run: _Run, parent: int, edge: Edge) -> int:
        """`_add_edge` for a node the tree grows from: its learning-query shift recorded."""
        node = self._add_edge(run.tree, parent, edge)
        if node == run.shifts.shape[0]:
            run.shifts = np.concatenate([run.shifts, np.empty_like(run.shifts)])
        run.shifts[node] = self.problem.system.wrap_shift(
            edge.traj[-1:, : self.problem.system.n_states])[0]
        return node

    def _result(self, run: _Run, cpu: float, wall: float) -> Plan:
        """The plan: the path to the goal node, else to the node nearest the goal region,
        with what became of the iterations and, unsolved, why."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        tree = run.tree
        if run.goal_node >= 0:
            status, end = "exact", run.goal_node
        else:
            dist = prob.goal_distance(tree.states[: tree.n_nodes])
            end = int(np.argmin(dist))
            status = "approximate" if end != 0 else "timeout"
        input_low, input_high = sys.input_limits() if sys.input_limited else (None, None)
        search = run.search
        lqr = run.lqr
        # the LQR connection: its tries, or why it is off (also in the diagnosis)
        lqr_extra = {} if lqr is None else {"goal_lqr": {"tries": lqr.tries} if lqr.lqr
                                                     else {"off": lqr.off}}
        diagnosis = None if run.goal_node >= 0 else diagnose(
            run.outcomes, run.stalled, tree.n_nodes, prob.u_max is not None,
            (float(prob.goal_distance(prob.start)[0]), float(dist[end])))
        if diagnosis is not None and lqr is not None and lqr.lqr is None:
            diagnosis += f"; LQR goal connection off: {lqr.off}"
        return Plan(
            system=sys.name, start=prob.start, goal=prob.goal,
            goal_tolerance=prob.goal_tolerance, time_weight=s.time_weight, dt=s.dt,
            status=status, planning_time_s=wall, planning_cpu_s=cpu,
            iterations=run.iterations, tree=tree, path_nodes=tree.path_to(end),
            u_max=prob.u_max, input_low=input_low, input_high=input_high,
            obstacles=[o.to_dict() for o in prob.validity.obstacles],
            goal_angles=prob.goal_angles, goal_test=prob.goal_test,
            end_goal_distance=self._end_goal_distance(tree.states[end]),
            # which edge reached the goal: the learned steering's, or a connection's
            extra={**({"goal_connected": run.connection is not None,
                       "connection": run.connection,
                       **({"funnel_states": len(search.funnel)} if search else {})}
                      if run.connecting or search or lqr else {}),
                   **lqr_extra,
                   **({"connections_switched_on": run.switched} if run.switched else {}),
                   "outcomes": run.outcomes, "stalled": run.stalled,
                   **({"edges_by": run.edges_by} if run.controls else {}),
                   **({} if diagnosis is None else {"diagnosis": diagnosis})},
        )


def load_kernels(system: System, explore: bool = False, lqr: bool = False) -> None:
    """Load the system's compiled kernels that a plan calls and this process has not loaded
    yet (numba's on-disk cache; compiled and cached when absent, once per system and
    machine), so that no plan spends its time limit, or its CPU figure, on them.

    `RRTCoLearn.solve` calls it before its clock starts, with what that solve may call: the
    compiled random-control iterations (``explore``: `integrate.explore_jit`, about 9 s to
    compile) and the LQR goal connection's loop (``lqr``: `integrate.closed_loop_jit`).
    `pipeline` runs a throwaway solve when a model is fitted or loaded, so the first
    compiled call of a process (it also initialises numba's compiler, about 0.2 s) and the
    cache loads count as the model's load, not as the first plan's. Each kernel
    runs once, on a state and parameters in the middle of their boxes and for zero or one
    step, through the function the planner calls it by, so the very signatures a plan uses
    are loaded; a kernel that has a signature already is skipped (microseconds).
    """
    from rrtcolearn.integrate import propagate, rollout, rollout_batch

    n, m = system.n_states, system.n_inputs
    x = np.ascontiguousarray((system.state_low + system.state_high) / 2, dtype=np.float64)
    p = np.ascontiguousarray((system.param_low + system.param_high) / 2, dtype=np.float64)
    z = np.concatenate([x, np.zeros(n + 1)])
    inf = np.full(n, np.inf)
    calls = [
        (system.costate_from_params_jit,
         lambda: system.costate_from_params_jit(x, p, 1.0, np.empty(n))),
        (system.rollout_jit, lambda: rollout(system, z, 1.0, 0.01, 0)),
        (system.input_max_abs_jit, lambda: system.input_max_abs_jit(z)),
        (system.propagate_jit,
         lambda: propagate(system, x, np.zeros(m), 0.01, 0, -inf, inf)),
        (system.rollout_batch_jit,
         lambda: rollout_batch(system, z[None], 1.0, 0.01, 1, 1.0, 1.0, n)),
        (system.rollout_draws_jit,
         lambda: rollout_draws(system, x, np.zeros((1, n)), np.zeros(1, np.int64), 1.0, 0.01,
                               -inf, inf, None)),
    ]
    if explore:
        calls.append((system.explore_jit, lambda: _load_explore(system)))
    if lqr:  # the argument types `lqr.GoalLQR.run` passes
        calls.append((system.closed_loop_jit, lambda: system.closed_loop_jit(
            x, x.copy(), np.zeros(m), np.zeros((m, n)), np.zeros((n, n)), -np.ones(m),
            np.ones(m), np.zeros(n, bool), 0.01, 0, -inf, inf)))
    for kernel, call in calls:
        if kernel is None or getattr(kernel, "signatures", None):
            continue  # no compiled kernel (a system built by hand), or loaded already
        try:
            call()
        except Exception:  # loading is what counts, not the outcome of the call
            pass


def _load_explore(system: System) -> None:
    """`integrate.explore_jit` called for no iteration, through `RRTCoLearn._explore` (so
    with the argument types a plan passes: one signature)."""
    x = (system.state_low + system.state_high) / 2
    planner = RRTCoLearn(PlanningProblem.create(system, x, x, 1.0), None,
                         PlannerSettings(control_edges=True))
    rng = np.random.default_rng(0)
    planner._explore(rng, planner._start(rng), 0)

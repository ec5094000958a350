"""Tracking a plan: time-varying LQR about its trajectory, and closed-loop rollouts.

Why: a plan is an open-loop trajectory. The swing-ups ride unstable equilibria and their
input limits, so a robot, or a simulator whose parameters differ a little from the model,
drifts off it; the practice that makes such plans usable is to track them with time-varying
LQR about the nominal (Drake's ``FiniteHorizonLinearQuadraticRegulator``; LQR-trees).

What, for any `System` and any plan (nothing here depends on a system's name):

* the nominal: the plan's path re-simulated edge by edge at the plan's step (the integration
  `evaluate.sample_path` exports), with the input of every RK4 stage of every step: within an
  extremal the optimal control u*(x, lambda) at the stage's state and costate, within a
  random-control edge its held input. On the model, replaying these stage inputs reproduces
  the plan to rounding;
* the linearisation: the RK4 step map of the planner's own integration under a held input,
  at every sample (`planning.lqr.step_jacobians`), A_k (n, n) and B_k (n, m);
* the weights: Bryson's rule from the problem's boxes, as the goal LQR states it
  (`planning.lqr`): Q_ii = dt / h_i^2 with h_i the state constraint box's half-width (an
  angle's: half a turn), R_jj = dt / g_j^2 with g_j the input box's half-width (the running
  cost's R_jj where an input has no finite limit), or R from the room the nominal leaves
  (`input_room_weights`: g_j the distance from the nominal input to the bound it pushes
  toward, time-varying), Q multiplied by the factor of `LADDER`: the rule and factor
  (`INPUT_RULES` x `LADDER`) a self-test on the plan's own model picks: with every input 20%
  weaker than modelled and the model's clock as it is, 5% and 10% slower (x' = s f(x, 0.8
  u), `SELF_TEST`; a margin for a robot that is heavier or weaker than its model, which the
  user does not have), process noise and a start error, the pair whose runs end within
  twice the goal tolerance most often over the three, ties to the smallest geometric mean
  of their median final errors. Bryson's rule alone is soft for a tolerance well under the
  boxes (0.1 against half a turn); stiffer gains saturate a plan that rides its input bound and the
  clipped loop can go unstable: the self-test sees both, on the model. A heavier or weaker
  robot needs more input where the plan pushes hard, in the direction it pushes: the room
  rule keeps the corrections out of the steps that leave little room;
* the terminal cost: the goal test's own squared distance, P_N = diag(w^2) (w the goal
  weights; `terminal_cost`), since the goal is judged on the end state's distance alone;
* the gains: the discrete Riccati recursion backwards, K_k = (R + B_k' P B_k)^-1 B_k' P A_k,
  P <- Q + A_k' P (A_k - B_k K_k);
* the law: u = clip(u_nom - K_k (x_k - x_nom,k)) into the input box, the correction computed
  at the start of each step and held over it (a digital controller at the plan's step).

`rollouts` simulates N runs open-loop (the nominal inputs alone) and tracked on the model or
on another system with the same states and inputs (the "truth"), with process noise and an
error of the start state, all drawn from one seeded generator (the same draws for both),
and `summarise` gives the figures `rrtcolearn track` prints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rrtcolearn.errors import ConfigError
from rrtcolearn.evaluate import edge_trajectory, plan_problem
from rrtcolearn.planning.lqr import bryson_weights, input_box, step_jacobians
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.systems.base import System

__all__ = ["INPUT_RULES", "LADDER", "ROOM_FLOOR", "SELF_TEST", "Nominal", "Rollouts",
           "TrackingController", "check_truth", "input_box", "input_room_weights",
           "nominal_trajectory", "riccati_gains", "rollouts", "summarise", "terminal_cost",
           "tracking_weights"]

LADDER = (1.0, 10.0, 100.0, 1000.0, 10000.0)
"""The multiples of Bryson's Q the self-test chooses among (`TrackingController.build`)."""
INPUT_RULES = ("box", "room")
"""The input weights the self-test chooses among, with each factor of `LADDER`: Bryson's rule
from the input box ("box", `tracking_weights`) and from the room the nominal input leaves to
the bound it pushes toward ("room", `input_room_weights`)."""
ROOM_FLOOR = 0.3
"""The least room `input_room_weights` counts, as a fraction of the input box's half-width
(where the nominal rides its bound; 0.1 tracks the table's plans alike, docs/tracking.md)."""
SELF_TEST = {"runs": 20, "input_scale": 0.8, "clocks": (1.0, 0.95, 0.9), "noise": 1e-3,
             "start_error": 0.01, "seed": 0}
"""The self-test's rollouts on the plan's model: their number per perturbed model, the factor
on every input (0.8: the inputs act 20% weaker than modelled; at 0.9 the self-test cannot
tell the cart-pole's good factors from its bad ones under `terminal_cost`), the factors on
the model's clock (x' = s f(x, u): 5% and 10% slower besides as modelled; a mechanical
system with larger masses and lengths moves as its model on a slower clock, and on the
model's clock alone the self-test ranks the acrobot's Q x 100 above x 10, docs/tracking.md),
noise and start error (`rollouts`), seed."""


@dataclass(frozen=True)
class Nominal:
    """A plan's trajectory at its step ``dt``: ``t`` (N+1,), ``state`` (N+1, n) (an edge's
    first state where edges meet), ``input`` (N+1, m) (the input at each sample, the next
    edge's where edges meet; the last the path's final input) and ``stage_inputs`` (N, 4, m),
    the input at each RK4 stage of each step."""

    t: np.ndarray
    state: np.ndarray
    input: np.ndarray
    stage_inputs: np.ndarray
    dt: float

    @property
    def steps(self) -> int:
        return len(self.stage_inputs)


def _stage_inputs(system: System, traj, w: float, dt: float) -> np.ndarray:
    """(k, 4, m) the inputs the state+costate RK4 (`integrate._rk4_step`) used at its four
    stages along an extremal ``traj`` (k+1 rows of z = (x, lambda, cost))."""
    n = system.n_states
    d = traj.shape[1]
    k1, k2, k3 = np.empty(d), np.empty(d), np.empty(d)
    stages = np.empty((len(traj) - 1, 4, d))
    for k, z in enumerate(traj[:-1]):
        system.rhs(z, w, k1)
        z2 = z + 0.5 * dt * k1
        system.rhs(z2, w, k2)
        z3 = z + 0.5 * dt * k2
        system.rhs(z3, w, k3)
        stages[k] = (z, z2, z3, z + dt * k3)
    flat = stages.reshape(-1, d)
    u = system.optimal_control(flat[:, :n], flat[:, n : 2 * n])
    return np.asarray(u, dtype=np.float64).reshape(len(traj) - 1, 4, -1)


def nominal_trajectory(system: System, plan) -> Nominal:
    """The `Nominal` of a plan (a `Plan` or a plan file's content) on ``system``."""
    from rrtcolearn.integrate import rollout

    d = plan if isinstance(plan, dict) else plan.to_dict()
    edges, w, dt = d["path"], float(d["time_weight"]), float(d["dt"])
    if not edges:
        raise ConfigError("the plan has no path to track")
    n, m = system.n_states, system.n_inputs
    states, inputs, stages = [], [], []
    for e in edges:
        steps = max(1, round(e["duration"] / dt))
        if e.get("control") is not None:
            traj = edge_trajectory(system, e, w, dt)
            u = np.broadcast_to(np.asarray(e["control"], dtype=np.float64), (steps, 4, m))
            states.append(traj.states[:-1])
            inputs.append(np.asarray(traj.inputs)[:-1])
            stages.append(u)
        else:
            z = rollout(system, np.r_[e["from"], e["costate"], 0.0], w, dt, steps)
            stages.append(_stage_inputs(system, z, w, dt))
            states.append(z[:-1, :n])
            inputs.append(stages[-1][:, 0])
    final = edge_trajectory(system, edges[-1], w, dt)
    state = np.concatenate([*states, final.states[-1:]])
    inp = np.concatenate([*inputs, np.asarray(final.inputs)[-1:]])
    return Nominal(np.arange(len(state)) * dt, state, inp, np.concatenate(stages), dt)


def _input_weight(system: System) -> np.ndarray:
    """(m,) the diagonal of the running cost's R, read off the Hamiltonian with a zero costate
    (H = w + u' R u / 2)."""
    m, n = system.n_inputs, system.n_states
    x = np.zeros((m, n))
    h = system.hamiltonian(x, np.zeros((m, n)), np.eye(m), 0.0)
    return 2.0 * np.asarray(h, dtype=np.float64)


def tracking_weights(problem: PlanningProblem, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(Q (n, n), R (m, m)) by Bryson's rule from the problem's boxes, as the goal LQR
    weighs them (`planning.lqr.bryson_weights`), with the running cost's own R."""
    return bryson_weights(problem, dt, _input_weight(problem.system))


def input_room_weights(problem: PlanningProblem, nominal: Nominal, dt: float) -> np.ndarray:
    """(N, m, m) R_k by Bryson's rule on the room each step's nominal input leaves: R_k,jj =
    dt / r_kj^2, r_kj the distance from the step's stage inputs to the bound they push toward
    (the upper where above the box's centre), the least over the four stages, at least
    `ROOM_FLOOR` x the half-width; the running cost's R_jj where an input has no finite limit.
    Why: a robot heavier or weaker than its model needs more input where the plan pushes, in
    the direction it pushes, so a correction asked for there is clipped; with this R the
    regulator corrects where the plan leaves room (the cart-pole row, docs/tracking.md)."""
    low, high = input_box(problem)
    R_box = np.diag(tracking_weights(problem, dt)[1])
    u = nominal.stage_inputs
    with np.errstate(invalid="ignore"):
        half, mid = 0.5 * (high - low), 0.5 * (high + low)
        room = np.where(u >= mid, high - u, u - low).min(axis=1)
        room = np.maximum(room, ROOM_FLOOR * half)
    r = np.where(np.isfinite(half), dt / room**2, R_box)
    return r[:, :, None] * np.eye(len(R_box))


def terminal_cost(problem: PlanningProblem, dt: float) -> tuple[np.ndarray, str]:
    """(P_N (n, n), what it is): the weight of the end state's deviation from the nominal's
    end, the goal test's own squared distance diag(w^2) (w the goal weights, 1 each
    without). Why: "reached" is the end state's goal distance, so the recursion weighs that
    and nothing else at the end. The goal LQR's infinite-horizon P (the terminal cost
    before) weighs the upright's unstable mode alone (the acrobot's: eigenvalues 70 and
    4e-4 to 0.045) and left the end state's spread in the other directions unchecked
    (docs/tracking.md). A goal function of one's own has no weights to read: diag(1 / h_i^2),
    the running weight of one second."""
    if problem.goal_fn is not None:
        return tracking_weights(problem, dt)[0] / dt, "diag(1/h^2) (a goal function)"
    w = np.ones(problem.system.n_states) if problem.goal_weights is None else \
        np.asarray(problem.goal_weights, dtype=np.float64)
    return np.diag(w**2), "diag(w^2), the goal test's squared distance"


def riccati_gains(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray,
                  P_final: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The finite-horizon discrete Riccati recursion backwards over A (N, n, n), B (N, n, m),
    R (m, m) or one per step (N, m, m): gains K (N, m, n) and cost-to-go matrices P (N+1, n,
    n), P[N] = ``P_final``."""
    N = len(A)
    K = np.empty((N, B.shape[2], A.shape[1]))
    P = np.empty((N + 1, *A.shape[1:]))
    P[N] = P_final
    for k in range(N - 1, -1, -1):
        a, b, p = A[k], B[k], P[k + 1]
        bp = b.T @ p
        K[k] = np.linalg.solve((R[k] if R.ndim == 3 else R) + bp @ b, bp @ a)
        nxt = Q + a.T @ p @ (a - b @ K[k])
        P[k] = 0.5 * (nxt + nxt.T)
    return K, P


@dataclass(frozen=True)
class TrackingController:
    """Time-varying LQR about a plan's nominal (module docstring); `build` makes it.

    ``K`` (N, m, n) the gain of each step, ``P`` (N+1, n, n) the cost-to-go matrices,
    ``u_low``/``u_high`` (m,) the clipping box, ``terminal`` how P[N] was chosen,
    ``state_weight`` the factor on Bryson's Q the gains were computed with, ``input_rule``
    the input weights' rule (`INPUT_RULES`)."""

    problem: PlanningProblem
    nominal: Nominal
    K: np.ndarray
    P: np.ndarray
    u_low: np.ndarray
    u_high: np.ndarray
    terminal: str
    state_weight: float = 1.0
    input_rule: str = "box"

    @classmethod
    def build(cls, system: System, plan, problem: PlanningProblem | None = None, *,
              state_weight: float = 1.0, ladder: tuple[float, ...] = LADDER,
              input_rules: tuple[str, ...] = INPUT_RULES) -> TrackingController:
        """The controller of a plan (a `Plan` or a plan file's content) on ``system`` (the
        plan's model); ``problem`` defaults to the one the plan records
        (`evaluate.plan_problem`). Q is Bryson's times the factor of ``ladder``, R by the rule
        of ``input_rules``, the pair the model's self-test picks (module docstring;
        ``ladder=(1.0,), input_rules=("box",)``: Bryson's rule as the goal LQR uses it), Q
        times ``state_weight`` (larger tracks more stiffly for the same inputs)."""
        problem = plan_problem(system, plan) if problem is None else problem
        nominal = nominal_trajectory(system, plan)
        dt = nominal.dt
        jac = [step_jacobians(system, x, u, dt)
               for x, u in zip(nominal.state[:-1], nominal.input[:-1], strict=True)]
        A = np.array([a for a, _ in jac])
        B = np.array([b for _, b in jac])
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
            raise ConfigError("the linearisation along the plan is not finite")
        Q, R_box = tracking_weights(problem, dt)
        P_final, terminal = terminal_cost(problem, dt)
        low, high = input_box(problem)
        unknown = set(input_rules) - set(INPUT_RULES)
        if unknown or not input_rules:
            raise ConfigError(f"input rules {sorted(unknown)}: give some of {INPUT_RULES}")
        rules = {"box": R_box, "room": input_room_weights(problem, nominal, dt)}
        if "box" in input_rules and np.all(rules["room"] == R_box):
            input_rules = ("box",)  # no finite input limit: the rules agree
        candidates = [(rule, factor) for rule in input_rules for factor in ladder]
        best, best_score = None, None
        for rule, factor in candidates:
            w = factor * state_weight
            K, P = riccati_gains(A, B, w * Q, rules[rule], P_final)
            c = cls(problem, nominal, K, P, low, high, terminal, float(w), rule)
            if len(candidates) == 1:
                return c
            score = _self_test(c)
            if best_score is None or score < best_score:
                best, best_score = c, score
        return best

    def deviation(self, x: np.ndarray, k: int) -> np.ndarray:
        """(N, n) x - the nominal state of sample ``k``, angles the short way round."""
        e = np.atleast_2d(x) - self.nominal.state[k]
        angles = list(self.problem.system.angle_dims)
        e[:, angles] = np.mod(e[:, angles] + np.pi, 2.0 * np.pi) - np.pi
        return e

    def step_index(self, t: float) -> int:
        """The step whose gain applies at time ``t`` (the last one after the plan's end)."""
        k = int(np.floor(t / self.nominal.dt + 1e-9))
        return min(max(k, 0), self.nominal.steps - 1)

    def input(self, t: float, x: np.ndarray) -> np.ndarray:
        """(m,) the input at time ``t`` (s, from the plan's start) in state ``x`` (n,): the
        nominal input at ``t`` (linear between samples) corrected by the step's gain against
        the nominal state at ``t``, clipped into the input box."""
        nom = self.nominal
        tt = min(max(float(t), 0.0), float(nom.t[-1]))
        x_nom = np.array([np.interp(tt, nom.t, c) for c in nom.state.T])
        u_nom = np.array([np.interp(tt, nom.t, c) for c in nom.input.T])
        e = np.asarray(x, dtype=np.float64) - x_nom
        angles = list(self.problem.system.angle_dims)
        e[angles] = np.mod(e[angles] + np.pi, 2.0 * np.pi) - np.pi
        return np.clip(u_nom - self.K[self.step_index(tt)] @ e, self.u_low, self.u_high)


def check_truth(model: System, truth: System) -> None:
    """ConfigError (one line) unless ``truth`` has the model's states and inputs (names,
    number and angle coordinates): a true system differs in its parameters only."""
    for what, a, b in (("states", model.state_names, truth.state_names),
                       ("inputs", model.input_names, truth.input_names),
                       ("angle coordinates", model.angle_dims, truth.angle_dims)):
        if tuple(a) != tuple(b):
            raise ConfigError(f"the true system {truth.name!r} has {what} {list(b)}, the "
                              f"plan's system {model.name!r} {list(a)}: give a system with the "
                              "same states and inputs")


@dataclass(frozen=True)
class Rollouts:
    """N simulated runs of a plan: ``states`` (N, K+1, n) and ``inputs`` (N, K, 4, m) (the
    input at each RK4 stage), open-loop or tracked."""

    states: np.ndarray
    inputs: np.ndarray
    tracked: bool


def _rk4_batch(f, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """One RK4 step of x' = f(x, u) for a batch x (N, n), with the stage inputs u (N, 4, m)."""
    k1 = f(x, u[:, 0])
    k2 = f(x + 0.5 * dt * k1, u[:, 1])
    k3 = f(x + 0.5 * dt * k2, u[:, 2])
    k4 = f(x + dt * k3, u[:, 3])
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rollouts(controller: TrackingController, n: int = 100, *, truth: System | None = None,
             noise: float = 0.0, start_error: float = 0.0, seed: int = 0
             ) -> tuple[Rollouts, Rollouts]:
    """(open-loop, tracked) runs of the controller's plan, ``n`` of each, on ``truth``
    (default the model; `check_truth`), seeded. ``start_error``: each start coordinate off
    the plan's by a uniform draw in +- that fraction of the system's box width (an angle's: a
    turn); ``noise``: after every step each coordinate moves by a normal draw of standard
    deviation ``noise`` x its box width x sqrt(dt / 1 s) (a Wiener process). Both kinds of
    runs see the same draws."""
    model = controller.problem.system
    truth = model if truth is None else truth
    check_truth(model, truth)
    nom = controller.nominal
    width = np.asarray(model.state_high, float) - np.asarray(model.state_low, float)
    width[list(model.angle_dims)] = 2.0 * np.pi
    rng = np.random.default_rng(seed)
    x0 = nom.state[0] + rng.uniform(-1.0, 1.0, (n, model.n_states)) * start_error * width
    kicks = rng.standard_normal((nom.steps, n, model.n_states)) * (
        noise * width * np.sqrt(nom.dt))
    out = []
    for tracked in (False, True):
        states = np.empty((n, nom.steps + 1, model.n_states))
        inputs = np.empty((n, nom.steps, 4, model.n_inputs))
        states[:, 0] = x0
        x = x0.copy()
        with np.errstate(all="ignore"):
            for k in range(nom.steps):
                u = np.broadcast_to(nom.stage_inputs[k], (n, 4, model.n_inputs))
                if tracked:
                    du = -controller.deviation(x, k) @ controller.K[k].T
                    u = np.clip(u + du[:, None, :], controller.u_low, controller.u_high)
                inputs[:, k] = u
                x = _rk4_batch(truth.dynamics, x, u, nom.dt)
                if noise:
                    x = x + kicks[k]
                states[:, k + 1] = x
        out.append(Rollouts(states, inputs, tracked))
    return out[0], out[1]


class _Perturbed:
    """The plan's model with every input scaled by ``scale`` and its clock by ``clock``:
    x' = clock f(x, scale u) (a self-test's truth)."""

    def __init__(self, system: System, scale: float, clock: float) -> None:
        self._system, self._scale, self._clock = system, scale, clock

    def __getattr__(self, name: str):
        return getattr(self._system, name)

    def dynamics(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self._clock * self._system.dynamics(x, self._scale * u)


def _self_test(controller: TrackingController) -> tuple[float, float]:
    """The controller's score on its own model perturbed (`SELF_TEST`: weaker inputs, each
    clock), smaller is better: (- the mean share of runs ending within twice the goal
    tolerance, the geometric mean of the median final goal distances)."""
    t = SELF_TEST
    shares, medians = [], []
    for clock in t["clocks"]:
        truth = _Perturbed(controller.problem.system, t["input_scale"], clock)
        _, runs = rollouts(controller, t["runs"], truth=truth, noise=t["noise"],
                           start_error=t["start_error"], seed=t["seed"])
        s = summarise(controller, runs)
        shares.append(s["reached_2x"])
        medians.append(s["final_error_median"])
    with np.errstate(divide="ignore"):
        return -float(np.mean(shares)), float(np.exp(np.mean(np.log(medians))))


def summarise(controller: TrackingController, runs: Rollouts) -> dict:
    """The figures of a set of runs: shares that reach the goal region at the plan's end
    (``reached``) and within twice its tolerance (``reached_2x``), median and largest final
    goal distance, median and largest deviation from the nominal (Euclidean, angles the
    short way round), the share of stage inputs at the input box's bounds
    (``time_at_limit``), whether every input lies in the box, and how many runs enter an
    obstacle (``obstacle_entries``) or leave the state constraints (``constraint_exits``)."""
    problem, nom = controller.problem, controller.nominal
    n = len(runs.states)
    flat = runs.states.reshape(-1, runs.states.shape[2])
    finite = np.isfinite(flat).all(axis=1)
    dev = np.full(len(flat), np.inf)
    steps = np.tile(np.arange(nom.steps + 1), n)
    with np.errstate(all="ignore"):
        for k in range(nom.steps + 1):  # per sample: its nominal state
            rows = np.flatnonzero(steps == k)
            dev[rows] = np.linalg.norm(controller.deviation(flat[rows], k), axis=1)
    dev[~finite] = np.inf
    largest_dev = dev.reshape(n, -1).max(axis=1)
    final = runs.states[:, -1]
    dist = np.full(n, np.inf)
    ok = np.isfinite(final).all(axis=1)
    if ok.any():
        dist[ok] = problem.goal_distance(final[ok])
    tol = problem.goal_tolerance
    inside = np.ones(len(flat), bool)
    inside[finite] = problem.within_bounds(flat[finite])
    inside &= finite
    in_obstacle = np.zeros(len(flat), bool)
    if problem.validity and finite.any():
        in_obstacle[finite] = ~problem.validity(flat[finite])
    u = runs.inputs
    low, high = controller.u_low, controller.u_high
    at_limit = (np.isclose(u, low) | np.isclose(u, high)).any(axis=-1)
    return {
        "runs": n,
        "reached": float(np.mean(dist <= tol)),
        "reached_2x": float(np.mean(dist <= 2.0 * tol)),
        "final_error_median": float(np.median(dist)),
        "final_error_max": float(dist.max()),
        "deviation_median": float(np.median(largest_dev)),
        "deviation_max": float(largest_dev.max()),
        "time_at_limit": float(at_limit.mean()),
        "inputs_in_box": bool(np.all((u >= low - 1e-12) & (u <= high + 1e-12))),
        "obstacle_entries": int(in_obstacle.reshape(n, -1).any(axis=1).sum()),
        "constraint_exits": int((~inside).reshape(n, -1).any(axis=1).sum()),
    }

"""Held-out evaluation of the learned functions (paper Experiments: steering MSE), the
re-simulation of a plan's path from its start, and the check that a plan (file) is what it
claims (`check_plan`)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, NoReturn

import numpy as np

from rrtcolearn.data.dataset import Dataset
from rrtcolearn.errors import ArtefactError
from rrtcolearn.integrate import propagate, rollout
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.planning.lqr import input_box
from rrtcolearn.systems.base import System

if TYPE_CHECKING:
    from rrtcolearn.planning.problem import PlanningProblem


@dataclass(frozen=True)
class HeldOutErrors:
    """Per-query errors on held-out (x0, x1) pairs that V accepts."""

    steer_mse: np.ndarray  # (Q,) mean over coordinates of the squared error to x1
    cost_rel_error: np.ndarray  # (Q,) |J_hat - J| / J
    param_error: np.ndarray  # (Q,) error of the costate parameters (circular ones on the circle)
    duration_error: np.ndarray  # (Q,) |T_hat - T|
    accepted_fraction: float  # share of the sampled held-out queries V accepted


def held_out_errors(system: System, functions: LearnedFunctions, held_out: Dataset, *,
                    n_queries: int = 1000, time_weight: float = 1.0, dt: float = 0.01,
                    seed: int = 0) -> HeldOutErrors:
    """Simulate from x0 with the *predicted*, unperturbed steering parameters.

    The paper's 0.11 is the median of this error; queries whose predicted costate does not
    exist (negative square root) count as failures with an infinite error.
    """
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(held_out))
    X = held_out.inputs[order]
    cost, steer, valid = functions.query(X)
    accepted = np.flatnonzero(valid)
    pick = accepted[:n_queries]
    n = system.n_states
    landed = landing_states(system, X[pick, :n], steer[pick], time_weight, dt)
    mse = np.mean((landed - X[pick, n:]) ** 2, axis=1)
    mse[~np.isfinite(mse)] = np.inf
    true_cost = held_out.cost[order][pick]
    true_params = held_out.params[order][pick]
    diff = np.abs(steer[pick, :-1] - true_params)
    period = system.param_high - system.param_low
    circ = np.asarray(system.param_circular, dtype=bool)
    diff[:, circ] = np.minimum(diff[:, circ], period[circ] - diff[:, circ])
    return HeldOutErrors(mse, np.abs(cost[pick] - true_cost) / true_cost,
                         np.linalg.norm(diff, axis=1),
                         np.abs(steer[pick, -1] - held_out.duration[order][pick]),
                         len(accepted) / len(X))


def landing_states(system: System, x0: np.ndarray, steer: np.ndarray, time_weight: float,
                   dt: float) -> np.ndarray:
    """Where U's unperturbed steering lands: the end states (Q, n) of the extremals from
    ``x0`` (Q, n) with the parameters and durations ``steer`` (Q, k+1); NaN rows where the
    parameters give no costate on H* = 0. The one rollout behind the held-out steering
    error and the co-learning loop's hit rate (`data.colearn`)."""
    n = system.n_states
    out = np.full((len(x0), n), np.nan)
    for i in range(len(x0)):  # one rollout per query: the compiled kernel does the work
        lam, ok = system.costate_from_params(x0[i : i + 1], steer[i : i + 1, :-1], time_weight)
        if not ok[0]:
            continue
        steps = max(1, round(steer[i, -1] / dt))
        out[i] = rollout(system, np.r_[x0[i], lam[0], 0.0], time_weight, dt, steps)[-1, :n]
    return out


@dataclass(frozen=True)
class EdgeTrajectory:
    """One plan edge re-integrated at the plan's step: states (k+1, n), inputs (k+1, m),
    costates (k+1, n) (NaN on a control edge) and the edge's cost."""

    states: np.ndarray
    inputs: np.ndarray
    costates: np.ndarray
    cost: float


def edge_trajectory(system: System, edge: dict, time_weight: float, dt: float
                    ) -> EdgeTrajectory:
    """Re-integrate one plan edge (`Plan.edges`) from its ``from`` state. An extremal edge
    runs the state+costate ODEs from its costate (u = u*, saturated where the system has
    limits); a control edge holds its input."""
    n = system.n_states
    steps = max(1, round(edge["duration"] / dt))
    x0 = np.asarray(edge["from"], dtype=float)
    if edge.get("control") is not None:
        u = np.asarray(edge["control"], dtype=float)
        states = propagate(system, x0, u, dt, steps)
        rate = float(system.hamiltonian(x0[None], np.zeros((1, n)), u[None], time_weight)[0])
        return EdgeTrajectory(states, np.broadcast_to(u, (steps + 1, u.size)),
                              np.full((steps + 1, n), np.nan), steps * dt * rate)
    traj = rollout(system, np.r_[x0, edge["costate"], 0.0], time_weight, dt, steps)
    return EdgeTrajectory(traj[:, :n], system.optimal_control(traj[:, :n], traj[:, n : 2 * n]),
                          traj[:, n : 2 * n], float(traj[-1, 2 * n]))


def _plan_fields(plan) -> tuple[list[dict], float, float]:
    """(edges, time weight, step) of a `Plan` or of a plan file's content."""
    if isinstance(plan, dict):
        return plan["path"], float(plan["time_weight"]), float(plan["dt"])
    return plan.edges(), float(plan.time_weight), float(plan.dt)


def resimulate(system: System, plan) -> dict:
    """Re-integrate a plan's path (a `Plan` or a plan file's content) edge by edge
    (`edge_trajectory`), each from its stored start node: the largest gap between an edge's
    end and the next node, the largest |cost| difference of an edge, the largest |u| along
    the path, and the path's cost and duration as re-simulated. A plan is what it claims when
    both gaps are at rounding level; `check_plan` checks this and everything else a plan
    claims."""
    edges, w, dt = _plan_fields(plan)
    gap = cost_gap = u_abs = cost = duration = 0.0
    for e in edges:
        t = edge_trajectory(system, e, w, dt)
        gap = max(gap, float(np.linalg.norm(t.states[-1] - np.asarray(e["to"]))))
        cost_gap = max(cost_gap, abs(t.cost - e["cost"]))
        u_abs = max(u_abs, float(np.abs(t.inputs).max()))
        cost += t.cost
        duration += (len(t.states) - 1) * dt
    return {"max_gap": gap, "max_cost_gap": cost_gap, "max_abs_u": u_abs, "path_cost": cost,
            "path_duration": duration}


def sample_path(system: System, plan, dt: float | None = None) -> dict[str, np.ndarray]:
    """Samples along a plan's path (a `Plan` or a plan file's content), re-simulated edge by
    edge from each edge's stored start node: ``t`` (K,), ``state`` (K, n), ``input`` (K, m),
    ``costate`` (K, n; NaN on random-control edges) and ``edge`` (K,), the path edge each
    sample belongs to.

    Every edge gives its first and its last sample, and between them every ``dt`` of the
    path's time: by default the plan's integration step; a whole multiple of it samples the
    re-simulation at that step; a whole fraction of it (step / k) re-simulates every edge at
    the finer step dt (held inputs held, extremals integrated finer: the same path to the
    integrator's error), for a follower that replays the inputs open-loop, whose error from
    interpolating them falls as dt^2 (docs/formats.md). Where two edges meet there are two
    rows with the same time: the end of the one edge (the left limit of the input) and the
    start of the next (its right limit; the costate is drawn afresh there, so the input
    jumps). A follower that interpolates the inputs linearly between rows, as
    ``numpy.interp`` does, then never blends two edges' inputs: within an extremal the input
    is continuous, within a random-control edge it is held."""
    edges, w, step = _plan_fields(plan)
    dt = step if dt is None else float(dt)
    every, finer = round(dt / step), round(step / dt)
    if every >= 1 and abs(every * step - dt) <= 1e-9 * max(1.0, dt):
        finer = 1
    elif finer > 1 and abs(finer * dt - step) <= 1e-9 * max(1.0, step):
        every, step = 1, dt
    else:
        raise ValueError(f"dt {dt}: give a whole multiple or a whole fraction of the plan's "
                         f"integration step {step}")
    if not edges:
        raise ValueError("the plan has no path to sample (it starts in the goal region or "
                         "was not solved and found no node nearer the goal)")
    parts: dict[str, list] = {"t": [], "state": [], "input": [], "costate": [], "edge": []}
    offset = 0  # steps of the path before this edge
    for i, e in enumerate(edges):
        traj = edge_trajectory(system, e, w, step)
        steps = len(traj.states) - 1
        local = np.arange(steps + 1)
        keep = local[((offset + local) % every == 0) | (local == 0) | (local == steps)]
        parts["t"].append((offset + keep) * step)
        parts["state"].append(traj.states[keep])
        parts["input"].append(np.asarray(traj.inputs)[keep])
        parts["costate"].append(traj.costates[keep])
        parts["edge"].append(np.full(len(keep), i))
        offset += steps
    return {k: np.concatenate(v) for k, v in parts.items()}


def plan_problem(system: System, plan, goal_fn=None) -> PlanningProblem:
    """The `PlanningProblem` a plan (file content or `Plan`) records: its start, goal and goal
    test (as `check_plan` measures it; ``goal_fn`` for a goal function of one's own), its
    ``u_max``, obstacles and state constraints. `PlanCheckError` if the plan is malformed or
    its goal test is a function it cannot hold and none is given."""
    from rrtcolearn.planning.problem import PlanningProblem, obstacle_checker, state_bounds

    f = _parse_plan(system, plan if isinstance(plan, dict) else plan.to_dict(),
                    PLAN_CHECK_RTOL)
    problem, how = _goal_problem(system, f, goal_fn)
    if problem is None:
        _fail(f"the plan's goal test is {how}: give the goal function")
    cfg = f["config"] or {}
    try:
        low, high = state_bounds(system, cfg.get("state_low"), cfg.get("state_high"))
    except (TypeError, ValueError) as exc:
        _fail(f"config.plan: {exc}")
    return PlanningProblem(system, f["start"], f["goal"], f["tol"], u_max=f["u_max"],
                           validity=obstacle_checker(system, f["obstacles"]),
                           wrap_goal=problem.wrap_goal, state_low=low, state_high=high,
                           goal_weights=problem.goal_weights, goal_fn=problem.goal_fn)


def replayed_edges(system: System, edges: list[dict], time_weight: float, dt: float,
                   x0: np.ndarray) -> Iterator[EdgeTrajectory]:
    """Each of ``edges`` (`Plan.edges`) re-integrated at the step ``dt`` from where the one
    before it ended (`edge_trajectory`), the first from ``x0``, as asked for."""
    x = np.asarray(x0, dtype=np.float64)
    for e in edges:
        t = edge_trajectory(system, {**e, "from": x.tolist()}, time_weight, dt)
        yield t
        x = t.states[-1]


def replay(problem, plan, dt: float | None = None) -> dict:
    """Re-integrate a plan's path (any planner's `Plan`) from the problem's start, each edge
    from where the previous one ended (`edge_trajectory`, not from the stored nodes), and
    check it against ``problem`` (a `PlanningProblem`): ``path_cost``, ``path_duration``,
    ``max_abs_u``, ``final_goal_distance`` (`PlanningProblem.goal_distance`), the
    ``final_state`` and whether the path ``reaches_goal``, keeps its inputs in the box
    (``inputs_in_box``: the system's limits and ``u_max``) and its states ``valid`` (finite,
    in the state constraints, free of obstacles at every step). ``reaches_goal`` needs all
    three: one check for every planner. ``dt``: the RK4 step to re-integrate at, a whole
    fraction of the plan's (default the plan's own; `step_check`)."""
    return _replayed(problem, plan, dt)[0]


def _replayed(problem, plan, dt: float | None = None) -> tuple[dict, np.ndarray]:
    """`replay`'s figures and the state at the end of each edge (edges, n)."""
    system = problem.system
    step = float(plan.dt)
    dt = step if dt is None else float(dt)
    if not (dt > 0 and abs(round(step / dt) * dt - step) <= 1e-9 * step):
        raise ValueError(f"dt {dt}: give a whole fraction of the plan's step {step}")
    low_u, high_u = input_box(problem)
    x = np.asarray(problem.start, dtype=np.float64)
    cost = duration = max_u = 0.0
    valid = inputs_ok = True
    ends = []
    for t in replayed_edges(system, plan.edges(), plan.time_weight, dt, x):
        max_u = max(max_u, float(np.abs(t.inputs).max()))
        inputs_ok &= bool(np.all((t.inputs >= low_u - 1e-9) & (t.inputs <= high_u + 1e-9)))
        states = t.states[1:]
        valid &= bool(np.isfinite(states).all() and problem.within_bounds(states).all())
        if problem.validity and len(states):
            valid &= bool(problem.validity(states).all())
        cost += t.cost
        duration += (len(t.states) - 1) * dt
        x = t.states[-1]
        ends.append(x)
    gap = float(problem.goal_distance(x[None])[0])
    return ({"path_cost": cost, "path_duration": duration, "max_abs_u": max_u,
             "final_goal_distance": gap, "final_state": x.tolist(), "inputs_in_box": inputs_ok,
             "valid": valid, "reaches_goal": bool(plan.path_nodes) and valid and inputs_ok
             and gap <= problem.goal_tolerance + 1e-9},
            np.array(ends) if ends else np.empty((0, len(x))))


def state_gaps(problem, full: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(N,) the gaps `step_check` measures between pairs of states (N, n) of one path,
    replayed at the plan's step (``full``) and at half of it: the distance of their offsets
    from the goal as the goal test measures it (with a goal function the difference of
    their two distances)."""
    full, half = np.asarray(full, dtype=np.float64), np.asarray(half, dtype=np.float64)
    if problem.goal_fn is None:
        return np.linalg.norm(problem.goal_residual(full) - problem.goal_residual(half),
                              axis=1)
    return np.abs(problem.goal_distance(full) - problem.goal_distance(half))


def step_check(problem, plan) -> dict:
    """Does the plan's integration step resolve its path? The path `replay`-ed from the
    start at the plan's step and at half of it: RK4's error at the half step is about 1/16
    of the step's, so the difference of the two ends estimates the plan's own integration
    error against the continuous dynamics. ``gap``: the distance between the two ends;
    ``goal_gap``: that distance as the goal test measures it (the weighted, wrapped offset
    from the goal; with a goal function the difference of its two distances);
    ``goal_distance``: the half step's end from the goal region; ``valid``: the half step's
    states finite, in the state constraints and free of obstacles; ``resolved``:
    ``node_gap``: the largest such distance at the end of an edge (the path's nodes, the
    end included); ``resolved``: ``node_gap`` below the goal tolerance (the end alone is not
    enough: two replays can part by more than the goal region on the way and end close by
    chance, as the inverted pole of sparse_rrt's cart-pole does, turning over once more at
    half the step; docs/anytime.md); ``replays``: the replay at the plan's step ends
    on the path's last node at the path's cost (to `PLAN_CHECK_RTOL`), as every plan must.

    A path ends at its first state inside the goal region, on its edge, and a planner's
    nodes graze obstacles, so any error can carry the half step's end out of the region
    (0.102 against a tolerance of 0.1) or a state into an obstacle by a hair: those are
    reported, not judged. An error as large as the goal region is: the plan's arrival is
    not resolved at all (a 65 s approach to an unstable upright, re-integrated at half its
    step, ended 6.4 from the goal against a tolerance of 1.5; docs/formats.md). Another
    seed, or a model fitted at a smaller ``generate.dt``, plans at a step that resolves it."""
    full, nodes = _replayed(problem, plan)
    half, half_nodes = _replayed(problem, plan, float(plan.dt) / 2.0)
    ends = np.array([full["final_state"], half["final_state"]])
    # (a path without an edge: both ends the start, no gap)
    gaps = state_gaps(problem, nodes, half_nodes) if len(nodes) else np.zeros(1)
    # the replay at the plan's own step is the plan's path, edge for edge: else the plan
    # records edges that are not what it integrated (a bug, never a property of the problem)
    edges = plan.edges()
    end = np.asarray(edges[-1]["to"] if edges else problem.start, dtype=np.float64)
    replays = bool(np.linalg.norm(ends[0] - end) <= PLAN_CHECK_RTOL * max(
        1.0, float(np.linalg.norm(end))) and abs(full["path_cost"] - plan.path_cost)
        <= PLAN_CHECK_RTOL * max(1.0, abs(plan.path_cost)))
    node_gap = float(gaps.max())
    return {"gap": float(np.linalg.norm(ends[0] - ends[1])), "goal_gap": float(gaps[-1]),
            "node_gap": node_gap, "goal_distance": half["final_goal_distance"],
            "valid": bool(half["valid"]), "resolved": bool(node_gap < problem.goal_tolerance),
            "replays": replays}


def is_resolved(problem, plan) -> bool:
    """`step_check`'s verdict: anytime planning's ``accept``
    (`anytime.solve_with_restarts`), so that it keeps the cheapest path its step resolves
    (and that replays as it claims)."""
    return StepChecks(problem)(plan)


class StepChecks:
    """`step_check` for anytime planning's ``accept`` (`is_resolved`'s verdict) and for the
    plan's record alike, each path replayed once: the last plan checked is remembered by its
    tree and path (a tree's nodes never change once added), so recording the plan anytime
    planning kept does not replay it again (`pipeline.plan`)."""

    def __init__(self, problem):
        self.problem = problem
        self._last: tuple | None = None  # (tree, path nodes, check)

    def __call__(self, plan) -> bool:
        c = self.check(plan)
        return c["resolved"] and c["replays"]

    def check(self, plan) -> dict:
        """`step_check` of ``plan``, replayed only if it is not the last plan checked."""
        last = self._last
        if last is not None and last[0] is plan.tree and last[1] == list(plan.path_nodes):
            return last[2]
        c = step_check(self.problem, plan)
        self._last = (plan.tree, list(plan.path_nodes), c)
        return c


class PlanCheckError(ArtefactError, ValueError):
    """A plan (file) that is not what it claims (`check_plan`): a malformed field, or a path
    whose re-simulation disagrees with what the plan records. One line naming the field."""


PLAN_CHECK_RTOL = 1e-9
"""`check_plan`'s tolerance, relative to max(1, the size of the quantity compared).

A plan records the end of every edge as the package's compiled RK4 integrated it at the
plan's step, and JSON keeps every float exactly; `edge_trajectory` runs the same RK4 at the
same step, so on one machine every gap is exactly zero (measured on extremal, saturated,
truncated and random-control pendulum plans; the test suite asserts < 1e-9). What may
legitimately differ is rounding: another machine's libm may round sin or cos differently in
the last place, and one unit in the last place of an edge's start moves its end by at most
1e-13 on the pendulum's plans (edges up to 19 s). 1e-9 leaves a factor of 1e4 for that and is
a thousandth of the 1e-6 docs/formats.md promises; an edited number, or another costate, step or
system, moves an end by orders of magnitude more."""

_STATUSES = ("exact", "approximate", "timeout")
# the most RK4 steps `check_plan` re-integrates (the longest pendulum plans take some 6000):
# a mistyped duration is an error, not an out-of-memory
_MAX_PATH_STEPS = 10_000_000
# a plan's ``goal_test``: its goal ball (weighted, wrapped), the system's own goal region
# (`System.defaults`), or a goal function of the user's that the file cannot hold
_GOAL_TESTS = ("ball", "system", "function")


def _fail(message: str) -> NoReturn:
    raise PlanCheckError(message)


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def _scalar(value, where: str, *, positive: bool = False, none: bool = False) -> float | None:
    """A finite number (positive with ``positive``; None where ``none`` allows it)."""
    if value is None and none:
        return None
    if not _is_number(value):
        _fail(f"{where} must be a number, got {_short(value)}")
    v = float(value)
    if not np.isfinite(v):
        _fail(f"{where} must be finite, got {v}")
    if positive and not v > 0:
        _fail(f"{where} must be positive, got {v:g}")
    return v


def _vector(value, names: tuple[str, ...] | list[str], where: str) -> np.ndarray:
    """One finite number per name in ``names``."""
    if not isinstance(value, (list, tuple)) or len(value) != len(names) \
            or not all(_is_number(v) for v in value):
        count = f"{len(names)} number{'s' if len(names) != 1 else ''}"
        _fail(f"{where} must be a list of {count} ({', '.join(names)}), got {_short(value)}")
    x = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        _fail(f"{where} must be finite, got {_short(list(value))}")
    return x


def _bound(value, names, where: str, fill: float) -> np.ndarray:
    """An input bound as a plan file writes it: null (unbounded, ``fill``), or a number or
    null (unbounded) per input."""
    if value is None:
        return np.full(len(names), fill)
    if not isinstance(value, (list, tuple)) or len(value) != len(names) \
            or not all(v is None or _is_number(v) for v in value):
        _fail(f"{where} must be null or a list of one number or null per input "
              f"({', '.join(names)}), got {_short(value)}")
    b = np.array([fill if v is None else float(v) for v in value])
    if np.any(np.isnan(b)):
        _fail(f"{where} must not hold NaN, got {_short(list(value))}")
    return b


def _apart(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(|a - b|, the tolerance's scale max(1, |b|_inf)) of two states."""
    return float(np.linalg.norm(a - b)), max(1.0, float(np.abs(b).max(initial=0.0)))


def _parse_edge(system: System, e, at: str, dt: float, rtol: float) -> dict:
    """A path edge's fields, checked: ``from``, ``to``, ``duration``, ``cost``, optional
    ``max_abs_u``, and ``costate`` and ``params`` (an extremal) or ``control`` (a
    random-control edge), told apart as `edge_trajectory` tells them."""
    if not isinstance(e, dict):
        _fail(f"{at} must be an edge (an object), got {_short(e)}")
    for key in ("from", "to", "duration", "cost"):
        if key not in e:
            _fail(f"{at} has no {key!r} field")
    edge = {"from": _vector(e["from"], system.state_names, f"{at}.from"),
            "to": _vector(e["to"], system.state_names, f"{at}.to"),
            "duration": _scalar(e["duration"], f"{at}.duration"),
            "cost": _scalar(e["cost"], f"{at}.cost"),
            "max_abs_u": _scalar(e.get("max_abs_u"), f"{at}.max_abs_u", none=True)}
    duration = edge["duration"]
    steps = round(duration / dt)
    if not duration > 0 or steps < 1 or abs(steps * dt - duration) > rtol * duration:
        _fail(f"{at}.duration is {duration:g}: an edge lasts a positive whole number of the "
              f"plan's steps (dt = {dt:g})")
    if e.get("control") is not None:
        for key in ("costate", "params"):
            if e.get(key) is not None:
                _fail(f"{at} has both a control and a {key}: a random-control edge has "
                      f"{key} null, an extremal control null")
        edge["control"] = _vector(e["control"], system.input_names, f"{at}.control")
        return edge
    if e.get("costate") is None:
        _fail(f"{at} has neither a costate (an extremal) nor a control (a random-control "
              "edge)")
    edge["costate"] = _vector(e["costate"], [f"lambda_{s}" for s in system.state_names],
                              f"{at}.costate")
    edge["params"] = _vector(e.get("params"), system.param_names, f"{at}.params")
    return edge


def _parse_plan(system: System, d, rtol: float) -> dict:
    """The plan's fields, checked for ``system``; PlanCheckError naming the first bad one."""
    from rrtcolearn.planning.validity import obstacle_from_dict

    if not isinstance(d, dict):
        _fail(f"a plan is a JSON object, got {type(d).__name__}")
    for key in ("system", "start", "goal", "goal_tolerance", "time_weight", "dt", "status",
                "path"):
        if key not in d:
            _fail(f"the plan has no {key!r} field")
    if d["system"] != system.name:
        _fail(f"the plan is for system {_short(d['system'])}, not {system.name!r}")
    status = d["status"]
    if status not in _STATUSES:
        _fail(f"status must be one of {', '.join(_STATUSES)}, got {_short(status)}")
    if "solved" in d and d["solved"] is not (status == "exact"):
        _fail(f"solved is {_short(d['solved'])} but status is {status!r}")
    f = {"status": status,
         "start": _vector(d["start"], system.state_names, "start"),
         "goal": _vector(d["goal"], system.state_names, "goal"),
         "tol": _scalar(d["goal_tolerance"], "goal_tolerance", positive=True),
         "w": _scalar(d["time_weight"], "time_weight", positive=True),
         "dt": _scalar(d["dt"], "dt", positive=True),
         "u_max": _scalar(d.get("u_max"), "u_max", positive=True, none=True),
         "low": _bound(d.get("input_low"), system.input_names, "input_low", -np.inf),
         "high": _bound(d.get("input_high"), system.input_names, "input_high", np.inf),
         "final": _scalar(d.get("final_goal_distance"), "final_goal_distance", none=True)}
    for key in ("path_cost", "path_duration", "max_abs_u"):
        f[key] = _scalar(d.get(key), key, none=True)
    if np.any(f["low"] >= f["high"]):
        _fail(f"input_low {f['low'].tolist()} must lie below input_high "
              f"{f['high'].tolist()}")
    if f["final"] is not None and f["final"] < 0:
        _fail(f"final_goal_distance must not be negative, got {f['final']:g}")
    angles = d.get("goal_angles", [])
    if not isinstance(angles, (list, tuple)) or not all(_is_number(a) for a in angles) \
            or sorted(angles) not in ([], sorted(system.angle_dims)):
        _fail(f"goal_angles must be [] or the system's angle coordinates "
              f"{list(system.angle_dims)}, got {_short(angles)}")
    f["wrap_goal"] = bool(angles)
    f["goal_test"] = d.get("goal_test")
    if f["goal_test"] is not None and f["goal_test"] not in _GOAL_TESTS:
        _fail(f"goal_test must be one of {', '.join(_GOAL_TESTS)}, got "
              f"{_short(f['goal_test'])}")
    obstacles = d.get("obstacles") or []
    if not isinstance(obstacles, list) or not all(isinstance(o, dict) for o in obstacles):
        _fail(f"obstacles must be a list of obstacles, got {_short(obstacles)}")
    try:
        f["obstacles"] = [obstacle_from_dict(o, system.n_states) for o in obstacles]
    except (KeyError, TypeError, ValueError) as exc:
        _fail(f"obstacles: {exc}")
    config = d.get("config")
    plan_cfg = config.get("plan") if isinstance(config, dict) else None
    f["config"] = plan_cfg if isinstance(plan_cfg, dict) else None
    if not isinstance(d["path"], list):
        _fail(f"path must be a list of edges, got {_short(d['path'])}")
    f["edges"] = [_parse_edge(system, e, f"path[{k}]", f["dt"], rtol)
                  for k, e in enumerate(d["path"])]
    steps = sum(round(e["duration"] / f["dt"]) for e in f["edges"])
    if steps > _MAX_PATH_STEPS:
        _fail(f"the path lasts {steps} steps of dt = {f['dt']:g}, more than the "
              f"{_MAX_PATH_STEPS} a check re-simulates")
    return f


def _goal_problem(system: System, f: dict, goal_fn) -> tuple[PlanningProblem | None, str]:
    """A `PlanningProblem` whose ``goal_distance`` is the plan's goal test, and how it
    measures; None where the file cannot say (a goal function it does not record, not
    given as ``goal_fn``)."""
    from rrtcolearn.planning.problem import PlanningProblem

    cfg = f["config"]
    wrap = f["wrap_goal"]
    if cfg is not None and "wrap_goal" in cfg and bool(cfg["wrap_goal"]) != wrap:
        _fail(f"goal_angles {list(system.angle_dims) if wrap else []} disagree with the "
              f"recorded configuration's plan.wrap_goal = {cfg['wrap_goal']}")
    weights = None if cfg is None else cfg.get("goal_weights")
    if weights is not None:
        weights = _vector(weights, system.state_names, "config.plan.goal_weights")
        if np.any(weights < 0) or not np.any(weights > 0):
            _fail("config.plan.goal_weights must be non-negative and not all zero, got "
                  f"{weights.tolist()}")
        if np.all(weights == 1):
            weights = None
    defaults = system.defaults
    test = f["goal_test"]
    if test == "system" and defaults.get("goal_fn") is None:
        _fail(f"goal_test is 'system' but system {system.name!r} has no goal region of its "
              "own")
    if goal_fn is not None:
        how = "the goal function given"
    elif test == "function":
        return None, "a goal function the plan does not record: not re-checked"
    elif test == "system" or (test is None and defaults.get("goal_fn") is not None
                              and defaults.get("goal") is not None and np.array_equal(
                                  f["goal"], np.asarray(defaults["goal"], dtype=np.float64))):
        # the system's standard query comes with its goal region (`pipeline.make_problem`)
        goal_fn, how = defaults["goal_fn"], f"the goal region of system {system.name!r}"
    else:
        how = ("weighted distance" if weights is not None else "distance") + " to the goal" + \
            (", angles modulo a turn" if wrap else "")
    return PlanningProblem(system, f["start"], f["goal"], f["tol"], wrap_goal=wrap,
                           goal_weights=weights, goal_fn=goal_fn), how


def check_plan(system: System, plan, *, goal_fn=None, rtol: float = PLAN_CHECK_RTOL) -> dict:
    """Check that a plan (a plan file's content, `pipeline.read_plan`, or a `Plan`) is what it
    claims, independently of the planner, on ``system`` (`pipeline.plan_system`).

    Structure: every field the re-simulation and the claims need is there, with the right
    shape for ``system`` (n states, m inputs; an extremal edge's ``costate`` and ``params``,
    a random-control edge's ``control``, told apart as `edge_trajectory` tells them),
    finite, with durations positive whole multiples of ``dt``.

    Re-simulation (each edge by `edge_trajectory` from its recorded ``from``: the
    integration `sample_path` exports): it ends at its ``to`` and costs its ``cost``; the
    edges join (the first starts at ``start``, every other where the one before ends); the
    inputs keep the recorded ``u_max`` and ``input_low``/``input_high`` (the system's
    limits, or a peer's input box); the states stay finite, out of the recorded obstacles
    and inside the state constraints of the recorded configuration; the plan's
    ``path_cost``, ``path_duration`` and ``max_abs_u`` and each edge's ``max_abs_u`` are the
    re-simulated ones. A path of more than 10 million steps is refused, not re-simulated.

    Goal: for status "exact" the path's end (the start for an empty path) lies within
    ``goal_tolerance`` of the goal, and ``final_goal_distance`` is its distance, both as the
    plan's goal test measures: the distance to ``goal`` with the angles in ``goal_angles``
    modulo a turn and the configuration's ``plan.goal_weights``; the system's own goal
    region (`System.defaults`) for its default goal; or ``goal_fn`` (states (N, n) ->
    distances (N,)) where given, for a plan made with a goal function of one's own (or a
    `Plan` made without `pipeline.plan`, which records no configuration:
    ``goal_fn=problem.goal_distance``). A ``goal_test`` field ("ball", "system" or
    "function") says which; a file cannot hold a goal function, so without ``goal_fn`` a
    "function" plan is checked only for an exact plan's recorded distance being within the
    tolerance (``goal_checked`` False), and a plan without the field is taken to have the
    goal ball (or the system's region) it records.

    Every comparison allows ``rtol`` times max(1, the size of the quantity compared):
    rounding (`PLAN_CHECK_RTOL`). Raises `PlanCheckError` (a ValueError, and an
    `ArtefactError` the command line prints as one line) naming the field or edge and by how
    much. Returns the figures: ``edges``; ``max_gap`` (an edge's re-simulated end to its
    ``to``), ``max_cost_gap``, ``max_join_gap`` (an edge's ``from`` to the previous ``to``);
    the re-simulated ``max_abs_u``, ``path_cost`` and ``path_duration``;
    ``end_goal_distance`` (None where not re-measured), ``goal_test`` (how it was measured)
    and ``goal_checked``; ``obstacles`` (how many were checked) and
    ``state_constraints_checked`` (a plan without its configuration records none).
    """
    from rrtcolearn.planning.problem import PlanningProblem, obstacle_checker, state_bounds

    f = _parse_plan(system, plan if isinstance(plan, dict) else plan.to_dict(), rtol)
    low_u, high_u = f["low"], f["high"]
    u_max = f["u_max"]
    w, dt, tol = f["w"], f["dt"], f["tol"]
    obstacles = obstacle_checker(system, f["obstacles"])
    constraints = None
    if f["config"] is not None:
        try:
            s_low, s_high = state_bounds(system, f["config"].get("state_low"),
                                         f["config"].get("state_high"))
        except (TypeError, ValueError) as exc:
            _fail(f"config.plan: {exc}")
        constraints = PlanningProblem(system, f["start"], f["goal"], tol, state_low=s_low,
                                      state_high=s_high)
    gap = cost_gap = join_gap = u_abs = cost = duration = 0.0
    end = f["start"]
    for k, e in enumerate(f["edges"]):
        at = f"path[{k}]"
        apart, scale = _apart(e["from"], end)
        if apart > rtol * scale:
            _fail(f"{at}.from is {apart:.3g} from "
                  f"{'the start' if k == 0 else f'path[{k - 1}].to'}: the path jumps")
        join_gap = max(join_gap, apart)
        with np.errstate(all="ignore"):
            t = edge_trajectory(system, e, w, dt)
        if not (np.all(np.isfinite(t.states)) and np.isfinite(t.cost)):
            _fail(f"{at}: re-simulated from its recorded from, its states do not stay finite")
        apart, scale = _apart(t.states[-1], e["to"])
        if apart > rtol * scale:
            _fail(f"{at}: re-simulated for {e['duration']:g} s from its recorded from, it ends "
                  f"{apart:.3g} from its recorded to (tolerance {rtol * scale:.3g})")
        gap = max(gap, apart)
        apart = abs(t.cost - e["cost"])
        if apart > rtol * max(1.0, abs(t.cost)):
            _fail(f"{at}: re-simulated, it costs {t.cost:.10g}, not the recorded "
                  f"{e['cost']:.10g} (by {apart:.3g})")
        cost_gap = max(cost_gap, apart)
        u = np.asarray(t.inputs, dtype=np.float64)
        top = float(np.abs(u).max())
        if u_max is not None and top > u_max + rtol * max(1.0, u_max):
            i, j = np.unravel_index(int(np.argmax(np.abs(u))), u.shape)
            _fail(f"{at}: input {system.input_names[j]} reaches {u[i, j]:.6g} at t = "
                  f"{duration + i * dt:.6g} s, beyond the recorded u_max {u_max:g} by "
                  f"{top - u_max:.3g}")
        over = np.maximum(low_u - u, u - high_u)
        i, j = np.unravel_index(int(np.argmax(over)), over.shape)
        if over[i, j] > rtol * max(1.0, abs(u[i, j])):
            _fail(f"{at}: input {system.input_names[j]} reaches {u[i, j]:.6g} at t = "
                  f"{duration + i * dt:.6g} s, outside the recorded input box "
                  f"[{low_u[j]:g}, {high_u[j]:g}] by {over[i, j]:.3g}")
        if e["max_abs_u"] is not None and abs(e["max_abs_u"] - top) > rtol * max(1.0, top):
            _fail(f"{at}.max_abs_u is recorded as {e['max_abs_u']:.10g}, the re-simulated "
                  f"edge reaches |u| = {top:.10g}")
        u_abs = max(u_abs, top)
        for name, checker in (("lies in a recorded obstacle", obstacles if obstacles else None),
                              ("leaves the state constraints of the recorded configuration",
                               None if constraints is None else constraints.within_bounds)):
            if checker is not None and not np.all(ok := checker(t.states[1:])):
                i = int(np.argmin(ok)) + 1
                _fail(f"{at}: the state {_short(t.states[i].tolist())} at t = "
                      f"{duration + i * dt:.6g} s {name}")
        cost += t.cost
        duration += (len(t.states) - 1) * dt
        end = e["to"]
    for key, value in (("path_cost", cost), ("path_duration", duration),
                       ("max_abs_u", u_abs)):
        if f[key] is not None and abs(f[key] - value) > rtol * max(1.0, abs(value)):
            _fail(f"{key} is recorded as {f[key]:.10g}, the re-simulated path gives "
                  f"{value:.10g}")
    problem, how = _goal_problem(system, f, goal_fn)
    slack = rtol * max(1.0, tol)
    distance = None
    if problem is None:  # only the recorded distance to go by
        if f["status"] == "exact" and not (f["final"] is not None and f["final"] <= tol + slack):
            _fail(f"status is 'exact' but final_goal_distance is {f['final']}, not within "
                  f"goal_tolerance {tol:g}")
    else:
        try:
            distance = float(np.asarray(problem.goal_distance(end[None]),
                                        dtype=np.float64).reshape(-1)[0])
        except Exception as exc:
            _fail(f"the goal test failed on the path's end: {type(exc).__name__}: {exc}")
        # an unmarked plan may have been made with a goal function of the user's own
        unrecorded = "" if goal_fn is not None or f["goal_test"] is not None else \
            "; or the plan was made with a goal function, which its file does not record"
        if f["status"] == "exact" and not distance <= tol + slack:
            recorded = "" if f["final"] is None else \
                f" (the plan records final_goal_distance {f['final']:.6g}{unrecorded})"
            _fail(f"status is 'exact' but the path ends {distance:.6g} from the goal "
                  f"{f['goal'].tolist()} ({how}), beyond goal_tolerance {tol:g}{recorded}")
        if f["final"] is not None and abs(f["final"] - distance) > rtol * max(1.0, distance):
            _fail(f"final_goal_distance is recorded as {f['final']:.10g}, but the path ends "
                  f"{distance:.10g} from the goal ({how}{unrecorded})")
    return {"edges": len(f["edges"]), "max_gap": gap, "max_cost_gap": cost_gap,
            "max_join_gap": join_gap, "max_abs_u": u_abs, "path_cost": cost,
            "path_duration": duration, "end_goal_distance": distance, "goal_test": how,
            "goal_checked": problem is not None, "obstacles": len(f["obstacles"]),
            "state_constraints_checked": constraints is not None}

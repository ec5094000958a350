"""Held-out evaluation of the learned functions (paper Experiments: steering MSE), and the
re-simulation of a plan's path from its start."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rrtcolearn.data.dataset import Dataset
from rrtcolearn.integrate import propagate, rollout
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.systems.base import System


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
    mse = np.empty(len(pick))
    for q, i in enumerate(pick):  # one rollout per query: the compiled kernel does the work
        lam, ok = system.costate_from_params(X[i : i + 1, :n], steer[i : i + 1, :-1],
                                             time_weight)
        if not ok[0]:
            mse[q] = np.inf
            continue
        steps = max(1, round(steer[i, -1] / dt))
        traj = rollout(system, np.r_[X[i, :n], lam[0], 0.0], time_weight, dt, steps)
        mse[q] = np.mean((traj[-1, :n] - X[i, n:]) ** 2)
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
    both gaps are at rounding level."""
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
    edge from each edge's stored start node at the plan's integration step: ``t`` (K,),
    ``state`` (K, n), ``input`` (K, m), ``costate`` (K, n; NaN on random-control edges) and
    ``edge`` (K,), the path edge each sample starts (the last sample is the path's end).
    ``dt`` (default the plan's step) must be a whole multiple of the plan's step: the
    samples are every such step of the one integration the plan was checked with."""
    edges, w, step = _plan_fields(plan)
    dt = step if dt is None else float(dt)
    every = round(dt / step)
    if every < 1 or abs(every * step - dt) > 1e-9 * max(1.0, dt):
        raise ValueError(f"dt {dt}: give a whole multiple of the plan's integration step "
                         f"{step}")
    if not edges:
        raise ValueError("the plan has no path to sample (it starts in the goal region or "
                         "was not solved and found no node nearer the goal)")
    parts = [edge_trajectory(system, e, w, step) for e in edges]
    state = np.concatenate([p.states[:-1] for p in parts] + [parts[-1].states[-1:]])
    inputs = np.concatenate([p.inputs[:-1] for p in parts] + [parts[-1].inputs[-1:]])
    costate = np.concatenate([p.costates[:-1] for p in parts] + [parts[-1].costates[-1:]])
    edge = np.concatenate([np.full(len(p.states) - 1, i) for i, p in enumerate(parts)]
                          + [np.array([len(parts) - 1])])
    keep = np.r_[np.arange(0, len(state) - 1, every), len(state) - 1]
    return {"t": keep * step, "state": state[keep], "input": inputs[keep],
            "costate": costate[keep], "edge": edge[keep]}


def replay(problem, plan) -> dict:
    """Re-integrate a plan's path (any planner's `Plan`) from the problem's start, each edge
    from where the previous one ended (`edge_trajectory`, not from the stored nodes), and
    check it against ``problem`` (a `PlanningProblem`): ``path_cost``, ``path_duration``,
    ``max_abs_u``, ``final_goal_distance`` (`PlanningProblem.goal_distance`) and whether the
    path ``reaches_goal``, keeps its inputs in the box (``inputs_in_box``: the system's
    limits and ``u_max``) and its states ``valid`` (finite, in the state constraints, free of
    obstacles at every step). ``reaches_goal`` needs all three: one check for every planner."""
    system = problem.system
    low_u, high_u = system.input_limits()
    if problem.u_max is not None:
        low_u, high_u = np.maximum(low_u, -problem.u_max), np.minimum(high_u, problem.u_max)
    x = np.asarray(problem.start, dtype=np.float64)
    cost = duration = max_u = 0.0
    valid = inputs_ok = True
    for e in plan.edges():
        t = edge_trajectory(system, {**e, "from": x.tolist()}, plan.time_weight, plan.dt)
        max_u = max(max_u, float(np.abs(t.inputs).max()))
        inputs_ok &= bool(np.all((t.inputs >= low_u - 1e-9) & (t.inputs <= high_u + 1e-9)))
        states = t.states[1:]
        valid &= bool(np.isfinite(states).all() and problem.within_bounds(states).all())
        if problem.validity and len(states):
            valid &= bool(problem.validity(states).all())
        cost += t.cost
        duration += (len(t.states) - 1) * plan.dt
        x = t.states[-1]
    gap = float(problem.goal_distance(x[None])[0])
    return {"path_cost": cost, "path_duration": duration, "max_abs_u": max_u,
            "final_goal_distance": gap, "inputs_in_box": inputs_ok, "valid": valid,
            "reaches_goal": bool(plan.path_nodes) and valid and inputs_ok
            and gap <= problem.goal_tolerance + 1e-9}

"""What the peers share: the input box they draw from, their goal test, and their result, a
`Plan` of control edges (constant inputs held for whole RK4 steps) like RRT-CoLearn's.

Peers choose inputs directly; their paths are executed with `rrtcolearn.integrate.propagate`
on the problem's `System.dynamics`, so every planner's plan is re-simulated by one check
(`rrtcolearn.evaluate.replay`).
"""

from __future__ import annotations

import numpy as np

from rrtcolearn.integrate import propagate
from rrtcolearn.planning.lqr import input_box as problem_input_box
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.tree import Plan, PlannerData


def input_box(problem: PlanningProblem, u_max: float | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """(m,) low and high input bounds of a random-control peer: the system's input limits,
    within the problem's ``u_max`` if it has one; an input still unbounded gets +-``u_max``
    (the peer's own bound). ValueError if an input stays unbounded."""
    low, high = problem_input_box(problem)
    if u_max is not None:
        low = np.where(np.isfinite(low), low, -float(u_max))
        high = np.where(np.isfinite(high), high, float(u_max))
    if not (np.isfinite(low).all() and np.isfinite(high).all()):
        raise ValueError(
            f"system {problem.system.name!r} has unbounded inputs and the problem sets no "
            "u_max: a random-control planner needs an input bound (give the planner u_max, "
            "or plan with input limits)")
    return low, high


def input_box_reason(problem: PlanningProblem, u_max: float | None = None) -> str | None:
    """Why `input_box` has no box for ``problem`` (None: it has one)."""
    try:
        input_box(problem, u_max)
    except ValueError as exc:
        return str(exc)
    return None


def in_goal(problem: PlanningProblem, states: np.ndarray) -> np.ndarray:
    """(N,) True for the states (N, n) inside the problem's goal region (as RRT-CoLearn
    tests it: the squared weighted distance, or the user's goal function)."""
    if problem.goal_fn is None:
        gd = problem.goal_residual(states)
        return np.einsum("ij,ij->i", gd, gd) <= problem.goal_tolerance**2
    return problem.goal_distance(states) <= problem.goal_tolerance


def edge_cost_rate(problem: PlanningProblem, u: np.ndarray, time_weight: float) -> float:
    """Running cost ``w + u^T R u / 2`` of the constant input ``u`` (m,)."""
    n = problem.system.n_states
    return float(problem.system.hamiltonian(problem.start[None], np.zeros((1, n)),
                                            np.asarray(u, dtype=np.float64)[None],
                                            time_weight)[0])


def control_plan(problem: PlanningProblem, controls: np.ndarray, steps: np.ndarray, *,
                 dt: float, time_weight: float, cpu_s: float, wall_s: float, iterations: int,
                 graph_states: int, extra: dict) -> Plan:
    """The `Plan` of a peer's path: ``controls[k]`` (m,) held for ``steps[k]`` RK4 steps of
    ``dt`` from the start, executed here edge after edge (`propagate`). The tree holds the
    path only (``graph_states`` is the size of the peer's graph). The status is "exact" only
    when the executed path stays valid (state constraints, obstacles, finite) and ends in the
    goal region; the peer's own claim is not taken on trust. An edge that turns invalid is
    recorded up to its last valid state, with the duration and cost of those steps, and ends
    the path."""
    sys = problem.system
    controls = np.asarray(controls, dtype=np.float64).reshape(len(steps), sys.n_inputs)
    tree = PlannerData(problem.start, sys.n_params, capacity=max(2, len(steps) + 1),
                       n_inputs=sys.n_inputs)
    low, high = problem.constraint_box
    valid = True
    for u, k in zip(controls, steps, strict=True):
        x = tree.states[tree.n_nodes - 1]
        traj = propagate(sys, x, u, dt, int(k), low, high)
        last_ok = bool(np.isfinite(traj[-1]).all()) and \
            bool(np.all((traj[-1] >= low) & (traj[-1] <= high)))
        keep = len(traj) if last_ok else len(traj) - 1  # (a stop's last state is outside)
        if problem.validity and keep > 1:
            free = problem.validity(traj[1:keep])
            if not free.all():
                keep = 1 + int(np.argmin(free))  # up to the state before the first obstacle
        ok = keep == int(k) + 1
        valid &= ok
        done = keep - 1  # the steps executed validly: the edge ends at the last valid state
        if done:  # with the duration and cost of its own steps
            tree.add(traj[done], tree.n_nodes - 1, np.full(sys.n_states, np.nan),
                     np.full(sys.n_params, np.nan), done * dt,
                     done * dt * edge_cost_rate(problem, u, time_weight), traj[:keep],
                     float(np.abs(u).max()), control=u)
        if not ok:
            break
    end = tree.states[tree.n_nodes - 1]
    reached = bool(in_goal(problem, end[None])[0])
    status = "exact" if valid and reached else ("approximate" if tree.n_nodes > 1
                                                else "timeout")
    return peer_plan(problem, tree, list(range(tree.n_nodes)), status, dt=dt,
                     time_weight=time_weight, cpu_s=cpu_s, wall_s=wall_s,
                     iterations=iterations, graph_states=graph_states,
                     extra={**extra, "valid": valid})


def peer_plan(problem: PlanningProblem, tree: PlannerData, path_nodes: list[int], status: str,
              *, dt: float, time_weight: float, cpu_s: float, wall_s: float, iterations: int,
              graph_states: int | None, extra: dict) -> Plan:
    """A peer's `Plan` with the problem's fields filled in as RRT-CoLearn fills them."""
    sys = problem.system
    region = problem.goal_fn is not None or problem.goal_weights is not None
    input_low, input_high = sys.input_limits() if sys.input_limited else (None, None)
    end = tree.states[path_nodes[-1]] if path_nodes else problem.start
    return Plan(
        system=sys.name, start=problem.start, goal=problem.goal,
        goal_tolerance=problem.goal_tolerance, time_weight=float(time_weight), dt=float(dt),
        status=status, planning_time_s=float(wall_s), planning_cpu_s=float(cpu_s),
        iterations=int(iterations), tree=tree, path_nodes=path_nodes, u_max=problem.u_max,
        input_low=input_low, input_high=input_high,
        obstacles=[o.to_dict() for o in problem.validity.obstacles],
        goal_angles=problem.goal_angles, goal_test=problem.goal_test,
        end_goal_distance=float(problem.goal_distance(end[None])[0]) if region else None,
        graph_states=graph_states, extra=extra)

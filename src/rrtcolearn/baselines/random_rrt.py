"""Random-control RRT with the Euclidean metric: the baseline of the paper's introduction.

Each iteration samples a target (the goal with probability ``goal_bias``), picks the tree
node nearest to it in Euclidean distance, applies a random input held for a random number of
propagation steps (the best of ``n_controls`` such samples), and keeps the edge's valid part.
"""

from __future__ import annotations

import time

import numpy as np

from rrtcolearn.baselines.base import BaselineResult, ControlPath
from rrtcolearn.integrate import propagate
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.termination import TerminationCondition


def _propagate(system, x: np.ndarray, u: np.ndarray, steps: int, dt: float) -> np.ndarray:
    """RK4 of rows x (K, n) under constant inputs u (K, m): states (steps, K, n)."""
    out = np.empty((steps, *x.shape))
    for k in range(len(x)):
        out[:, k] = propagate(system, x[k], u[k], dt, steps)[1:]
    return out


def solve_random_rrt(problem: PlanningProblem, *, seed: int = 0, time_limit: float = 10.0,
                     max_iterations: int | None = None, u_bound: float | None = None,
                     n_controls: int = 1, dt: float = 0.01, step: float = 0.02,
                     min_steps: int = 1, max_steps: int = 25, goal_bias: float = 0.05
                     ) -> BaselineResult:
    """Plan with random controls; ``u_bound`` defaults to the problem's ``u_max`` (else 5)."""
    sys = problem.system
    rng = np.random.default_rng(seed)
    ub = problem.u_max if problem.u_max is not None else (u_bound or 5.0)
    sub = round(step / dt)
    n = sys.n_states
    states = np.empty((1024, n))
    states[0] = problem.start
    parents = [-1]
    controls = [np.zeros(sys.n_inputs)]
    durations = [0.0]
    count = 1
    tol2 = problem.goal_tolerance**2
    bounded = sys.bounded_dims
    check = bool(problem.validity)
    goal_node = -1
    iterations = 0
    stop = TerminationCondition(time_limit, max_iterations)
    cpu0 = time.process_time()
    stop.start()
    while goal_node < 0 and not stop(iterations):
        iterations += 1
        target = problem.goal if rng.random() < goal_bias else \
            rng.uniform(sys.state_low, sys.state_high)
        d = states[:count] - target
        near = int(np.argmin(np.einsum("ij,ij->i", d, d)))
        u = rng.uniform(-ub, ub, size=(n_controls, sys.n_inputs))
        k = rng.integers(min_steps, max_steps + 1, size=n_controls)
        traj = _propagate(sys, np.repeat(states[near][None], n_controls, axis=0), u,
                          int(k.max()) * sub, dt)
        ends = traj[k * sub - 1, np.arange(n_controls)]
        best = int(np.argmin(np.sum((ends - target) ** 2, axis=1)))
        path = traj[: k[best] * sub, best]
        ok = np.isfinite(path).all(axis=1)
        if bounded.size:
            ok &= np.all((path[:, bounded] >= sys.state_low[bounded])
                         & (path[:, bounded] <= sys.state_high[bounded]), axis=1)
        if check:
            ok &= problem.validity(path)
        end = len(path) if ok.all() else int(np.argmin(ok))
        gd = path[:end] - problem.goal
        hit = np.flatnonzero(np.einsum("ij,ij->i", gd, gd) <= tol2)
        if hit.size:
            end = int(hit[0]) + 1
        end = (end // sub) * sub if not hit.size else end  # whole propagation steps
        if end == 0:
            continue
        if count == len(states):
            states = np.concatenate([states, np.empty_like(states)])
        states[count] = path[end - 1]
        parents.append(near)
        controls.append(u[best])
        durations.append(end * dt)
        if hit.size:
            goal_node = count
        count += 1
    cpu, wall = time.process_time() - cpu0, stop.elapsed()
    if goal_node >= 0:
        status, last = "exact", goal_node
    else:
        gd = states[:count] - problem.goal
        last = int(np.argmin(np.einsum("ij,ij->i", gd, gd)))
        status = "approximate" if last != 0 else "timeout"
    chain = []
    while last > 0:
        chain.append(last)
        last = parents[last]
    chain.reverse()
    path = ControlPath(problem.start.copy(),
                       np.array([controls[i] for i in chain]).reshape(-1, sys.n_inputs),
                       np.array([durations[i] for i in chain]))
    return BaselineResult("random-rrt", status == "exact", status, cpu, wall, iterations,
                          count, path, {"u_bound": ub, "n_controls": n_controls})

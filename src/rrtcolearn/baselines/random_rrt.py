"""Random-control RRT with the (metric-scaled) Euclidean metric: the baseline of the paper's
introduction, on any `System`.

Each iteration samples a target (a goal state with probability ``goal_bias``, else uniform in
the problem's state box), picks the tree node nearest to it in the distance weighted by
``System.metric_scale`` (1 for the pendulum: plain Euclidean), applies a random input from the
input box (`input_box`) held for a random number of propagation steps (the best of
``n_controls`` such samples), and keeps the edge's valid part (state constraints, obstacles),
cut at its first state in the goal region.
"""

from __future__ import annotations

import time

import numpy as np

from rrtcolearn.baselines.base import (
    edge_cost_rate,
    in_goal,
    input_box,
    input_box_reason,
    peer_plan,
)
from rrtcolearn.integrate import propagate
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan, PlannerData


class RandomControlRRT:
    """The random-control RRT as a `rrtcolearn.planners.Planner`.

    ``u_max`` bounds the inputs the problem leaves unbounded (`input_box`); ``dt`` is the RK4
    step, ``step`` the propagation step (a multiple of it), and an edge holds its input for
    ``min_steps..max_steps`` propagation steps. ``time_weight`` prices the path
    (``w + u^T R u / 2``; the search ignores cost).
    """

    name = "random-rrt"

    def __init__(self, *, time_weight: float = 1.0, u_max: float | None = None,
                 n_controls: int = 1, dt: float = 0.01, step: float = 0.02,
                 min_steps: int = 1, max_steps: int = 25, goal_bias: float = 0.05):
        self.time_weight = time_weight
        self.u_max = u_max
        self.n_controls = n_controls
        self.dt = dt
        self.step = step
        self.min_steps = min_steps
        self.max_steps = max_steps
        self.goal_bias = goal_bias

    def supports(self, problem: PlanningProblem) -> str | None:
        """None, or why the planner cannot run on ``problem`` (no input box)."""
        return input_box_reason(problem, self.u_max)

    def solve(self, problem: PlanningProblem, termination: TerminationCondition,
              seed: int = 0) -> Plan:
        """Grow the tree until a node reaches the goal region or ``termination`` says stop."""
        sys = problem.system
        rng = np.random.default_rng(seed)
        low_u, high_u = input_box(problem, self.u_max)
        dt, nc = self.dt, self.n_controls
        sub = round(self.step / dt)
        tree = PlannerData(problem.start, sys.n_params, capacity=1024, n_inputs=sys.n_inputs)
        scale = sys.metric_scale
        low, high = problem.constraint_box
        check = bool(problem.validity)
        goal_node = -1 if not in_goal(problem, problem.start[None])[0] else 0
        iterations = 0
        nan_n, nan_p = np.full(sys.n_states, np.nan), np.full(sys.n_params, np.nan)
        cpu0 = time.process_time()
        termination.start()
        while goal_node < 0 and not termination(iterations):
            iterations += 1
            target = problem.sample_goal(rng) if rng.random() < self.goal_bias else \
                rng.uniform(problem.state_low, problem.state_high)
            d = (tree.states[: tree.n_nodes] - target) * scale
            near = int(np.argmin(np.einsum("ij,ij->i", d, d)))
            u = rng.uniform(low_u, high_u, size=(nc, sys.n_inputs))
            k = rng.integers(self.min_steps, self.max_steps + 1, size=nc)
            x0 = tree.states[near].copy()
            trajs = [propagate(sys, x0, u[c], dt, int(k[c]) * sub)[1:] for c in range(nc)]
            ends = np.array([t[-1] for t in trajs])
            best = int(np.argmin(np.sum(((ends - target) * scale) ** 2, axis=1)))
            path = trajs[best]
            ok = np.isfinite(path).all(axis=1) & np.all((path >= low) & (path <= high), axis=1)
            if check:
                ok &= problem.validity(path)
            end = len(path) if ok.all() else int(np.argmin(ok))
            hit = np.flatnonzero(in_goal(problem, path[:end])) if end else np.zeros(0, int)
            end = int(hit[0]) + 1 if hit.size else (end // sub) * sub  # whole propagation steps
            if end == 0:
                continue
            ub = u[best]
            cost = end * dt * edge_cost_rate(problem, ub, self.time_weight)
            node = tree.add(path[end - 1], near, nan_n, nan_p, end * dt, cost,
                            np.vstack([x0[None], path[:end]]), float(np.abs(ub).max()),
                            control=ub)
            if hit.size:
                goal_node = node
        cpu, wall = time.process_time() - cpu0, termination.elapsed()
        if goal_node >= 0:
            status, last = "exact", goal_node
        else:
            last = int(np.argmin(problem.goal_distance(tree.states[: tree.n_nodes])))
            status = "approximate" if last != 0 else "timeout"
        return peer_plan(problem, tree, tree.path_to(last), status, dt=dt,
                         time_weight=self.time_weight, cpu_s=cpu, wall_s=wall,
                         iterations=iterations, graph_states=None,
                         extra={"planner": self.name, "input_low": low_u.tolist(),
                                "input_high": high_u.tolist(), "n_controls": nc})


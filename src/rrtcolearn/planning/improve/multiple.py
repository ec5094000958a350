"""Indirect multiple shooting of a whole path (`multiple_shooting`): one extremal from the
start into the goal region, the path's nodes as the segments' starts."""

from __future__ import annotations

from collections.abc import Callable
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn.planning.connections import (
    LAND_TOLERANCE,
    SHOOT_TOLERANCE,
    extremal_chain,
    terminal_conditions,
)
from rrtcolearn.planning.improve.common import costs_to_come, grafted, recorded
from rrtcolearn.planning.shooting import multiple_shoot
from rrtcolearn.planning.tree import Plan

if TYPE_CHECKING:
    from rrtcolearn.planning.rrt import RRTCoLearn

def _segments(durations: np.ndarray, longest: float) -> list[int]:
    """Positions (in the path, 0 first) where `multiple_shooting`'s segments start: the
    path's nodes, merged greedily from the start into segments that last at most
    ``longest`` (an edge longer than that is a segment of its own); ``durations`` are the
    path's edge durations in order."""
    starts, since = [0], 0.0
    for k, d in enumerate(durations):
        if since > 0.0 and since + d > longest + 1e-9:
            starts.append(k)
            since = 0.0
        since += d
    return starts


def multiple_shooting(planner: RRTCoLearn, plan: Plan, stop: Callable[[], bool] | None = None
                      ) -> Plan:
    """``plan`` with its whole path replaced by one extremal from the start into the goal
    region found by indirect multiple shooting (`shooting.multiple_shoot`) where that is
    cheaper; the same plan otherwise.

    Segments: the path's nodes merged into stretches of at most the data's longest
    extremal (``max_duration``: how far the learned steering and shooting reach), so M
    follows the path's duration. Each segment starts at its first node's state (the
    interior ones unknowns) with the costate of its first edge where that is an extremal,
    else U's prediction for (its first node, its last node); the total duration starts at
    the path's, split as the path splits it, and lasts at most the path's cost over w. The
    solution is built as a chain of extremal edges from the root, each simulated from where
    the previous one ended with its own segment's costate (costate continuity holds to the
    solve's tolerance), each checked like a planner edge (state box, obstacles, input limit,
    cut at its first state in the goal region), and kept as new leaves below the root if the
    chain ends in the goal region and is cheaper. ``stop()`` is asked before each Newton
    iteration. ``extra["multiple_shooting"]`` records the segments, whether the solve
    converged, the Newton iterations, whether the chain was kept and else why not."""
    record = {"segments": 0, "converged": False, "iterations": [0, 0], "kept": False,
              "why": None}
    sys, s, prob = planner.problem.system, planner.settings, planner.problem
    if not plan.solved or len(plan.path_nodes) < 3 or sys.params_from_costate is None:
        record["why"] = "nothing to do"
        return recorded(plan, planner.propagator, None, "multiple_shooting", record)
    n = sys.n_states
    prop, tree = planner.propagator, plan.tree
    path = list(plan.path_nodes)
    durations = tree.durations[path[1:]]
    best = float(costs_to_come(tree, path)[-1])
    starts = _segments(durations, s.max_duration)
    record["segments"] = len(starts)
    if len(starts) < 2:  # one segment: single shooting from the root, the goal walk's
        record["why"] = "one segment"
        return recorded(plan, prop, None, "multiple_shooting", record)
    bounds = [*starts, len(path) - 1]
    x = tree.states[path]
    lams = np.empty((len(starts), n))
    need_u = []
    for i, a in enumerate(starts):
        edge = path[a + 1]
        if not np.isnan(tree.costates[edge]).any():
            lams[i] = tree.costates[edge]
        else:
            need_u.append(i)
    if need_u:
        if planner.model is None:
            record["why"] = "no costate guess"
            return recorded(plan, prop, None, "multiple_shooting", record)
        a, b = np.array([bounds[i] for i in need_u]), np.array([bounds[i + 1] for i in need_u])
        shift = sys.wrap_shift(x[a])
        u = planner.model.query(np.hstack([x[a] + shift, x[b] + shift]))[1]
        lam_u, valid = sys.costate_from_params(x[a], u[:, :-1], s.time_weight)
        # where U's parameters give no costate: the nearest extremal edge's on the path
        has = np.flatnonzero(~np.isnan(tree.costates[path[1:]]).any(axis=1))
        for k, i in enumerate(need_u):
            if valid[k]:
                lams[i] = lam_u[k]
            elif has.size:
                lams[i] = tree.costates[path[1 + has[np.argmin(np.abs(has - starts[i]))]]]
            else:
                lams[i] = 0.0
    seg_durations = np.array([durations[a:b].sum() for a, b in pairwise(bounds)])
    longest = best / s.time_weight if s.time_weight > 0 else 4.0 * seg_durations.sum()
    stopped = [False]

    def halt() -> bool:
        stopped[0] = stopped[0] or (stop is not None and stop())
        return stopped[0]

    res = multiple_shoot(sys, x[0], lams, x[starts[1:]], seg_durations, terminal_conditions(prob),
                         time_weight=s.time_weight, dt=s.dt, max_duration=longest,
                         tolerance=SHOOT_TOLERANCE, grid_tolerance=LAND_TOLERANCE,
                         stop=halt)
    if res is None:
        record["why"] = "stopped" if stopped[0] else "not converged"
        return recorded(plan, prop, None, "multiple_shooting", record)
    record["converged"] = True
    record["iterations"] = list(res.iterations)
    chain = extremal_chain(prop, x[0], res.costates, res.steps)
    if chain is None:
        record["why"] = "edge check"
        return recorded(plan, prop, None, "multiple_shooting", record)
    cost = sum(e.cost for e in chain)
    if cost >= best - 1e-9:
        record["why"] = "not cheaper"
        return recorded(plan, prop, None, "multiple_shooting", record)
    record["kept"] = True
    new_path = grafted(tree, path, 0, [(edge, "shooting") for edge in chain], s.dt)
    return recorded(plan, prop, new_path, "multiple_shooting", record)

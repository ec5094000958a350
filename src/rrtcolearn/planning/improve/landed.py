"""Landed shortcuts (`landed_shortcuts`): stretches of a path joined by one extremal over
the same duration, landed on the stretch's end by Newton's method on the costate."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn.planning.connections import LAND_TOLERANCE
from rrtcolearn.planning.contracts import Edge
from rrtcolearn.planning.improve.common import (
    INTERIOR_MISSES,
    costs_to_come,
    grafted,
    reattached,
    recorded,
    station_pairs,
)
from rrtcolearn.planning.shooting import land
from rrtcolearn.planning.tree import Plan, PlannerData

if TYPE_CHECKING:
    from rrtcolearn.planning.rrt import RRTCoLearn

# `landed_shortcuts`: Newton's iterations of each landing (`land`'s default 12 landed 1 of
# 8 stretches of the shipped acrobot into its funnel, 60 landed 5: docs/anytime.md), and the
# least gain kept, as a fraction of the path's cost (a stretch that is one extremal already
# lands on itself, a few ulps cheaper, again and again)
LANDED_ITERATIONS = 60
LANDED_GAIN = 1e-6


def landed_shortcuts(planner: RRTCoLearn, plan: Plan,
                     stop: Callable[[], bool] | None = None) -> Plan:
    """``plan`` with stretches of its path joined by one extremal over the same duration
    wherever that is cheaper; the same plan when none is.

    A chain of extremals with costate jumps can be far dearer than one extremal between
    its ends over the same time: the shipped acrobot's paths reach the goal funnel through
    learned edges that cost 10-250 in 0.01-0.3 s (docs/anytime.md). `interior_shortcuts`
    misses most of these stretches: it asks for H* = 0 (a free duration) from the
    stretch's own or U's guess, and only where V accepts the query. Here a stretch from
    node a to node b (0 <= a < b; the dearest input first: its cost less w times its
    duration) is landed on x_b with its duration fixed (`shooting.land`, Newton's method on
    the costate) from the costate 0 (no input at the start) and from its first edge's
    costate. The rest of the path is simulated again from where the extremal ends
    (`reattached`); the chain is kept, as new leaves below node a, if every edge passes
    the planner's checks, it ends in the goal region and the path gets cheaper; the search
    then starts again on the new path. It stops after INTERIOR_MISSES stretches in a row
    that gave nothing, or once ``stop()`` is true (asked before each stretch).
    ``extra["landed"]`` records the stretches tried, the landings (tried, converged) and
    the chains kept.

    Over twice the duration too: on 8 acrobot first solutions the same costs but on 3
    seeds (4.27x against 4.53x, 5.57x against 6.59x, 4.46x against 5.11x the optimum) for
    2-5 times the CPU (0.27-1.53 s a path against 0.11-0.71 s); up to 8 times: 0.74-3.03 s
    a path (docs/anytime.md)."""
    sys, s = planner.problem.system, planner.settings
    record = {"stretches": 0, "landings": [0, 0], "kept": 0, "added": 0}
    if not plan.solved or len(plan.path_nodes) < 2 or sys.params_from_costate is None:
        plan.extra["landed"] = record
        return plan
    n, w = sys.n_states, s.time_weight
    prop, tree = planner.propagator, plan.tree
    lam, z0 = np.empty(n), np.empty(2 * n + 1)
    path = list(plan.path_nodes)
    best = float(costs_to_come(tree, path)[-1])
    tried: set[tuple[int, int]] = set()
    misses = 0
    while misses < INTERIOR_MISSES:
        come = costs_to_come(tree, path)
        ends = np.concatenate([[0.0], np.cumsum(tree.durations[path[1:]])])
        a, b = station_pairs(len(path))
        excess = come[b] - come[a] - w * (ends[b] - ends[a])  # the input's share of the cost
        keep = (excess > 0) & np.array([(path[i], path[j]) not in tried
                                        for i, j in zip(a, b, strict=True)], dtype=bool)
        order = np.flatnonzero(keep)[np.argsort(-excess[keep], kind="stable")]
        found = None
        for k in order:
            if misses >= INTERIOR_MISSES or (stop is not None and stop()):
                misses = INTERIOR_MISSES
                break
            i, j = int(a[k]), int(b[k])
            tried.add((path[i], path[j]))
            record["stretches"] += 1
            found = _landed(planner, tree, path, i, j, come, float(ends[j] - ends[i]), best,
                            lam, z0, record)
            if found is not None:
                break
            misses += 1
        if found is None:
            break
        misses = 0
        i, chain = found
        path = grafted(tree, path, i, chain, s.dt)
        record["added"] += len(chain)
        record["kept"] += 1
        best = float(costs_to_come(tree, path)[-1])
    return recorded(plan, prop, path if record["added"] else None, "landed", record)


def _landed(planner: RRTCoLearn, tree: PlannerData, path: list[int], a: int, b: int,
            come: np.ndarray, duration: float, best: float, lam: np.ndarray, z0: np.ndarray,
            record: dict) -> tuple[int, list[tuple[Edge, str | None]]] | None:
    """`landed_shortcuts`' try at the stretch of ``path`` from position a to b (lasting
    ``duration``): (a, the new chain of (edge, kind to record)), or None."""
    prop, s = planner.propagator, planner.settings
    sys = planner.problem.system
    n, w = sys.n_states, s.time_weight
    x0, target = tree.states[path[a]], tree.states[path[b]].copy()
    guesses = [np.zeros(n)]
    first = path[a + 1]
    if not np.isnan(tree.costates[first]).any():
        guesses.append(tree.costates[first].copy())
    steps = max(1, round(duration / s.dt))
    rest = path[b + 1 :]
    for guess in guesses:
        record["landings"][0] += 1
        costate = land(sys, x0, guess, steps, target, time_weight=w, dt=s.dt,
                       tolerance=LAND_TOLERANCE, max_iterations=LANDED_ITERATIONS)
        if costate is None:
            continue
        record["landings"][1] += 1
        z0[:n], z0[n : 2 * n], z0[2 * n] = x0, costate, 0.0
        if not prop.within_limit(z0):
            continue
        p = np.append(sys.params_from_costate(x0[None], costate[None])[0], steps * s.dt)
        edge = prop.extremal_edges(x0, p[None], costate[None])
        if edge is None or not (edge.hit or edge.steps == steps) or come[a] + edge.cost >= best:
            continue
        chain: list[tuple[Edge, str | None]] = [(edge, "shooting")]
        if not edge.hit:
            after = reattached(prop, tree, rest, edge.traj[-1, :n], lam, z0)
            if after is None:
                continue
            chain += [(e, tree.made_by.get(node)) for e, node in zip(after, rest, strict=False)]
        if come[a] + sum(e.cost for e, _ in chain) < best * (1.0 - LANDED_GAIN):
            return a, chain
    return None

"""Improve a solved plan in its own tree: interior shortcuts (a stretch of the path replaced
by one extremal, the rest re-attached), landed shortcuts (the same with the stretch's
duration kept, `landed_shortcuts`) and goal shortcuts by shooting (choose-parent for the
goal). `shortcut` runs all three, goal shortcuts first; it is the anytime scheme's
``improve``.
Indirect multiple shooting of the whole path (`multiple_shooting`) is here too; the anytime
scheme runs it before `shortcut` on each new best path, on an allowance of its own
(`anytime.solve_with_restarts`' ``first``; docs/anytime.md).

Interior shortcuts (`interior_shortcuts`): between nodes a < b of the path, one extremal
from x_a shot at x_b (`shooting.shoot`, a point target), from the stretch's first edge
where that is an extremal and from U's guess for (x_a, x_b) where V accepts the query. The
stretches J predicts to save most are tried first. The extremal lands within the rounding
of its duration to the RK4 grid of x_b, and is then put on x_b by Newton's method on its
costate with the duration fixed (`shooting.land`: H* = 0 is given up by about the rounding).
The edges after b are simulated again from there (held inputs by their inputs, extremals by
their steering parameters), or replaced by a goal tail from there; the chain is kept only
if every edge passes the planner's checks, it ends in the goal region and the path is
cheaper. docs/anytime.md has what it gains, system by system.

Goal shortcuts (`goal_shortcuts`). A first solution is a chain of extremals (and, with an
input box, constant-input edges) with a jump in the costate at every node: each edge is
locally optimal, the chain is not. The optimum of a free-final-time problem is a single
extremal from the start to the goal region (Pontryagin), so the path gets cheaper as its
tail is replaced by one extremal from ever earlier nodes.

`goal_shortcuts` walks the path backwards from the last edge's parent to the root. From
node i it tries two kinds of tail into the goal region:
- one extremal by shooting (`shooting.shoot`) from two guesses: the path's own edge out of i
  (its steering parameters, with the duration of the rest of the path: the chain after i is
  what the extremal has to straighten), and U's prediction for (x_i, goal) where the learned
  J says that edge may be cheaper;
- the LQR goal loop (`lqr.GoalLQR`, as the planner's LQR connection runs it: a chain of
  constant-input edges), where the settings allow it and the goal has an equilibrium.
The cheapest tail that reaches the goal region, passes every check of a planner edge (state
box, obstacles, input limit) and makes the cost to come of x_i plus its cost less than the
best path's is added to the tree as new leaves below node i, and becomes the best path; the
walk goes on from the node before i on that path. Nothing in the tree is moved or deleted,
so the tree stays a tree: every node is reached from the root by edges that re-simulate, and
its cost to come is the sum of its path's edge costs.

The longest extremal worth shooting from node i is bounded by the cost: one that ends the
path cheaper lasts at most (best - cost to come of x_i) / w.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn.integrate import propagate_draws
from rrtcolearn.planning.connections import (
    LAND_TOLERANCE,
    SHOOT_TOLERANCE,
    FunnelConnection,
    extremal_chain,
    goal_lqr,
    lqr_chain,
    shoot_edge,
    terminal_conditions,
)
from rrtcolearn.planning.contracts import Edge, add_edge
from rrtcolearn.planning.learned import goal_query
from rrtcolearn.planning.propagator import Propagator
from rrtcolearn.planning.shooting import land, multiple_shoot, shoot
from rrtcolearn.planning.tree import Plan, PlannerData

if TYPE_CHECKING:
    from rrtcolearn.planning.rrt import RRTCoLearn

__all__ = ["goal_shortcuts", "interior_shortcuts", "landed_shortcuts", "multiple_shooting",
           "shortcut", "start_funnel"]

# an interior shortcut is shot at its stretch's end node to SHOOT_TOLERANCE, the state
# residual (its end is then off by the rounding of its duration to the RK4 grid), then put
# on it to LAND_TOLERANCE with its duration on the grid (`shooting.land`; Newton's method
# converges quadratically): the tolerances of multiple shooting (`connections`)
# the stretches tried in a row without a cheaper path before the interior search gives up
INTERIOR_MISSES = 24
# a re-attached path's last edge may run this many times its steps to reach the goal region
REATTACH_STRETCH = 2
# `landed_shortcuts`: Newton's iterations of each landing (`land`'s default 12 landed 1 of
# 8 stretches of the shipped acrobot into its funnel, 60 landed 5: docs/anytime.md), and the
# least gain kept, as a fraction of the path's cost (a stretch that is one extremal already
# lands on itself, a few ulps cheaper, again and again)
LANDED_ITERATIONS = 60
LANDED_GAIN = 1e-6
# the pairwise searches (`_pairs`, `landed_shortcuts`) consider at most this many of a
# path's nodes, evenly spaced along it (the first and the last kept): every pair of a path of
# thousands of one-step edges (an LQR chain) is millions of model queries. Paths of the
# shipped problems have tens of nodes and are searched whole.
PAIR_NODES = 192
# `_pairs` asks the model for this many stretches at a time and ``stop()`` between blocks
PAIR_BLOCK = 4096


def _recorded(plan: Plan, prop, path: list[int] | None, key: str, record: dict) -> Plan:
    """``plan`` with ``record`` as ``extra[key]``, and, when an improvement found a new
    ``path`` (None: none), that path as the plan's, with its goal distance and duration by
    edge kind."""
    if path is None:
        plan.extra[key] = record
        return plan
    out = replace(plan, path_nodes=path,
                  end_goal_distance=prop.end_goal_distance(plan.tree.states[path[-1]]),
                  extra={**plan.extra, key: record})
    out.extra["duration_by"] = out.duration_by
    return out


def _costs_to_come(tree: PlannerData, path: list[int]) -> np.ndarray:
    """Cost to come of each node of ``path`` (path order)."""
    return np.concatenate([[0.0], np.cumsum(tree.costs[path[1:]])])


def goal_shortcuts(planner: RRTCoLearn, plan: Plan, stop: Callable[[], bool] | None = None
                   ) -> Plan:
    """``plan`` (solved, from ``planner``'s last `solve`) with its tail replaced by a single
    extremal or an LQR chain to the goal wherever that is cheaper; the same plan when nothing
    is.

    ``planner`` is the `RRTCoLearn` that made the plan (its problem, settings, learned U and
    edge checks, ``planner.propagator``, are used). Stops early once ``stop()`` is true
    (checked before each node). ``extra["shortcuts"]`` records the edges added, the shots
    and the LQR loops tried.
    """
    if not plan.solved or len(plan.path_nodes) < 3:
        return plan
    prob, sys, s = planner.problem, planner.problem.system, planner.settings
    n = sys.n_states
    w = s.time_weight
    tree = plan.tree
    lam, z0 = np.empty(n), np.empty(2 * n + 1)
    # the LQR connection's loop, where the settings allow it and the goal has an equilibrium
    prop = planner.propagator
    lqr = goal_lqr(prop) if s.goal_lqr is not False else None
    if isinstance(lqr, str):  # no equilibrium at the goal, or an unstable loop
        lqr = None
    can_shoot = sys.params_from_costate is not None
    path = list(plan.path_nodes)
    best = float(_costs_to_come(tree, path)[-1])
    added, shots, loops = 0, 0, 0
    pos = len(path) - 2  # the last edge's parent: U's guess may beat the edge the tree had
    while pos >= 0:
        if stop is not None and stop():
            break
        come = _costs_to_come(tree, path)
        node = path[pos]
        budget = (best - come[pos]) / w if w > 0 else np.inf
        if budget <= s.dt:
            pos -= 1
            continue
        x0 = tree.states[node]
        tails = []  # chains of edges from x0 into the goal region
        guesses = []
        child = path[pos + 1]
        if can_shoot and not np.isnan(tree.costates[child]).any():
            rest = float(np.sum(tree.durations[path[pos + 1:]]))
            guesses.append((tree.params[child], min(rest, budget)))
        if can_shoot and planner.model is not None:
            # U's guess where J says the edge may be cheaper (V's verdict is not asked: far
            # from the data U's guess still converges often enough to pay)
            query = goal_query(x0, sys.wrap_shift(x0[None])[0], prob.goal_offset(x0[None])[0])
            j, u, _ = (a[0] for a in planner.model.query(query))
            if come[pos] + j < best:
                guesses.append((u[:-1], min(max(u[-1], s.dt), budget)))
        for params, duration in guesses:
            shots += 1
            edge = shoot_edge(prop, x0, params, duration, max(budget, s.dt), lam, z0)
            if edge is not None:
                tails.append([edge])
        if lqr is not None:
            loops += 1
            chain, _ = lqr_chain(prop, lqr, x0)
            if chain is not None:
                tails.append(chain)
        costs = [sum(e.cost for e in t) for t in tails]
        if costs and come[pos] + min(costs) < best - 1e-9:
            parent = node
            path = path[: pos + 1]
            tail = tails[int(np.argmin(costs))]
            for edge in tail:
                parent = add_edge(tree, parent, edge, s.dt)
                # a shortcut is one extremal by shooting, or an LQR chain of held inputs
                tree.made_by[parent] = "lqr" if edge.control is not None else "shooting"
                path.append(parent)
                added += 1
            best = float(come[pos] + min(costs))
        pos -= 1
    return _recorded(plan, prop, path if added else None, "shortcuts",
                     {"added": added, "shots": shots, "lqr_loops": loops})


def _held_edge(propagator: Propagator, x0: np.ndarray, u: np.ndarray, steps: int
               ) -> Edge | None:
    """The held input ``u`` from ``x0`` for ``steps`` RK4 steps, checked like a
    random-control edge (state constraints, obstacles) and cut at its first state in the
    goal region; None where a state fails a check before that."""
    prob, s = propagator.problem, propagator.settings
    flat, _, stops = propagate_draws(prob.system, x0, u[None], np.array([steps]), s.dt,
                                     *propagator.box)
    if stops[0]:
        return None
    if prob.validity and not prob.validity(flat).all():
        return None
    hits = np.flatnonzero(propagator.goal_mask(flat))
    end = int(hits[0]) + 1 if hits.size else steps
    traj = np.vstack([x0[None], flat[:end]])
    return Edge(traj, end, end * s.dt * propagator.hold_rate(u), float(np.abs(u).max()),
                bool(hits.size), control=u.copy())


def _replayed(propagator: Propagator, tree: PlannerData, node: int, x0: np.ndarray,
              steps: int, lam: np.ndarray, z0: np.ndarray) -> Edge | None:
    """Node ``node``'s edge simulated again from ``x0`` for ``steps`` steps: a held input by
    its input, an extremal by its costate (not by its steering parameters: an interior
    shortcut's costate is off H* = 0, and its parameters do not give it back), checked like
    every edge and cut at its first state in the goal region; None where it fails a check
    before that."""
    if not np.isnan(tree.controls[node]).any():
        return _held_edge(propagator, x0, tree.controls[node], steps)
    n = tree.states.shape[1]
    lam[:] = tree.costates[node]
    z0[:n], z0[n : 2 * n], z0[2 * n] = x0, lam, 0.0
    if not propagator.within_limit(z0):
        return None
    params = np.append(tree.params[node], steps * propagator.settings.dt)
    edge = propagator.extremal_edges(x0, params[None], lam[None])
    return edge if edge is not None and (edge.hit or edge.steps == steps) else None


def _reattached(propagator: Propagator, tree: PlannerData, rest: list[int], x0: np.ndarray,
                lam: np.ndarray, z0: np.ndarray) -> list[Edge] | None:
    """The path's edges ``rest`` (node indices, in order) simulated again one after the
    other from ``x0``; the last may run up to REATTACH_STRETCH times its steps to reach the
    goal region. None unless every edge passes its checks and the chain ends in the goal
    region (it stops at the first edge that gets there)."""
    s = propagator.settings
    chain, x = [], x0
    for k, node in enumerate(rest):
        steps = max(1, round(tree.durations[node] / s.dt))
        edge = _replayed(propagator, tree, node, x, steps, lam, z0)
        if edge is not None and not edge.hit and k == len(rest) - 1:
            edge = _replayed(propagator, tree, node, x, REATTACH_STRETCH * steps, lam, z0)
        if edge is None:
            return None
        chain.append(edge)
        if edge.hit:
            return chain
        x = edge.traj[-1, : tree.states.shape[1]]
    return None


def _goal_tail(planner: RRTCoLearn, lqr, x0: np.ndarray, budget: float,
               lam: np.ndarray, z0: np.ndarray) -> list[Edge] | None:
    """The cheaper of U's extremal by shooting and the LQR chain from ``x0`` into the goal
    region (the goal walk's tails), or None."""
    prop, s = planner.propagator, planner.settings
    prob, sys = planner.problem, planner.problem.system
    tails = []
    if planner.model is not None:
        query = goal_query(x0, sys.wrap_shift(x0[None])[0], prob.goal_offset(x0[None])[0])
        u = planner.model.query(query)[1][0]
        edge = shoot_edge(prop, x0, u[:-1], min(max(u[-1], s.dt), budget), max(budget, s.dt),
                          lam, z0)
        if edge is not None:
            tails.append([edge])
    if lqr is not None:
        chain, _ = lqr_chain(prop, lqr, x0)
        if chain is not None:
            tails.append(chain)
    return min(tails, key=lambda t: sum(e.cost for e in t), default=None)


def _stations(count: int) -> np.ndarray:
    """Positions of a path's first ``count`` nodes that the pairwise searches consider: all
    of them, or PAIR_NODES evenly spaced (the first and the last among them) on a longer
    path."""
    if count <= PAIR_NODES:
        return np.arange(count)
    return np.unique(np.round(np.linspace(0, count - 1, PAIR_NODES)).astype(int))


def _station_pairs(count: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of positions (a < b) among `_stations` (count)."""
    at = _stations(count)
    i, j = np.triu_indices(at.size, 1)
    return at[i], at[j]


def _pairs(planner: RRTCoLearn, tree: PlannerData, path: list[int], come: np.ndarray,
           tried: set[tuple[int, int]], stop: Callable[[], bool] | None = None
           ) -> list[tuple[int, int, float, np.ndarray]]:
    """Stretches of ``path`` worth a shortcut, most promising first: positions (a, b),
    0 <= a < b < the path's last node (among `_stations`), spanning two edges or more or
    one held input, not tried yet, where V accepts the query (x_a, x_b) and J predicts one
    extremal undercuts the stretch's cost; with J's prediction and U's (k + 1,). The model
    is asked PAIR_BLOCK stretches at a time; none are returned once ``stop()`` is true
    (asked between blocks)."""
    sys = planner.problem.system
    held = np.isnan(tree.costates[path]).any(axis=1)  # node's edge is a held input
    a, b = _station_pairs(len(path) - 1)
    keep = (b - a >= 2) | held[b]
    keep &= np.array([(path[i], path[j]) not in tried for i, j in zip(a, b, strict=True)],
                     dtype=bool)
    a, b = a[keep], b[keep]
    if not a.size:
        return []
    x0, x1 = tree.states[path][a], tree.states[path][b]
    shift = sys.wrap_shift(x0)
    query = np.hstack([x0 + shift, x1 + shift])
    blocks = []
    for k in range(0, len(query), PAIR_BLOCK):
        if k and stop is not None and stop():
            return []
        blocks.append(planner.model.query(query[k : k + PAIR_BLOCK]))
    j, u, valid = (np.concatenate(parts) for parts in zip(*blocks, strict=True)) \
        if len(blocks) > 1 else blocks[0]
    # J and U mean something only where V accepts the query: far from the data k-NN's J
    # is its neighbours' (sparse_rrt's cart-pole: 0.9 for the whole 40 m transfer)
    gain = np.where(valid, come[b] - come[a] - j, -np.inf)
    order = np.argsort(-gain, kind="stable")
    order = order[gain[order] > 0]
    return [(int(a[k]), int(b[k]), float(j[k]), u[k]) for k in order]


def interior_shortcuts(planner: RRTCoLearn, plan: Plan,
                       stop: Callable[[], bool] | None = None) -> Plan:
    """``plan`` with stretches of its path replaced by one extremal each wherever that is
    cheaper; the same plan when none is.

    A stretch from node a to node b (`_pairs`: the greatest saving J predicts first) is
    shot at x_b (`shooting.shoot`) from the first edge's own steering parameters (an
    extremal's) with the stretch's duration, from U's costate for (x_a, x_b) with the
    stretch's duration, and from U's whole guess. The extremal ends near x_b (its duration
    is a whole number of RK4 steps), then on it by Newton's method on its costate alone
    (`shooting.land`). The edges after b are simulated again from where it ends
    (`_reattached`), else replaced by a goal tail from there (`_goal_tail`). The new chain
    is kept, as new leaves below node a, if every edge passes the planner's checks, it ends
    in the goal region and the path gets cheaper; the search then starts again on the new
    path. It stops after INTERIOR_MISSES stretches in a row that gave nothing, or once
    ``stop()`` is true (asked before each stretch). ``extra["interior"]`` records the
    stretches tried, the shots by guess (tried, converged), the shots put on x_b
    (``on_target``), the chains kept, those that needed a goal tail, and the shots whose
    rest of the path could be neither re-attached nor replaced by a goal tail (``lost``).
    """
    if not plan.solved:
        return plan
    sys, s = planner.problem.system, planner.settings
    record = {"stretches": 0, "shots": {"edge": [0, 0], "U_stretch": [0, 0], "U": [0, 0]},
              "on_target": 0, "kept": 0, "goal_tails": 0, "lost": 0, "added": 0}
    if len(plan.path_nodes) < 3 or planner.model is None or sys.params_from_costate is None:
        plan.extra["interior"] = record
        return plan
    n = sys.n_states
    prop, tree = planner.propagator, plan.tree
    lam, z0 = np.empty(n), np.empty(2 * n + 1)
    lqr = goal_lqr(prop) if s.goal_lqr is not False else None
    lqr = None if isinstance(lqr, str) else lqr
    path = list(plan.path_nodes)
    best = float(_costs_to_come(tree, path)[-1])
    tried: set[tuple[int, int]] = set()
    misses = 0
    while misses < INTERIOR_MISSES:
        come = _costs_to_come(tree, path)
        pairs = _pairs(planner, tree, path, come, tried, stop)
        if not pairs:
            break
        found = None
        for a, b, _, u in pairs:
            if misses >= INTERIOR_MISSES or (stop is not None and stop()):
                misses = INTERIOR_MISSES
                break
            tried.add((path[a], path[b]))
            record["stretches"] += 1
            found = _shortcut_stretch(planner, tree, path, a, b, u, come, best, lqr, lam, z0,
                                      record)
            if found is not None:
                break
            misses += 1
        if found is None:
            break
        misses = 0
        a, chain, tail = found
        path = _grafted(tree, path, a, chain, s.dt, record)
        record["goal_tails"] += tail
        best = float(_costs_to_come(tree, path)[-1])
    return _recorded(plan, prop, path if record["added"] else None, "interior", record)


def _grafted(tree: PlannerData, path: list[int], a: int, chain: list, dt: float,
             record: dict) -> list[int]:
    """``path`` up to position a, then ``chain``'s (edge, kind) added as new leaves below it
    (a kind of None keeps the edge's default); counts the edges added and the chain kept in
    ``record``. The interior and landed shortcuts' way of keeping a chain."""
    parent, path = path[a], path[: a + 1]
    for edge, kind in chain:
        parent = add_edge(tree, parent, edge, dt)
        if kind is not None:
            tree.made_by[parent] = kind
        path.append(parent)
        record["added"] += 1
    record["kept"] += 1
    return path


def _shortcut_stretch(planner: RRTCoLearn, tree: PlannerData, path: list[int], a: int, b: int,
                      u: np.ndarray, come: np.ndarray, best: float, lqr, lam: np.ndarray,
                      z0: np.ndarray, record: dict
                      ) -> tuple[int, list[tuple[Edge, str | None]], bool] | None:
    """`interior_shortcuts`' try at the stretch of ``path`` from position a to b: (a, the
    new chain of (edge, kind to record), whether it ends in a goal tail), or None when no
    guess lands or the chain is no cheaper than ``best``."""
    prop, s = planner.propagator, planner.settings
    sys = planner.problem.system
    n = sys.n_states
    x0, target = tree.states[path[a]], tree.states[path[b]].copy()
    stretch_cost = come[b] - come[a]
    stretch = float(np.sum(tree.durations[path[a + 1 : b + 1]]))
    # an extremal cheaper than the stretch lasts at most its cost over w
    longest = min(stretch_cost / s.time_weight if s.time_weight > 0 else np.inf,
                  2.0 * stretch + s.max_duration)
    # the guesses in the order they converged most often on the shipped acrobot's k-NN model
    # (docs/anytime.md: 18, 14 and 3 of 38 stretches): the stretch's first extremal, U's
    # costate with the stretch's duration, U's own guess
    guesses = []
    first = path[a + 1]
    if not np.isnan(tree.costates[first]).any():
        guesses.append(("edge", tree.params[first], min(stretch, longest)))
    guesses.append(("U_stretch", u[:-1], float(np.clip(stretch, s.dt, longest))))
    guesses.append(("U", u[:-1], float(np.clip(u[-1], s.dt, longest))))
    rest = path[b + 1 :]
    for name, params, duration in guesses:
        record["shots"][name][0] += 1
        res = shoot(sys, x0, params, duration, lambda x: x - target,
                    time_weight=s.time_weight, dt=s.dt, max_duration=longest,
                    tolerance=SHOOT_TOLERANCE, max_iterations=20)
        if res is None:
            continue
        record["shots"][name][1] += 1
        # on x_b exactly, the duration kept on the RK4 grid (`shooting.land`): the rest of
        # the path then starts where it did; else the extremal shot, within the rounding
        start = sys.costate_from_params(x0[None], res.params[None], s.time_weight)[0][0]
        exact = land(sys, x0, start, res.steps, target, time_weight=s.time_weight, dt=s.dt,
                     tolerance=LAND_TOLERANCE)
        record["on_target"] += exact is not None
        costate = start if exact is None else exact
        params = res.params if exact is None else \
            sys.params_from_costate(x0[None], exact[None])[0]
        p = np.append(params, res.steps * s.dt)
        z0[:n], z0[n : 2 * n], z0[2 * n] = x0, costate, 0.0
        if not prop.within_limit(z0):
            continue
        edge = prop.extremal_edges(x0, p[None], costate[None])
        if edge is None or not (edge.hit or edge.steps == res.steps) or \
                come[a] + edge.cost >= best:
            continue
        chain: list[tuple[Edge, str | None]] = [(edge, "shooting")]
        tail = False
        if not edge.hit:
            landed = edge.traj[-1, :n]
            after = _reattached(prop, tree, rest, landed, lam, z0)
            if after is not None:
                chain += [(e, tree.made_by.get(node)) for e, node in zip(after, rest,
                                                                           strict=False)]
            else:
                left = (best - come[a] - edge.cost) / s.time_weight if s.time_weight > 0 \
                    else np.inf
                if left <= s.dt:
                    continue
                goal = _goal_tail(planner, lqr, landed, left, lam, z0)
                if goal is None:
                    record["lost"] += 1
                    continue
                chain += [(e, "lqr" if e.control is not None else "shooting") for e in goal]
                tail = True
        if come[a] + sum(e.cost for e, _ in chain) < best - 1e-9:
            return a, chain, tail
    return None


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
    (`_reattached`); the chain is kept, as new leaves below node a, if every edge passes
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
    best = float(_costs_to_come(tree, path)[-1])
    tried: set[tuple[int, int]] = set()
    misses = 0
    while misses < INTERIOR_MISSES:
        come = _costs_to_come(tree, path)
        ends = np.concatenate([[0.0], np.cumsum(tree.durations[path[1:]])])
        a, b = _station_pairs(len(path))
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
        path = _grafted(tree, path, i, chain, s.dt, record)
        best = float(_costs_to_come(tree, path)[-1])
    return _recorded(plan, prop, path if record["added"] else None, "landed", record)


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
            after = _reattached(prop, tree, rest, edge.traj[-1, :n], lam, z0)
            if after is None:
                continue
            chain += [(e, tree.made_by.get(node)) for e, node in zip(after, rest, strict=False)]
        if come[a] + sum(e.cost for e, _ in chain) < best * (1.0 - LANDED_GAIN):
            return a, chain
    return None


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
        return _recorded(plan, planner.propagator, None, "multiple_shooting", record)
    n = sys.n_states
    prop, tree = planner.propagator, plan.tree
    path = list(plan.path_nodes)
    durations = tree.durations[path[1:]]
    best = float(_costs_to_come(tree, path)[-1])
    starts = _segments(durations, s.max_duration)
    record["segments"] = len(starts)
    if len(starts) < 2:  # one segment: single shooting from the root, the goal walk's
        record["why"] = "one segment"
        return _recorded(plan, prop, None, "multiple_shooting", record)
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
            return _recorded(plan, prop, None, "multiple_shooting", record)
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
        return _recorded(plan, prop, None, "multiple_shooting", record)
    record["converged"] = True
    record["iterations"] = list(res.iterations)
    chain = extremal_chain(prop, x[0], res.costates, res.steps)
    if chain is None:
        record["why"] = "edge check"
        return _recorded(plan, prop, None, "multiple_shooting", record)
    cost = sum(e.cost for e in chain)
    if cost >= best - 1e-9:
        record["why"] = "not cheaper"
        return _recorded(plan, prop, None, "multiple_shooting", record)
    parent, new_path = path[0], [path[0]]
    for edge in chain:
        parent = add_edge(tree, parent, edge, s.dt)
        tree.made_by[parent] = "shooting"
        new_path.append(parent)
    record["kept"] = True
    return _recorded(plan, prop, new_path, "multiple_shooting", record)


# `start_funnel` tries the pool's nearest extremal again only once it is this much nearer
# than the last one tried (each try, a continuation and multiple shooting, costs 0.1-1.5 s)
AIM_RETRY = 0.7


def start_funnel(planner: RRTCoLearn, plan: Plan, stop: Callable[[], bool] | None = None
                 ) -> Plan:
    """``plan``'s path replaced by a funnel continuation from the start where that is
    cheaper: rounds of the query's search for goal-funnel extremals through the start
    (`funnel.AimedSearch`, kept from call to call until its rounds are done), each round
    followed by the funnel connection's steering from the start along the pool's extremal
    passing nearest it (`FunnelConnection.steer_from`) when that one is new and within the
    funnel's radius. The path found is added below the root (edges ``funnel``).
    ``stop()`` is asked before each round. ``extra["start_funnel"]``: the rounds run, the
    nearest distance reached, the continuations tried and whether a path was kept.

    The acrobot's optimum is one 5.4-s extremal from the start; its first paths are chains
    whose junctions no shooting from them removes, while the funnel's extremals pass 0.85
    from the start and, after a few rounds, within 0.01-0.1 (docs/anytime.md)."""
    record = {"rounds": 0, "nearest": None, "tries": 0, "kept": False}
    prob, sys, prop = planner.problem, planner.problem.system, planner.propagator
    stream = planner.query_funnel()
    tree = plan.tree
    search = None if stream is None or not plan.solved or sys.params_from_costate is None \
        else stream.aimed(tree.states[0], sys, prob.offset_to)
    if search is None:
        return _recorded(plan, prop, None, "start_funnel", record)
    radius = planner.settings.funnel_radius
    best = float(_costs_to_come(tree, plan.path_nodes)[-1])
    x0 = tree.states[0]
    found, tried = None, np.inf
    # while an extremal near the start could still undercut the path (its cost to go from
    # its state nearest the start below the path's cost): on the shipped cart-pole they
    # cost 4-7x the optimum, its anytime paths 1.0-1.3x
    while not (stop is not None and stop()) and search.cheapest < best:
        funnel = search.step(stream.build)
        if funnel is None:
            break
        record["rounds"] += 1
        # the pool's nearest extremal, at its nearest state, if new and within the radius
        dist = search.distances(funnel)
        j = int(np.argmin(dist)) if len(dist) else -1
        if j < 0 or dist[j] > radius or dist[j] > AIM_RETRY * tried or \
                funnel.cost_to_go[j] >= best:
            continue
        tried = float(dist[j])
        record["tries"] += 1
        chain = FunnelConnection(prop, funnel).steer_from(x0, dist[j : j + 1],
                                                          np.array([j]), radius, own=True)
        cost = np.inf if chain is None else float(sum(e.cost for e in chain))
        if cost < best - 1e-9:
            best, found = cost, chain
    record["nearest"] = search.nearest
    if found is None:
        return _recorded(plan, prop, None, "start_funnel", record)
    parent, path = 0, [0]
    for edge in found:
        parent = add_edge(tree, parent, edge, planner.settings.dt)
        tree.made_by[parent] = "funnel"
        path.append(parent)
    record["kept"] = True
    return _recorded(plan, prop, path, "start_funnel", record)


def shortcut(planner: RRTCoLearn, plan: Plan, stop: Callable[[], bool] | None = None
             ) -> Plan:
    """``plan`` improved in its own tree: its tail replaced by an extremal or an LQR chain
    into the goal region (`goal_shortcuts`), then stretches of what is left by single
    extremals (`interior_shortcuts`), then stretches by single extremals over the same
    duration (`landed_shortcuts`), then the whole path by the goal funnel's extremal
    through the start where one undercuts it (`start_funnel`, last: it takes what the
    others leave of the allowance; run first it cost the acrobot's shortcuts their gains,
    median 4.63x -> 5.11x on seeds 0-7); ``stop`` as all four take it. The anytime scheme's
    ``improve`` (``plan.anytime``).

    Not `multiple_shooting`: within this allowance it was cut on 341 of 343 tries (run
    last) or took the allowance the goal and interior shortcuts pay with (run first); the
    anytime scheme gives it one of its own (``first``; docs/anytime.md).

    Goal shortcuts first: where one extremal reaches the goal from early on (the pendulum)
    nothing is left for the interior to do, and under the anytime scheme's allowance the
    interior search run first left the goal walk too little CPU (the pendulum at u_max = 1,
    10 s: 5.785 against 5.668 on seed 0, 121 solves against 160)."""
    plan = landed_shortcuts(planner, interior_shortcuts(planner, goal_shortcuts(planner, plan,
                                                                                 stop), stop),
                            stop)
    return start_funnel(planner, plan, stop)

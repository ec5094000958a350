"""Interior shortcuts (`interior_shortcuts`): between nodes a < b of the path, one extremal
from x_a shot at x_b (`shooting.shoot`, a point target), from the stretch's first edge
where that is an extremal and from U's guess for (x_a, x_b) where V accepts the query. The
stretches J predicts to save most are tried first. The extremal lands within the rounding
of its duration to the RK4 grid of x_b, and is then put on x_b by Newton's method on its
costate with the duration fixed (`shooting.land`: H* = 0 is given up by about the rounding).
The edges after b are simulated again from there (held inputs by their inputs, extremals by
their steering parameters), or replaced by a goal tail from there; the chain is kept only
if every edge passes the planner's checks, it ends in the goal region and the path is
cheaper. docs/anytime.md has what it gains, system by system.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn.integrate import rollout
from rrtcolearn.planning.connections import LAND_TOLERANCE, SHOOT_TOLERANCE
from rrtcolearn.planning.contracts import Edge
from rrtcolearn.planning.improve.common import (
    INTERIOR_MISSES,
    PAIR_NODES,
    costs_to_come,
    grafted,
    reattached,
    recorded,
    station_pairs,
)
from rrtcolearn.planning.improve.goal import goal_tail
from rrtcolearn.planning.shooting import land, shoot
from rrtcolearn.planning.tree import Plan, PlannerData

if TYPE_CHECKING:
    from rrtcolearn.planning.rrt import RRTCoLearn

# an interior shortcut is shot at its stretch's end node to SHOOT_TOLERANCE, the state
# residual (its end is then off by the rounding of its duration to the RK4 grid), then put
# on it to LAND_TOLERANCE with its duration on the grid (`shooting.land`; Newton's method
# converges quadratically): the tolerances of multiple shooting (`connections`)
# `_pairs` asks the model for this many stretches at a time and ``stop()`` between blocks
PAIR_BLOCK = 4096


def _pieces(planner: RRTCoLearn, tree: PlannerData, path: list[int], count: int
            ) -> tuple[list[int], dict[int, int]]:
    """``path`` with its edges cut into pieces of at most ``span`` RK4 steps, the span such
    that the path has about ``count`` nodes, added as new leaves (the edges after the first
    one cut copied below the pieces), and a dict from each new node to the path node whose
    edge it is (a piece of). A piece's states are its edge's own (its stored trajectory);
    an extremal piece starts with the edge's costate integrated again to its start (an
    edge whose integration does not give back its states and cost is kept whole) and
    records its own largest |u*|, a held input's piece holds the same input. The same path
    and {} where no edge is longer."""
    s, sys, prop = planner.settings, planner.problem.system, planner.propagator
    n = sys.n_states
    steps = [len(tree.trajectories[i]) - 1 for i in path[1:]]
    span = max(1, -(-sum(steps) // max(1, count)))
    if not steps or max(steps) <= span:
        return path, {}
    new, origin, parent = [path[0]], {}, path[0]
    for node, k in zip(path[1:], steps, strict=True):
        traj = tree.trajectories[node]
        held = not np.isnan(tree.controls[node]).any()
        z = None
        if k > span and not held:
            z = rollout(sys, np.concatenate([tree.states[tree.parents[node]], tree.costates[node],
                                             [0.0]]), s.time_weight, s.dt, k)
            if not (np.array_equal(z[:, :n], traj[:, :n]) and
                    abs(z[-1, 2 * n] - tree.costs[node]) <= 1e-9 * max(1.0, abs(tree.costs[node]))):
                z = None
        cut = k > span and (held or z is not None)
        if not cut and parent == tree.parents[node]:
            new.append(node)
            parent = node
            continue
        if not cut:  # the edge as it is, below the pieces before it
            pieces = [Edge(traj, k, tree.costs[node], tree.max_abs_u[node], False,
                           np.append(tree.params[node], k * s.dt), tree.costates[node],
                           tree.controls[node] if held else None)]
        elif held:
            u = tree.controls[node]
            pieces = [Edge(traj[s0 : s1 + 1], s1 - s0, (s1 - s0) * s.dt * prop.hold_rate(u),
                           tree.max_abs_u[node], False, control=u)
                      for s0, s1 in pairwise([*range(0, k, span), k])]
        else:
            pieces = []
            for s0, s1 in pairwise([*range(0, k, span), k]):
                lam0 = z[s0, n : 2 * n]
                params = sys.params_from_costate(z[s0, :n][None], lam0[None])[0]
                top = max(sys.input_max_abs_jit(z[r]) for r in range(s0, s1 + 1))
                pieces.append(Edge(traj[s0 : s1 + 1, :n], s1 - s0,
                                   float(z[s1, 2 * n] - z[s0, 2 * n]), float(top), False,
                                   np.append(params, (s1 - s0) * s.dt), lam0))
        new = grafted(tree, new, len(new) - 1,
                      [(edge, tree.made_by.get(node)) for edge in pieces], s.dt)
        origin.update(dict.fromkeys(new[-len(pieces):], origin.get(node, node)))
        parent = new[-1]
    return new, origin


def _pairs(planner: RRTCoLearn, tree: PlannerData, path: list[int], come: np.ndarray,
           tried: set[tuple[int, int]], stop: Callable[[], bool] | None = None,
           origin: dict[int, int] | None = None) -> list[tuple[int, int, float, np.ndarray]]:
    """Stretches of ``path`` worth a shortcut, most promising first: positions (a, b),
    0 <= a < b < the path's last node (among `common.station_pairs`), spanning two edges or more or
    one held input, not tried yet, where V accepts the query (x_a, x_b) and J predicts one
    extremal undercuts the stretch's cost; with J's prediction and U's (k + 1,). The model
    is asked PAIR_BLOCK stretches at a time; none are returned once ``stop()`` is true
    (asked between blocks)."""
    sys = planner.problem.system
    held = np.isnan(tree.costates[path]).any(axis=1)  # node's edge is a held input
    a, b = station_pairs(len(path) - 1)
    keep = (b - a >= 2) | held[b]
    if origin:  # not within one extremal cut into pieces (`_pieces`): it is one already
        of = np.array([origin.get(i, i) for i in path])
        keep &= held[b] | (of[a + 1] != of[b])
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
    (`reattached`), else replaced by a goal tail from there (`goal_tail`). The new chain
    is kept, as new leaves below node a, if every edge passes the planner's checks, it ends
    in the goal region and the path gets cheaper; the search then starts again on the new
    path. It stops after INTERIOR_MISSES stretches in a row that gave nothing, or once
    ``stop()`` is true (asked before each stretch). ``extra["interior"]`` records the
    stretches tried, the shots by guess (tried, converged), the shots put on x_b
    (``on_target``), the chains kept, those that needed a goal tail, and the shots whose
    rest of the path could be neither re-attached nor replaced by a goal tail (``lost``).
    """
    return _shortcuts(planner, plan, stop, cut=False)


def piece_shortcuts(planner: RRTCoLearn, plan: Plan,
                    stop: Callable[[], bool] | None = None) -> Plan:
    """`interior_shortcuts` between stations along the path's edges: the path cut into
    pieces first (`_pieces`: about PAIR_NODES nodes in all, as new leaves), stretches
    within one extremal edge left out (it is one extremal already). A path of a few long
    edges (the unicycle's among obstacles, 7-20 edges) gives the interior search few
    stretches, none of them the detours inside an edge. ``extra["pieces"]`` records what
    ``extra["interior"]`` does, and ``pieces``: the nodes the cutting added (left in the
    tree as leaves whether a shortcut is kept or not)."""
    return _shortcuts(planner, plan, stop, cut=True)


def _shortcuts(planner: RRTCoLearn, plan: Plan, stop: Callable[[], bool] | None, *,
               cut: bool) -> Plan:
    """`interior_shortcuts` (``cut`` False) or `piece_shortcuts` (True)."""
    if not plan.solved:
        return plan
    sys, s = planner.problem.system, planner.settings
    key = "pieces" if cut else "interior"
    record = {"stretches": 0, "shots": {"edge": [0, 0], "U_stretch": [0, 0], "U": [0, 0]},
              "on_target": 0, "kept": 0, "goal_tails": 0, "lost": 0, "added": 0,
              **({"pieces": 0} if cut else {})}
    if len(plan.path_nodes) < 3 or planner.model is None or \
            sys.params_from_costate is None or (cut and stop is not None and stop()):
        plan.extra[key] = record
        return plan
    n = sys.n_states
    prop, tree = planner.propagator, plan.tree
    lam, z0 = np.empty(n), np.empty(2 * n + 1)
    lqr = planner.goal_loop if s.goal_lqr is not False else None
    lqr = None if isinstance(lqr, str) else lqr
    path, origin = list(plan.path_nodes), {}
    if cut:
        nodes = tree.n_nodes
        path, origin = _pieces(planner, tree, path, PAIR_NODES)
        record["pieces"] = tree.n_nodes - nodes
    found = _search(planner, tree, path, origin, lqr, lam, z0, record, stop)
    return recorded(plan, prop, found, key, record)


def _search(planner: RRTCoLearn, tree: PlannerData, path: list[int], origin: dict[int, int],
            lqr, lam: np.ndarray, z0: np.ndarray, record: dict,
            stop: Callable[[], bool] | None) -> list[int] | None:
    """`interior_shortcuts`' search on ``path`` (``origin``: `_pieces`'): the path after
    the stretches it shortcut, or None when it kept none."""
    s = planner.settings
    added = record["added"]
    best = float(costs_to_come(tree, path)[-1])
    tried: set[tuple[int, int]] = set()
    misses = 0
    while misses < INTERIOR_MISSES:
        come = costs_to_come(tree, path)
        pairs = _pairs(planner, tree, path, come, tried, stop, origin)
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
        path = grafted(tree, path, a, chain, s.dt)
        record["added"] += len(chain)
        record["kept"] += 1
        record["goal_tails"] += tail
        best = float(costs_to_come(tree, path)[-1])
    return path if record["added"] > added else None


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
            after = reattached(prop, tree, rest, landed, lam, z0)
            if after is not None:
                chain += [(e, tree.made_by.get(node)) for e, node in zip(after, rest,
                                                                           strict=False)]
            else:
                left = (best - come[a] - edge.cost) / s.time_weight if s.time_weight > 0 \
                    else np.inf
                if left <= s.dt:
                    continue
                goal = goal_tail(planner, lqr, landed, left, lam, z0)
                if goal is None:
                    record["lost"] += 1
                    continue
                chain += [(e, "lqr" if e.control is not None else "shooting") for e in goal]
                tail = True
        if come[a] + sum(e.cost for e, _ in chain) < best - 1e-9:
            return a, chain, tail
    return None

"""What the improvements share: a plan with its record and new path (`recorded`), a
path's costs to come, a chain kept as new leaves (`grafted`), the rest of a path simulated
again from a new state (`reattached`), and the node pairs the pairwise searches consider
(`station_pairs`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from rrtcolearn.integrate import propagate_draws
from rrtcolearn.planning.contracts import Edge, add_edge
from rrtcolearn.planning.propagator import Propagator
from rrtcolearn.planning.tree import Plan, PlannerData

# the stretches tried in a row without a cheaper path before the interior search gives up
INTERIOR_MISSES = 24
# a re-attached path's last edge may run this many times its steps to reach the goal region
REATTACH_STRETCH = 2

# the pairwise searches (`interior_shortcuts`, `landed_shortcuts`) consider at most this many of a
# path's nodes, evenly spaced along it (the first and the last kept): every pair of a path of
# thousands of one-step edges (an LQR chain) is millions of model queries. Paths of the
# shipped problems have tens of nodes and are searched whole.
PAIR_NODES = 192


def recorded(plan: Plan, prop, path: list[int] | None, key: str, record: dict) -> Plan:
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


def costs_to_come(tree: PlannerData, path: list[int]) -> np.ndarray:
    """Cost to come of each node of ``path`` (path order)."""
    return np.concatenate([[0.0], np.cumsum(tree.costs[path[1:]])])


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


def reattached(propagator: Propagator, tree: PlannerData, rest: list[int], x0: np.ndarray,
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


def _stations(count: int) -> np.ndarray:
    """Positions of a path's first ``count`` nodes that the pairwise searches consider: all
    of them, or PAIR_NODES evenly spaced (the first and the last among them) on a longer
    path."""
    if count <= PAIR_NODES:
        return np.arange(count)
    return np.unique(np.round(np.linspace(0, count - 1, PAIR_NODES)).astype(int))


def station_pairs(count: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of positions (a < b) among `_stations` (count)."""
    at = _stations(count)
    i, j = np.triu_indices(at.size, 1)
    return at[i], at[j]


def grafted(tree: PlannerData, path: list[int], a: int, chain: list, dt: float) -> list[int]:
    """``path`` up to position a, then ``chain``'s (edge, kind) added as new leaves below it
    (a kind of None keeps the edge's default): the way every pass keeps a chain."""
    parent, path = path[a], path[: a + 1]
    for edge, kind in chain:
        parent = add_edge(tree, parent, edge, dt)
        if kind is not None:
            tree.made_by[parent] = kind
        path.append(parent)
    return path

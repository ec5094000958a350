"""Goal-funnel extremals through the start (`start_funnel`): the query's aimed search for
the funnel's extremals passing the start, and the funnel connection's steering along them."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn.planning.connections import aimed_round
from rrtcolearn.planning.improve.common import costs_to_come, grafted, recorded
from rrtcolearn.planning.tree import Plan

if TYPE_CHECKING:
    from rrtcolearn.planning.rrt import RRTCoLearn


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
        return recorded(plan, prop, None, "start_funnel", record)
    best = float(costs_to_come(tree, plan.path_nodes)[-1])
    x0 = tree.states[0]
    found, tried = None, np.inf
    # while an extremal near the start could still undercut the path (its cost to go from
    # its state nearest the start below the path's cost): on the shipped cart-pole they
    # cost 4-7x the optimum, its anytime paths 1.0-1.3x
    while not (stop is not None and stop()) and search.cheapest < best:
        done = aimed_round(prop, stream, search, x0, planner.funnel_reach[0], tried, best)
        if done is None:
            break
        record["rounds"] += 1
        steered, tried, chain = done
        record["tries"] += steered
        cost = np.inf if chain is None else float(sum(e.cost for e in chain))
        if cost < best - 1e-9:
            best, found = cost, chain
    record["nearest"] = search.nearest
    if found is None:
        return recorded(plan, prop, None, "start_funnel", record)
    path = grafted(tree, [0], 0, [(edge, "funnel") for edge in found], planner.settings.dt)
    record["kept"] = True
    return recorded(plan, prop, path, "start_funnel", record)

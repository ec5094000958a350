"""Goal shortcuts (`goal_shortcuts`): A first solution is a chain of extremals (and, with an
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
Before the walk, where that loop exists, the finite-horizon law with the plan's own running
cost (`lq_tail`, `lqr.GoalLQ`; a chain of held inputs, kind ``lqr``) from the node and over
the horizon it predicts cheapest, kept only where it undercuts the path and the plan's step
resolves it (the path replayed at half the step ends within the goal tolerance of where it
ends at the step, as `evaluate.step_check` judges the whole path).
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

import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn.evaluate import replayed_edges, state_gaps
from rrtcolearn.integrate import propagate_controls
from rrtcolearn.planning.connections import held_chain, lqr_chain, shoot_edge
from rrtcolearn.planning.contracts import Edge
from rrtcolearn.planning.improve.common import costs_to_come, grafted, recorded
from rrtcolearn.planning.learned import goal_query
from rrtcolearn.planning.lqr import GoalLQ
from rrtcolearn.planning.tree import Plan

if TYPE_CHECKING:
    from rrtcolearn.planning.propagator import Propagator
    from rrtcolearn.planning.rrt import RRTCoLearn

# the `GoalLQ` tail (`lq_tail`): at most this many runs per call; a run the step does not
# resolve caps the horizons tried at this share of its horizon, and once a run is
# resolved the horizon is bisected between the longest resolved and the shortest unresolved
LQ_TRIES, LQ_SHORTER = 8, 0.7
# the calls of one anytime run try the law while they number fewer than this many times
# (1 + the calls that kept a tail): where it never pays (the shipped cart-pole's swing-up,
# outside the linearisation's reach, whose tables alone took 0.86 s) it stops after two,
# where it does (sparse_rrt's cart-pole transfer) it goes on
LQ_PATIENCE = 2
# each planner's law (`GoalLQ`), by its propagator: built and grown once per query
_LAWS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def lq_tail(propagator: Propagator, lqr, plan: Plan, path: list[int], best: float,
            record: list[int] | None = None) -> tuple[int, list[Edge]] | None:
    """The cheapest path's tail by the finite-horizon law with the plan's own running cost
    (`lqr.GoalLQ`): (the position on ``path`` to graft at, the chain), or None. The law's
    cost is predicted from every node of the path for every horizon up to the least
    predicted cost's (the model's time alone, w j dt, bounds it); the node and horizon
    predicted cheapest are run, and the run kept if it reaches the goal region, undercuts
    ``best`` and the plan's step resolves it: the path replayed at half the step stays
    within the goal tolerance of the chain at each of its steps (`evaluate.state_gaps`, the
    gap `evaluate.step_check` measures at the path's end; the end alone is not enough: on
    sparse_rrt's cart-pole a 26-s run whose pole turns over once more at half the step ends
    0.8 from it, against a tolerance of 1.5). A run the step does not resolve caps the
    horizons at `LQ_SHORTER` of its horizon until one is resolved; then the horizon is
    bisected between them (the cheapest resolved run kept); at most `LQ_TRIES` runs
    (compiled: `lqr.GoalLQ.run`); a planner whose calls
    keep no tail stops trying (`LQ_PATIENCE`; ``record``: [calls, calls that kept a
    tail] of the run so far, updated; `RRTCoLearn.run_records`)."""
    prob, s = propagator.problem, propagator.settings
    w, dt = s.time_weight, s.dt
    if not (w > 0 and np.isfinite(best)):  # (no free final time to choose, or no path)
        return None
    record = [0, 0] if record is None else record
    if record[0] >= LQ_PATIENCE * (record[1] + 1):
        return None
    record[0] += 1
    lq = _LAWS.get(propagator)
    if lq is None:  # the law's tables depend on the query's goal and cost alone: kept
        lq = _LAWS[propagator] = GoalLQ(lqr, propagator.input_weight, w)
    tree = plan.tree
    come = costs_to_come(tree, path)[:-1]  # (not the goal node: nothing to replace there)
    xs = tree.states[path[:-1]]
    n = max(1, round(lqr.horizon / dt))
    limit = best / (w * dt)
    while True:  # horizons doubled while the least predicted cost is at the longest
        cost = lq.predicted(xs, n) + come[:, None]
        a, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
        limit = min(limit, (cost[a, j] - come.min()) / (w * dt))
        longer = int(min(limit, 2 * n))
        if j < 0.9 * n or longer <= n:
            break
        n = longer
    # the path's states at half the step, up to each node (replayed once, as needed)
    sys, half = prob.system, 0.5 * float(plan.dt)
    ends = (t.states[-1] for t in replayed_edges(sys, plan.edges(), plan.time_weight, half,
                                                 prob.start))
    halves = [np.asarray(prob.start, dtype=np.float64)]
    # the horizons tried: longer than `lo`, at most `cap`; `lo` the longest horizon whose
    # run was resolved (the tail `kept`, its cost `bound`, its predicted cost `guess`: a run
    # cut at the goal region costs less than predicted, so predictions are compared with
    # predictions), `hi` the shortest whose run reached the goal region but was not resolved
    cap, lo, hi, kept, bound, guess = cost.shape[1] - 1, 0, None, None, best, best
    for _ in range(LQ_TRIES):
        window = cost[:, lo + 1: cap + 1]
        a, j = np.unravel_index(int(np.argmin(window)), window.shape)
        j += lo + 1
        if not cost[a, j] < guess:
            break
        out = lq.run(tree.states[path[a]], int(j), propagator.box, propagator.goal_mask,
                     prob.validity if prob.validity else None)
        total = come[a] + sum(propagator.hold_rate(u) * dt for u in out.inputs)
        if not out.reached or total >= bound:
            cost[a] = np.inf
            continue
        while len(halves) <= a:
            halves.append(next(ends))
        y = propagate_controls(sys, halves[a], out.inputs, np.full(len(out.inputs), 2),
                               half)[::2]
        if len(y) == len(out.states) and \
                state_gaps(prob, out.states, y).max() < prob.goal_tolerance:
            kept, bound, guess, lo = (int(a), out), total, cost[a, j], int(j)
            if hi is None:  # the cheapest prediction, resolved: nothing longer to try
                break
        else:
            hi = int(j) if hi is None else min(hi, int(j))
        cap = int(LQ_SHORTER * hi) if kept is None else (lo + hi) // 2
        if cap <= lo:
            break
    if kept is None:
        return None
    record[1] += 1
    return kept[0], held_chain(propagator, kept[1])


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
    lqr = planner.goal_loop if s.goal_lqr is not False else None
    if isinstance(lqr, str):  # no equilibrium at the goal, or an unstable loop
        lqr = None
    can_shoot = sys.params_from_costate is not None
    path = list(plan.path_nodes)
    best = float(costs_to_come(tree, path)[-1])
    added, shots, loops, lq_kept = 0, 0, 0, 0
    if lqr is not None and w > 0:
        found = lq_tail(prop, lqr, plan, path, best,
                        planner.run_records.setdefault("lq_tail", [0, 0]))
        if found is not None:
            at, tail = found
            path = grafted(tree, path, at, [(edge, "lqr") for edge in tail], s.dt)
            added += len(tail)
            lq_kept = 1
            best = float(costs_to_come(tree, path)[-1])
    pos = len(path) - 2  # the last edge's parent: U's guess may beat the edge the tree had
    while pos >= 0:
        if stop is not None and stop():
            break
        come = costs_to_come(tree, path)
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
            tail = tails[int(np.argmin(costs))]
            # a shortcut is one extremal by shooting, or an LQR chain of held inputs
            path = grafted(tree, path, pos, [(edge, "lqr" if edge.control is not None
                                              else "shooting") for edge in tail], s.dt)
            added += len(tail)
            best = float(come[pos] + min(costs))
        pos -= 1
    return recorded(plan, prop, path if added else None, "shortcuts",
                     {"added": added, "shots": shots, "lqr_loops": loops,
                      "lq_tail": lq_kept})


def goal_tail(planner: RRTCoLearn, lqr, x0: np.ndarray, budget: float,
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

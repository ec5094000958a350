"""The goal connections: ways to finish from a node of the tree into the goal region, each a
`contracts.Connection` (``connect(tree) -> (node, edges) | None``) that keeps its own search
state between the loop's goal-biased iterations.

- `ShootingConnection`: one extremal by shooting (`shooting.shoot`) from the nearest untried
  node, starting at U's guess;
- `FunnelConnection`: continuation along a funnel of extremals into the goal
  (`funnel.GoalFunnel`), then polished by shooting, or landed as a chain of extremals by
  multiple shooting along it;
- `LQRConnection`: the LQR closed loop about the goal's equilibrium (`lqr.GoalLQR`) as a chain
  of constant-input edges.

`cheaper_goal_edge` is choose-parent for the goal once a solve reached it (the planner's
last step). `shoot_edge` and `lqr_chain` are also what the anytime shortcuts
(`planning.improve`) use.
`extremal_chain` and `terminal_conditions` serve multiple shooting here and in
`planning.improve`. When each connection is switched on is `planning.schedule`'s to say.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from itertools import pairwise

import numpy as np

from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.planning.contracts import Edge, GrowingTree, grown
from rrtcolearn.planning.funnel import (
    AIM_RETRY,
    AimedSearch,
    Continuation,
    FunnelStream,
    GoalFunnel,
)
from rrtcolearn.planning.learned import REFINE_PROGRESS, goal_query
from rrtcolearn.planning.lqr import GoalLQR, LQRTry, build_goal_lqr
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.propagator import Propagator
from rrtcolearn.planning.schedule import Allowance
from rrtcolearn.planning.shooting import endpoints, multiple_shoot, shoot

# Funnel states tried per node, nearest first. 1, not 3: on bench/ablation.py's models
# (derived funnel duration, seeds 0-19, first solutions) no node ever connected from its
# second or third nearest funnel state (where the nearest's continuation failed, its
# neighbours on the adjacent extremals failed too, or gave the same edge that failed the
# checks), so the same paths came out with 0.79x the acrobot's CPU per seed (total 0.68x)
# and 0.97x the cart-pole's; docs/ablation.md, "Continuation along the funnel"
FUNNEL_POINTS = 1
FUNNEL_STRETCH = 1.5  # a funnel connection may last this times the funnel's duration
# where a funnel continuation converged but its extremal, integrated forwards from the node
# as one edge, misses the goal or fails a check (the acrobot: 28 of 29 such results over 10
# seeds; the unstable dynamics amplify the interpolation between RK4 steps), indirect
# multiple shooting along it: the extremal cut into this many segments in turn, each
# doubling halving how long an error grows, the segments' starts and costates taken from
# the continuation's extremal (docs/ablation.md, "Multiple shooting along a funnel
# continuation")
CHAIN_SEGMENTS = (2, 4, 8)
# where every free-final-time chain fails: the last count of segments with their ends on the
# RK4 grid and the duration fixed, from the node, else by continuation from where the
# extremal starts to the node at these fractions of the way (`FunnelConnection._grid_chain`)
GRID_FRACTIONS = (0.25, 0.5, 0.75, 1.0)
# choose-parent through the funnel (`FunnelConnection.cheaper`) tries plan.goal_parent_tries
# nodes within each of these multiples of the funnel's radius in turn (the untried ones):
# a continuation converges from farther than the radius the connection keeps to while the
# tree grows (there every try costs iterations), and once the goal is reached the cheapest
# node is worth a few. Alternating per seed, seeds 0-19 (docs/ablation.md): (1, 2) against
# (1,) cart-pole first median 4.88x -> 4.34x, acrobot 7.75x -> 6.38x, none dearer, at
# 1.08x and 1.14x the CPU per seed; one rung of 2 alone made 2 and 4 seeds dearer (its
# tries spent on other nodes); a third at 4: cart-pole 3.95x at 1.04x, the acrobot the same
# paths at 1.26x the CPU
PARENT_REACH = (1.0, 2.0)
# `multiple_shoot`'s tolerances: the state and costate residual of the free-final-time
# solve, then of the solve with the segments' durations rounded to the RK4 grid
SHOOT_TOLERANCE = 1e-6
LAND_TOLERANCE = 1e-8


def terminal_conditions(problem: PlanningProblem) -> Callable[[np.ndarray], np.ndarray]:
    """The terminal conditions of one extremal into ``problem``'s goal for ends z (B, 2n):
    the goal residual (`PlanningProblem.goal_residual`, the offset to the goal centre that
    the goal shortcuts shoot at), and for a coordinate the goal leaves free (weight 0) its
    costate (transversality: lambda_j(T) = 0)."""
    n = problem.system.n_states
    weights = problem.goal_weights
    free = np.zeros(n, dtype=bool) if weights is None or problem.goal_fn is not None else \
        np.asarray(weights) == 0

    def terminal(z: np.ndarray) -> np.ndarray:
        r = problem.goal_residual(z[:, :n])
        if free.any():
            r[:, free] = z[:, n:][:, free]
        return r
    return terminal


def extremal_chain(propagator: Propagator, x0: np.ndarray, costates: np.ndarray,
                   steps: np.ndarray) -> list[Edge] | None:
    """The edges of a multiple-shooting solution from ``x0``: segment after segment, each
    simulated from where the previous one ended with its own costate (``costates`` (M, n),
    ``steps`` (M,) RK4 steps each; continuity holds to the solve's tolerance) and checked
    like every planner edge (state box, obstacles, input limit, cut at its first state in
    the goal region). None unless they all pass, each of its full length, and the chain
    ends in the goal region."""
    sys, s = propagator.problem.system, propagator.settings
    n = sys.n_states
    lam, z0 = np.empty(n), np.empty(2 * n + 1)
    chain, at = [], np.asarray(x0, dtype=np.float64)
    for costate, k in zip(costates, steps, strict=True):
        z0[:n], z0[n : 2 * n], z0[2 * n] = at, costate, 0.0
        if not propagator.within_limit(z0):
            return None
        params = np.append(sys.params_from_costate(at[None], costate[None])[0], k * s.dt)
        lam[:] = costate
        edge = propagator.extremal_edges(at, params[None], lam[None])
        if edge is None or not (edge.hit or edge.steps == k):
            return None
        chain.append(edge)
        if edge.hit:
            return chain
        at = edge.traj[-1, :n]
    return None


def shoot_edge(propagator: Propagator, x0: np.ndarray, params: np.ndarray, duration: float,
               max_duration: float, lam: np.ndarray, z0: np.ndarray) -> Edge | None:
    """The edge to the goal that shooting finds from ``x0`` starting at ``params`` and
    ``duration``, checked like every edge; None unless it reaches the goal region. ``lam``
    (n,) and ``z0`` (2n + 1,) are scratch."""
    prob, s = propagator.problem, propagator.settings
    res = shoot(prob.system, x0, params, duration, prob.goal_residual,
                time_weight=s.time_weight, dt=s.dt, max_duration=max_duration,
                tolerance=0.25 * prob.goal_tolerance, max_iterations=20)
    if res is None:
        return None
    return propagator.goal_extremal(x0, np.append(res.params, res.steps * s.dt), lam, z0)


def cheaper_goal_edge(propagator: Propagator, model: LearnedFunctions, tree: GrowingTree,
                      goal_node: int, tries: int, stop: Callable[[], bool] | None = None
                      ) -> tuple[tuple[int, Edge, str] | None, dict]:
    """Choose-parent for the goal once a solve has reached it at ``goal_node``: shots at the
    goal (`shoot_edge`, from U's guess) from the nodes whose cost-to-come plus the learned J
    to the goal is below the path's cost, least first, at most ``tries`` of them (among the
    nodes within ``connect_reach`` of the goal, as the shooting connection's, whose query V
    accepts). U's guess is integrated first: a hit needs no shooting, and a guess that did
    not come ``REFINE_PROGRESS`` of the way is passed over. (node, edge, kind: "learned" for
    U's guess itself, "shooting" for a shot) of the cheapest path found, or None, and its
    record: tries, and the path's cost before and after; ``stop()`` is asked before each try.

    The first path is the first chain of edges that happened to land; the cheapest node by
    cost-to-come + J is often another one (the pendulum, seeds 0-19: median first cost 2.31x
    -> 1.53x the optimum, docs/ablation.md). Only shots that could make the path cheaper are
    tried: an extremal costs at least w T, so none longer than the saving."""
    prob, s = propagator.problem, propagator.settings
    data, states = tree.data, tree.states
    m = data.n_nodes
    come = data.cost_to_come(np.arange(m))
    best = float(come[goal_node])
    record = {"tries": 0, "cost_before": best, "cost": best}
    # the nodes the shooting connection would shoot from: within connect_reach of the goal
    wd = prob.goal_residual(states) * tree.weight
    near = np.flatnonzero((come < best)
                          & (np.einsum("ij,ij->i", wd, wd) <= s.connect_reach**2))
    if near.size == 0 or tries <= 0:
        return None, record
    query = goal_query(states[near], tree.shifts[near], prob.goal_offset(states[near]))
    rows, cost, neighbours = model.query_valid(query)
    total = come[near[rows]] + cost
    n = states.shape[1]
    lam, z0 = np.empty(n), np.empty(2 * n + 1)
    found = None
    for r in np.argsort(total, kind="stable")[:tries]:
        if total[r] >= best or (stop is not None and stop()):
            break
        node, row = int(near[rows[r]]), int(rows[r])
        record["tries"] += 1
        guess = model.steer(query[row : row + 1], neighbours[r][None])[0]
        longest = min(s.max_duration, (best - come[node]) / s.time_weight) \
            if s.time_weight > 0 else s.max_duration
        if longest < s.dt:
            continue
        x0 = states[node].copy()
        params = np.append(guess[:-1], min(max(guess[-1], s.dt), longest))
        # U's guess itself first: a hit needs no shooting, and a guess that did not come
        # REFINE_PROGRESS of the way is not worth Newton's method (as `LearnedSteering.refine`)
        edge = propagator.extremal_edges(x0, params[None], lam[None]) \
            if propagator.start_extremal(x0, params, lam, z0) else None
        if edge is None:
            continue
        kind = "learned"
        if not edge.hit:
            miss = np.linalg.norm(prob.goal_residual(edge.traj[-1:, :n].copy()))
            if miss > REFINE_PROGRESS * np.linalg.norm(prob.goal_residual(x0[None])):
                continue
            edge, kind = shoot_edge(propagator, x0, guess[:-1], params[-1], longest, lam,
                                    z0), "shooting"
        if edge is not None and come[node] + edge.cost < best:
            best = float(come[node] + edge.cost)
            found = (node, edge, kind)
    record["cost"] = best
    return found, record


def lqr_chain(propagator: Propagator, lqr: GoalLQR, x0: np.ndarray
              ) -> tuple[list[Edge] | None, str]:
    """The LQR closed loop from ``x0`` as a chain of constant-input edges (consecutive equal
    inputs, e.g. saturated, merged into one) if it reaches the goal region within
    its horizon (`GoalLQR.horizon`), and how the loop ended (`GoalLQR.run`)."""
    prob, s = propagator.problem, propagator.settings
    out = lqr.run(x0, max(1, round(lqr.horizon / s.dt)), propagator.box,
                  propagator.goal_mask, prob.validity if prob.validity else None)
    if not out.reached:
        return None, out.end
    return held_chain(propagator, out), out.end


def held_chain(propagator: Propagator, out: LQRTry) -> list[Edge]:
    """A closed-loop run into the goal region (`lqr.LQRTry`, reached) as a chain of
    constant-input edges, consecutive equal inputs (e.g. saturated) merged into one."""
    prob, s = propagator.problem, propagator.settings
    us = out.inputs
    breaks = [0, *np.flatnonzero(np.any(us[1:] != us[:-1], axis=1)) + 1, len(us)]
    chain = []
    for a, b in pairwise(breaks):
        u = us[a].copy()
        rate = propagator.hold_rate(u)
        last = b == len(us)
        chain.append(Edge(out.states[a : b + 1].copy(), b - a, (b - a) * s.dt * rate,
                          float(np.abs(u).max()), last, control=u,
                          end_distance=float(prob.goal_distance(out.states[b])[0])
                          if last else None))
    return chain


def goal_lqr(propagator: Propagator) -> GoalLQR | str:
    """The LQR controller about the goal's equilibrium, or why there is none
    (`lqr.build_goal_lqr`)."""
    return build_goal_lqr(propagator.problem, propagator.settings.dt, propagator.input_weight)


class ShootingConnection:
    """Shooting from the nearest untried node within ``connect_reach`` of the goal, from U's
    guess."""

    name = "shooting"

    def __init__(self, propagator: Propagator, model: LearnedFunctions):
        self.propagator, self.model = propagator, model
        n = propagator.problem.system.n_states
        self._lam, self._z0 = np.empty(n), np.empty(2 * n + 1)
        self.tried = np.zeros(256, dtype=bool)
        self.allowance = Allowance()
        # per tree node its weighted squared goal distance (rows filled up to `queried`)
        self.d2 = np.full(256, np.inf)
        self.queried = 0

    def connect(self, tree: GrowingTree) -> tuple[int, list[Edge]] | None:
        """An edge from the nearest untried node to the goal by shooting, or None (also
        when the `schedule.Allowance` holds no attempt now).

        The first guesses are U's prediction for (node, goal) with its duration and with
        2, 4 and 8 times it: U's duration is the least reliable part of its guess far from the
        data, and Newton's method on the duration alone would not cross the long stretches
        where the residual grows before it falls.
        """
        prob, s = self.propagator.problem, self.propagator.settings
        self.allowance.accrue()
        m = tree.data.n_nodes
        self.tried = tried = grown(self.tried, m, False)
        self.d2 = grown(self.d2, m, np.inf)
        states = tree.states
        if self.queried < m:  # the nodes added since the last call
            wd = prob.goal_residual(states[self.queried : m]) * tree.weight
            self.d2[self.queried : m] = np.einsum("ij,ij->i", wd, wd)
            self.queried = m
        d2 = self.d2[:m].copy()
        d2[tried[:m] | (d2 > s.connect_reach**2)] = np.inf
        node = int(np.argmin(d2))
        if np.isfinite(d2[node]) and self.allowance.take():
            tried[node] = True
            x0 = states[node]
            offset = prob.goal_offset(x0)[0]
            guess = self.model.query(goal_query(x0, tree.shifts[node], offset))[1][0]
            for factor in (1.0, 2.0, 4.0, 8.0):
                duration = min(max(guess[-1], s.dt) * factor, s.max_duration)
                edge = shoot_edge(self.propagator, x0, guess[:-1], duration, s.max_duration,
                                  self._lam, self._z0)
                if edge is not None:
                    return node, [edge]
                if duration >= s.max_duration:
                    break
        return None

    def report(self) -> dict:
        return {}

    def note(self) -> str | None:
        return None


class FunnelConnection:
    """Continuation from the untried node nearest a funnel state (within ``funnel_radius``)."""

    name = "funnel"

    def __init__(self, propagator: Propagator, funnel: GoalFunnel,
                 more: Callable[[int], GoalFunnel] | None = None, limit: int = 0,
                 grow_after: int = 0, duration: float | None = None, own: bool = False):
        self.propagator, self.funnel = propagator, funnel
        # the funnel's parts (``funnel``, the first, then each growth's), each with its own
        # index, and the first (global) index of each part's states
        self.parts, self.starts = [funnel], [0]
        n = propagator.problem.system.n_states
        self._lam, self._z0 = np.empty(n), np.empty(2 * n + 1)
        # per tree node: its nearest funnel states (distances and indices, rows filled up to
        # `queried`) and whether the connection has started from it
        self.dist = np.full((256, FUNNEL_POINTS), np.inf)
        self.index = np.zeros((256, FUNNEL_POINTS), int)
        self.tried = np.zeros(256, bool)
        self.queried = 0
        self._states = np.empty((0, n))  # the tree's states at the last call
        # growing (`build` with ``limit``): ``more(k)`` builds k more extremals; the funnel
        # doubles, up to ``limit`` extremals, after ``grow_after`` calls in a row that found
        # no untried node within its radius (``idle``)
        self._more, self.limit, self.grow_after = more, limit, grow_after
        self.simulations = len(funnel.goal_costates)  # extremals drawn
        self.idle = 0
        self.grown = 0
        self.allowance = Allowance()
        # the extremals' longest duration (by default ``funnel_duration``), and whether
        # `connect` falls back on the chain along a funnel state's own extremal
        self.duration = propagator.settings.funnel_duration if duration is None else \
            float(duration)
        self.own = own
        # the query's funnel stream, whose aimed search for extremals through the start
        # `connect` runs a round of where no node steers (`aim`; None: no search), the rounds
        # run, the steerings tried and the distance of the last one tried
        self.stream: FunnelStream | None = None
        self.aimed = [0, 0]
        self._aim_tried = np.inf

    @classmethod
    def build(cls, propagator: Propagator, rng: np.random.Generator, weight: np.ndarray,
              n_simulations: int, limit: int = 0, grow_after: int = 0,
              reach: tuple[float, float] | None = None, own: bool = False
              ) -> FunnelConnection:
        """The connection along a goal funnel of ``n_simulations`` extremals (drawn from
        ``rng``; built inside the timed region: its CPU time counts as planning time); with
        ``limit`` > ``n_simulations`` a funnel that doubles (more extremals from ``rng``) up
        to ``limit`` extremals each time ``grow_after`` calls in a row found no tree node
        within its radius to start from. ``reach``: the extremals' longest duration and
        cost bound (by default ``funnel_duration`` and ``funnel_max_cost``). ``own``: where
        a node's continuation fails, try the chain along its funnel state's own extremal
        (`steer_from`)."""
        prob, s = propagator.problem, propagator.settings
        duration, max_cost = reach or (s.funnel_duration, s.funnel_max_cost)
        more = partial(
            GoalFunnel.build, prob.system, prob.goal, prob.goal_offset, rng,
            time_weight=s.time_weight, dt=s.dt, max_duration=duration,
            max_cost=max_cost, scale=weight,
            # the funnel drops its states within this plain distance of the goal; a goal
            # region's tolerance is in its own units, so there every state is kept
            tolerance=prob.goal_tolerance if prob.goal_fn is None and
            prob.goal_weights is None else 0.0,
            min_duration=s.funnel_min_duration, box=(prob.state_low, prob.state_high))
        connection = cls(propagator, more(n_simulations=n_simulations), more, limit,
                         grow_after, duration, own)
        connection.simulations = n_simulations  # drawn (a draw may give no costate)
        return connection

    def grow(self) -> None:
        """Double the funnel (as many more extremals as it has, at most up to ``limit``) as
        a new part with its own index (no index is built again); the nodes queried so far
        keep their nearest funnel states among the old parts' and the new part's."""
        k = min(self.simulations, self.limit - self.simulations)
        part = self._more(n_simulations=k)
        self.simulations += k
        self.idle, self.grown = 0, self.grown + 1
        self.starts.append(self.starts[-1] + len(self.parts[-1]))
        self.parts.append(part)
        q = self.queried
        if q and len(part):
            offsets = self.propagator.problem.goal_offset(self._states[:q])
            d, i = part.nearest(offsets, FUNNEL_POINTS, self.propagator.settings.funnel_radius)
            self.dist[:q], self.index[:q] = _nearest_of(
                [(self.dist[:q], self.index[:q]), (d, i + self.starts[-1])])

    def nearest(self, offsets: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """Weighted distances (N, FUNNEL_POINTS) from states given by their goal offsets to
        their nearest funnel states within ``radius`` over every part (inf where fewer), and
        those states' global indices."""
        found = [part.nearest(offsets, FUNNEL_POINTS, radius) for part in self.parts
                 if len(part)]
        if not found:
            return (np.full((len(offsets), FUNNEL_POINTS), np.inf),
                    np.zeros((len(offsets), FUNNEL_POINTS), int))
        starts = [a for a, part in zip(self.starts, self.parts, strict=True) if len(part)]
        return _nearest_of([(d, i + a) for (d, i), a in zip(found, starts, strict=True)])

    def cost_to_go(self, js: np.ndarray) -> np.ndarray:
        """The cost to the goal along their extremals of funnel states ``js`` (global
        indices over the parts)."""
        parts = np.searchsorted(self.starts, js, side="right") - 1
        out = np.empty(len(js))
        for p in np.unique(parts):
            at = parts == p
            out[at] = self.parts[p].cost_to_go[js[at] - self.starts[p]]
        return out

    def steer(self, offset: np.ndarray, j: int, max_duration: float) -> Continuation | None:
        """`GoalFunnel.steer` from funnel state ``j`` (a global index over the parts)."""
        p = int(np.searchsorted(self.starts, j, side="right")) - 1
        return self.parts[p].steer(offset, j - self.starts[p], max_duration)

    def aim(self, stream: FunnelStream) -> None:
        """Search ``stream`` (the query's, whose parts this funnel is made of) for extremals
        through the start where no node steers (`connect`)."""
        self.stream = stream

    def connect(self, tree: GrowingTree) -> tuple[int, list[Edge]] | None:
        """An edge to the goal from an untried node within the funnel's radius (`_from_node`),
        else, with `aim`, from the start along an extremal of the query's search for those
        passing it (`_from_start`); or None."""
        found = self._from_node(tree)
        return found if found is not None else self._from_start(tree)

    def _from_start(self, tree: GrowingTree) -> tuple[int, list[Edge]] | None:
        """One round of the query's aimed search (`funnel.AimedSearch`: the extremals from
        the goal passing nearest the start, drawn around again; shared with the anytime
        search, `improve.start_funnel`), then, where the pool's nearest extremal is within
        the funnel's radius and `AIM_RETRY` nearer than the last tried, the chain from the
        root along it (`steer_from`, its own extremal's chain included); None until the
        search has a part to start from and after its `AIM_ROUNDS`.

        Why: the shipped acrobot's optimum is one extremal from the start; its first paths,
        chains of learned edges and a funnel continuation, cost 3.8-12x it (seeds 0-9),
        where the search's extremal through the start gives 1.8-2.3x on 8 of 10 seeds at
        about the same CPU (docs/anytime.md, "The search in the first solve")."""
        if self.stream is None:
            return None
        prob = self.propagator.problem
        root = tree.data.states[0]
        search = self.stream.aimed(root, prob.system, prob.offset_to)
        done = None if search is None else aimed_round(
            self.propagator, self.stream, search, root, self.duration, self._aim_tried)
        if done is None:
            return None
        self.aimed[0] += 1
        steered, self._aim_tried, chain = done
        self.aimed[1] += steered
        return None if chain is None else (0, chain)

    def _from_node(self, tree: GrowingTree) -> tuple[int, list[Edge]] | None:
        """An edge to the goal from an untried node within the funnel's radius, or None
        (also when the `schedule.Allowance` holds no attempt now): the funnel extremal's
        solution moved to the node (`GoalFunnel.steer`), then polished by a forward solve
        from the node. First from the node whose path would cost least (cost to come plus
        its nearest funnel state's cost to go: the shipped cart-pole's first paths 15.4x ->
        11.6x the optimum, median of 10 seeds), then from the node nearest a funnel state."""
        self.allowance.accrue()
        near = self._untried(tree)
        if not len(near):
            self.idle += 1
            if self.idle >= self.grow_after and self.simulations < self.limit:
                self.grow()
            return None
        # of the untried nodes within reach, first the one whose path would cost least (its
        # cost to come plus the cost to go of its nearest funnel state's extremal), then,
        # where that fails, the one nearest a funnel state, the likeliest to steer
        cheapest = int(near[np.argmin(tree.data.cost_to_come(near) + self.cost_to_go(
            self.index[near, 0]))])
        nearest = int(near[np.argmin(self.dist[near, 0])])
        self.idle = 0
        if not self.allowance.take():
            return None
        for node in dict.fromkeys((cheapest, nearest)):
            self.tried[node] = True
            chain = self.steer_from(tree.data.states[node], self.dist[node],
                                    self.index[node], self.propagator.settings.funnel_radius,
                                    self.own)
            if chain is not None:
                return node, chain
        return None

    def cheaper(self, tree: GrowingTree, best: float, tries: int,
                stop: Callable[[], bool] | None = None
                ) -> tuple[tuple[int, list[Edge]] | None, int]:
        """Choose-parent for the goal through the funnel, once a solve has reached the goal
        at cost ``best``: continuations (`steer_from`) from the untried nodes within each
        multiple of the funnel's radius in `PARENT_REACH` in turn whose cost to come plus
        their nearest funnel state's cost to go is below ``best``, least first, at most
        ``tries`` of them per multiple (``stop()`` asked before each). ((node, edges) of the
        cheapest path found, or None; the tries made).

        On the shipped cart-pole the first path's cost is almost all its one funnel edge,
        from whichever node the allowance happened to try first (docs/ablation.md,
        "Through the goal funnel too")."""
        self._untried(tree)  # (the per-node arrays sized to the tree)
        radius = self.propagator.settings.funnel_radius
        m = tree.data.n_nodes
        # every untried node's nearest funnel states within the widest rung, once; each
        # rung then takes those within its own radius that are still untried
        nodes = np.flatnonzero(~self.tried[:m])
        dist, index = self.nearest(self.propagator.problem.goal_offset(
            tree.data.states[nodes]), PARENT_REACH[-1] * radius)
        come = tree.data.cost_to_come(nodes)
        total = come + self.cost_to_go(index[:, 0])
        found, made = None, 0
        for reach in PARENT_REACH:
            rung = np.flatnonzero((dist[:, 0] <= reach * radius) & ~self.tried[nodes])
            for r in rung[np.argsort(total[rung], kind="stable")][:tries]:
                if total[r] >= best or (stop is not None and stop()):
                    break
                node = int(nodes[r])
                self.tried[node] = True
                made += 1
                chain = self.steer_from(tree.data.states[node], dist[r], index[r],
                                        reach * radius)
                cost = np.inf if chain is None else float(come[r] + sum(e.cost for e in chain))
                if cost < best:
                    best, found = cost, (node, chain)
        return found, made

    def _untried(self, tree: GrowingTree) -> np.ndarray:
        """The tree's nodes within the funnel's radius that no continuation has started
        from, after querying the nodes added since the last call for their nearest funnel
        states."""
        prob, s = self.propagator.problem, self.propagator.settings
        m = tree.data.n_nodes
        self.dist = grown(self.dist, m, np.inf)
        self.index = grown(self.index, m, 0)
        self.tried = grown(self.tried, m, False)
        self._states = tree.data.states
        if self.queried < m:
            offsets = prob.goal_offset(tree.data.states[self.queried : m])
            d, i = self.nearest(offsets, s.funnel_radius)
            self.dist[self.queried : m], self.index[self.queried : m] = d, i
            self.queried = m
        return np.flatnonzero(~self.tried[:m] & (self.dist[:m, 0] <= s.funnel_radius))

    def steer_from(self, x0: np.ndarray, dist: np.ndarray, index: np.ndarray, radius: float,
                   own: bool = False) -> list[Edge] | None:
        """The edges to the goal from state ``x0`` along its nearest funnel states ``index``
        (global indices, at weighted distances ``dist``; those within ``radius`` in turn, the
        first whose continuation and solve succeed): one extremal, else a chain of them by
        multiple shooting along the continuation's (`_chain`); or None. With ``own``, where
        the continuation fails, the chain along the funnel state's own extremal
        (`GoalFunnel.extremal`): from a state very near it, where the continuation's
        backward solves fail for the same ill-conditioning as any single shooting
        (`improve.start_funnel`)."""
        prop = self.propagator
        prob, sys, s = prop.problem, prop.problem.system, prop.settings
        lam, z0 = self._lam, self._z0
        offset = prob.goal_offset(x0)[0]
        # the node may be farther from the goal than the funnel state it starts from
        longest = FUNNEL_STRETCH * self.duration
        for q in range(FUNNEL_POINTS):
            if not dist[q] <= radius:
                break
            guess = self.steer(offset, int(index[q]), longest)
            if guess is None:
                if own:
                    p = int(np.searchsorted(self.starts, index[q], side="right")) - 1
                    chain = self._chain(x0, self.parts[p].extremal(
                        int(index[q]) - self.starts[p]), longest)
                    if chain is not None:
                        return chain
                continue
            params = sys.params_from_costate(x0[None], guess.costate[None])[0]
            # the continuation's extremal as it is (exact up to the interpolation between
            # RK4 steps), else polished by a forward solve
            edge = prop.goal_extremal(
                x0, np.append(params, max(1, round(guess.duration / s.dt)) * s.dt), lam, z0) \
                or shoot_edge(prop, x0, params, guess.duration, longest, lam, z0)
            if edge is not None:
                return [edge]
            chain = self._chain(x0, guess, longest)
            if chain is not None:
                return chain
        return None

    def _chain(self, x0: np.ndarray, guess: Continuation, longest: float
               ) -> list[Edge] | None:
        """Edges from ``x0`` into the goal region by indirect multiple shooting
        (`shooting.multiple_shoot`) along the continuation's extremal ``guess``: cut into
        M equal segments (each M of `CHAIN_SEGMENTS` in turn until one gives a chain), the
        interior segments' start states and costates read off the extremal integrated
        backwards from the goal; `extremal_chain` makes and checks the edges."""
        prop = self.propagator
        prob, sys, s = prop.problem, prop.problem.system, prop.settings
        terminal = terminal_conditions(prob)
        for m in CHAIN_SEGMENTS:
            # the segments' starts, as durations back from the goal (the first is x0's)
            segments = self._segments(x0, guess, guess.duration * (1.0 - np.arange(0, m) / m))
            if segments is None:
                return None
            _, lams, xs = segments
            res = multiple_shoot(sys, x0, lams, xs, np.full(m, guess.duration / m), terminal,
                                 time_weight=s.time_weight, dt=s.dt, max_duration=longest,
                                 tolerance=SHOOT_TOLERANCE, grid_tolerance=LAND_TOLERANCE)
            if res is not None:
                chain = extremal_chain(prop, x0, res.costates, res.steps)
                if chain is not None:
                    return chain
        return self._grid_chain(x0, guess)

    def _segments(self, x0: np.ndarray, guess: Continuation, back: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The extremal ``guess`` at its segments' starts, given as durations ``back`` (m,)
        from the goal (the first at x0's end of it), integrated backwards from the goal:
        that first state (n,), the segments' costates (m, n; the first ``guess``'s own) and
        the interior segments' start states (m - 1, n), all moved by the whole turns of
        their angles that bring the first nearest ``x0`` (the goal's image nearest the
        node); None where the integration fails."""
        prop = self.propagator
        prob, sys, s = prop.problem, prop.problem.system, prop.settings
        n = sys.n_states
        with np.errstate(all="ignore"):
            z, _ = endpoints(sys, prob.goal, np.column_stack(
                [np.repeat(guess.goal_costate[None], len(back), axis=0), back]),
                s.time_weight, -s.dt)
        if not np.isfinite(z).all():
            return None
        turns = np.zeros(n)
        angles = list(sys.angle_dims)
        turns[angles] = 2.0 * np.pi * np.round((x0 - z[0, :n])[angles] / (2.0 * np.pi))
        return z[0, :n] + turns, np.vstack([guess.costate[None], z[1:, n:]]), \
            z[1:, :n] + turns

    def _grid_chain(self, x0: np.ndarray, guess: Continuation) -> list[Edge] | None:
        """`_chain`'s last resort: the extremal ``guess`` cut into ``CHAIN_SEGMENTS[-1]``
        segments whose ends lie on the RK4 grid, solved with the duration fixed
        (`multiple_shoot` without its free-final-time phase: Pontryagin's extremal of that
        duration) from ``x0``; where that fails, by continuation from the extremal's own
        start (the funnel state; the node itself for a continuation's guess) to ``x0`` at
        `GRID_FRACTIONS` of the way, each solve started from the last.

        Why: the free phase's segment ends move between RK4 steps, where the states are
        interpolated; along the acrobot's swing-up from the funnel state itself it stalled
        at a residual of 7e-5, where the grid's converges in two iterations to 1e-13. The
        start-funnel search then steers from 3 of the 4 seeds where it reached the start's
        neighbourhood and no chain was found (docs/anytime.md, "Segments on the RK4 grid")."""
        prop = self.propagator
        prob, sys, s = prop.problem, prop.problem.system, prop.settings
        m = CHAIN_SEGMENTS[-1]
        total = max(m, round(guess.duration / s.dt))
        ends = np.rint(np.arange(1, m + 1) * (total / m)).astype(np.int64)
        steps = np.diff(ends, prepend=0)
        segments = self._segments(x0, guess, (total - ends + steps) * s.dt)
        if segments is None:
            return None
        start, lams, xs = segments
        terminal = terminal_conditions(prob)

        def solve(at: np.ndarray, lams: np.ndarray, xs: np.ndarray):
            return multiple_shoot(sys, at, lams, xs, steps * s.dt, terminal,
                                  time_weight=s.time_weight, dt=s.dt,
                                  max_duration=total * s.dt, grid_tolerance=LAND_TOLERANCE,
                                  free_time=False)

        res = solve(x0, lams, xs)
        if res is None:
            for f in GRID_FRACTIONS:
                res = solve(start + f * (x0 - start), lams, xs)
                if res is None:
                    return None
                lams, xs = res.costates, res.states[1:]
        return extremal_chain(prop, x0, res.costates, res.steps)

    def report(self) -> dict:
        longer = self.duration != self.propagator.settings.funnel_duration
        return {"funnel_states": sum(len(part) for part in self.parts),
                **({"funnel_grown": self.grown} if self.grown else {}),
                # the aimed search's rounds and steerings from the start (`_from_start`)
                **({"funnel_aimed": list(self.aimed)} if self.aimed[0] else {}),
                # the derived horizon where the goal admits no LQR connection (`rrt`)
                **({"funnel_duration": self.duration} if longer else {})}

    def note(self) -> str | None:
        return None


def aimed_round(propagator: Propagator, stream: FunnelStream, search: AimedSearch,
                x0: np.ndarray, duration: float, tried: float, best: float | None = None
                ) -> tuple[bool, float, list[Edge] | None] | None:
    """One round of the query's search for funnel extremals through ``x0`` (its start), then
    the chain from ``x0`` along the pool's nearest extremal (`FunnelConnection.steer_from`,
    its own extremal's chain included, extremals of up to ``duration``) where that lies within
    the funnel's radius, `AIM_RETRY` nearer than the last one tried (at distance ``tried``)
    and, with ``best``, its cost to go from there below it. None once the search's rounds are
    done; else whether it steered, the distance of the last one tried, and the chain or None.
    The rounds of a solve (`FunnelConnection._from_start`) and of the anytime improvement
    (`improve.start_funnel`)."""
    funnel = search.step(stream.build)
    if funnel is None:
        return None
    radius = propagator.settings.funnel_radius
    dist = search.distances(funnel)
    j = int(np.argmin(dist)) if len(dist) else -1
    if j < 0 or dist[j] > radius or dist[j] > AIM_RETRY * tried or \
            (best is not None and funnel.cost_to_go[j] >= best):
        return False, tried, None
    chain = FunnelConnection(propagator, funnel, duration=duration).steer_from(
        x0, dist[j : j + 1], np.array([j]), radius, own=True)
    return True, float(dist[j]), chain


def _nearest_of(found: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The FUNNEL_POINTS nearest per row among several (distances, indices) answers, each
    (N, FUNNEL_POINTS) and sorted by distance, ties to the earlier answer."""
    d_all = np.concatenate([d for d, _ in found], axis=1)
    i_all = np.concatenate([i for _, i in found], axis=1)
    order = np.argsort(d_all, axis=1, kind="stable")[:, :FUNNEL_POINTS]
    return np.take_along_axis(d_all, order, axis=1), np.take_along_axis(i_all, order, axis=1)


class LQRConnection:
    """The LQR closed loop from the untried node with the least Lyapunov value; off (never
    connects, ``off`` says why) where the goal has no equilibrium or the loop is unstable."""

    name = "lqr"

    def __init__(self, propagator: Propagator, built: GoalLQR | str | None = None):
        self.propagator = propagator
        built = goal_lqr(propagator) if built is None else built
        self.lqr, self.off = (None, built) if isinstance(built, str) else (built, None)
        # per tree node its Lyapunov value (rows filled up to `queried`) and whether the
        # connection has started from it; `tries` counts the closed loops run
        self.value = np.full(256, np.inf)
        self.tried = np.zeros(256, dtype=bool)
        self.queried = 0
        self.tries = 0
        # the least value from which the loop ran out of time (its horizon) without
        # reaching the goal: only nodes below it are tried (from farther in V it takes longer)
        self.ceiling = np.inf

    def connect(self, tree: GrowingTree) -> tuple[int, list[Edge]] | None:
        """The LQR closed loop to the goal from the untried node with the least Lyapunov
        value, as a chain of constant-input edges; (node, edges) or None when it does not
        reach the goal region within its horizon (`GoalLQR.horizon`), leaves the
        constraints, meets an obstacle or leaves the loop's basin (`GoalLQR.run`). Once a
        loop runs out of time, only nodes with a lower value than its start are tried."""
        lqr = self.lqr
        if lqr is None:
            return None
        m = tree.data.n_nodes
        self.value = grown(self.value, m, np.inf)
        self.tried = grown(self.tried, m, False)
        if self.queried < m:
            self.value[self.queried : m] = lqr.value(tree.data.states[self.queried : m])
            self.queried = m
        value = np.where(self.tried[:m], np.inf, self.value[:m])
        node = int(np.argmin(value))
        if not value[node] < self.ceiling:
            return None
        self.tried[node] = True
        self.tries += 1
        chain, end = lqr_chain(self.propagator, lqr, tree.data.states[node])
        if end == "timeout":
            self.ceiling = float(value[node])
        return None if chain is None else (node, chain)

    def report(self) -> dict:
        return {"goal_lqr": {"tries": self.tries} if self.lqr else {"off": self.off}}

    def note(self) -> str | None:
        return None if self.lqr is not None else f"LQR goal connection off: {self.off}"

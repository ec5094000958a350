"""RRT-CoLearn (Alg. 1): the loop.

One loop grows the tree: it samples a target, lets a steering strategy propose an edge
toward it, asks the goal connections to finish at goal-biased iterations, stops at the goal,
the termination condition or a stall, and counts what became of each iteration. It knows the
strategies only through `contracts.Steering` and `contracts.Connection`; `schedule` says
when each is on. docs/architecture.md draws the picture.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from rrtcolearn.errors import ConfigError
from rrtcolearn.integrate import rollout_draws
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.planning.connections import (
    FunnelConnection,
    LQRConnection,
    ShootingConnection,
    cheaper_goal_edge,
    goal_lqr,
)
from rrtcolearn.planning.contracts import (
    OUTCOMES,
    Connection,
    Edge,
    GrowingTree,
    Progress,
    Steering,
)
from rrtcolearn.planning.controls import BATCH_ITERATIONS, RandomControls
from rrtcolearn.planning.diagnosis import diagnose
from rrtcolearn.planning.funnel import FunnelStream
from rrtcolearn.planning.learned import LearnedSteering
from rrtcolearn.planning.lqr import GoalLQR
from rrtcolearn.planning.nearest import NodeIndex
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.propagator import Propagator
from rrtcolearn.planning.schedule import (
    AUTO_FUNNEL,
    CONNECT_AFTER,
    CONTROLS_AFTER,
    FUNNEL_START,
    Schedule,
)
from rrtcolearn.planning.settings import PlannerSettings
from rrtcolearn.planning.shooting import compiled_kernels as shooting_kernels
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan, PlannerData
from rrtcolearn.systems.base import System

# (the thresholds, the settings, the outcomes and the diagnosis are defined in their own
# modules; named here too for the code that imports them from the planner)
__all__ = ["AUTO_FUNNEL", "CONNECT_AFTER", "CONTROLS_AFTER", "FUNNEL_START", "OUTCOMES",
           "Edge", "PlannerSettings", "RRTCoLearn", "diagnose", "load_kernels"]


@dataclass
class Solve:
    """What one `RRTCoLearn.solve` keeps between iterations: the growing tree, the loop's
    counters, the schedule, the goal connections by name in the order they are tried
    (None: off until the schedule switches it on), and the stream the goal funnel's
    extremals come from (the query's, shared by its solves)."""

    tree: GrowingTree
    progress: Progress
    schedule: Schedule
    connections: dict[str, Connection | None]
    funnel: FunnelStream
    goal_parent: dict | None = None  # choose-parent for the goal's record (`_cheaper_goal`)


class RRTCoLearn:
    """Alg. 1 with the learned J, U, V; needs no local planner.

    Each iteration samples a target (the goal with probability ``goal_bias``, else uniform in
    the system's state box), keeps the tree nodes whose query (node, target) is valid under V,
    expands the one with the least predicted cost-to-go J, draws steering parameters around
    U's prediction and integrates the state+costate ODEs (`learned.LearnedSteering`). An edge
    is cut at its first state inside the goal region, or before its first state that the
    problem's validity checker rejects (obstacles); it is rejected when it leaves the state
    box in a non-angle coordinate or when its input exceeds the problem's ``u_max`` anywhere
    (`propagator.Propagator`).

    Beyond the paper, for a system with an input box: once the learned steering stalls, the
    tree also grows by random-control edges (``control_edges``,
    `controls.RandomControls`), and the learned steering is kept for goal targets within
    the data's reach; goal-biased iterations try the goal connections that are on
    (`connections`, `schedule`).

    ``connections``: more goal connections, each made by calling the factory with the
    planner at the start of every solve, on from the start and tried after the planner's
    own (a `contracts.Connection`).
    """

    def __init__(self, problem: PlanningProblem, model: LearnedFunctions | None,
                 settings: PlannerSettings | None = None,
                 connections: tuple[Callable[[RRTCoLearn], Connection], ...] = ()):
        self.problem = problem
        self.model = model
        sys = problem.system
        given = settings or PlannerSettings()
        self.settings = given.resolved(sys)
        explicit = self.settings.goal_connect is True or bool(self.settings.goal_funnel)
        if explicit and sys.params_from_costate is None:
            raise ConfigError(f"system {sys.name!r} has no params_from_costate: the goal "
                              "connection and the goal funnel need it (plan.goal_connect, "
                              "plan.goal_funnel)")
        self.propagator = Propagator(problem, self.settings)
        if model is None and (self.propagator.control_box is None
                              or self.settings.control_edges is False
                              or self.settings.goal_connect is True):
            raise ConfigError("without learned functions the planner grows by random-control "
                              "edges only: it needs an input box (input limits or u_max), "
                              "plan.control_edges not false and plan.goal_connect not true")
        # the steering strategies: the learned one (with a model), random controls (with an
        # input box to draw from)
        self.learned = None if model is None else LearnedSteering(self.propagator, model)
        self.controls = None if self.propagator.control_box is None else \
            RandomControls(self.propagator)
        self.extra_connections = tuple(connections)
        # why the goal admits no LQR connection (None: it does). Where it admits none (a
        # unicycle at rest: its linearisation is not stabilisable) only shooting and the
        # funnel can connect, so they switch on even while random controls explore
        # (`schedule`), and a derived funnel runs each extremal until it leaves the state
        # box, for at most ``generate.max_duration``, whatever the data's cost bound: near
        # such a goal the states one short extremal reaches are a thin set, and the tree
        # must meet one from where it stalls (dynobench's second-order unicycle,
        # docs/dynobench.md). Turning the connection off (plan.goal_lqr false) changes
        # neither. (Asked only where shooting and the funnel can run.)
        s = self.settings
        loop = self.goal_loop if model is not None and sys.params_from_costate is not None \
            else None
        self.goal_lqr_off = loop if isinstance(loop, str) else None
        self.funnel_reach = (s.duration_cap, np.inf) \
            if self.goal_lqr_off is not None and given.funnel_duration is None \
            else (s.funnel_duration, s.funnel_max_cost)
        # the goal funnel of the last query solved: its key and its stream (`funnel_stream`)
        self._funnel: tuple[tuple, FunnelStream] | None = None
        # what the improvements of the current run of a query record for their later calls
        # (name -> record; `improve.goal.lq_tail`): emptied when a run begins (`solve`)
        self.run_records: dict[str, list] = {}

    def solve(self, termination: TerminationCondition, seed: int | np.random.SeedSequence = 0,
              control_scale: float = 1.0, query: int | np.random.SeedSequence | None = None
              ) -> Plan:
        """Grow the tree until a node reaches the goal region or ``termination`` says stop;
        random-control inputs drawn from the input box shrunk by ``control_scale`` towards
        zero (`controls.RandomControls.draw_box`; anytime planning's later solves).
        ``query``: the seed of the query this solve is one of (anytime planning's solves
        after the first: `anytime.solve_with_restarts`), by default ``seed`` (a query of
        its own): the goal funnel's extremals are drawn from a stream of the query's seed
        and built once per query (`funnel.FunnelStream`, `funnel_stream`), so a query's
        later solves reuse what its earlier ones built. A solve without ``query`` begins a
        new run of its query (`FunnelStream.begin`: the improvements' search through the
        start restarts), so a run does not continue an earlier run's search."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        controls = self.controls
        if controls is not None:
            controls.scale = float(control_scale)
        # compiled code this solve may call and no earlier one loaded: before the clock
        load_kernels(sys, explore=controls is not None and s.control_edges is not False
                     and controls.compiled, lqr=s.goal_lqr is not False,
                     shooting=self.model is not None and sys.params_from_costate is not None)
        rng = np.random.default_rng(seed)
        cpu0 = time.thread_time()
        termination.start()
        if query is None:  # a query of its own, or an anytime run's first solve
            self.funnel_stream(seed).begin()
            self.run_records = {}
        # a goal funnel asked for is built here: it counts as planning
        run = self.start(rng, seed if query is None else query)
        tree, progress, schedule = run.tree, run.progress, run.schedule
        if progress.best_goal <= prob.goal_tolerance:
            progress.goal_node = 0
        while progress.goal_node < 0 and not termination(progress.iterations):
            if schedule.exploring and controls.batch is not None:
                # the iterations up to the next goal-biased one, compiled
                budget = BATCH_ITERATIONS if termination.max_iterations is None else \
                    min(BATCH_ITERATIONS, termination.max_iterations - progress.iterations)
                if not controls.run_batch(rng, tree, progress, budget):
                    continue
                to_goal = True  # the batch ended at a goal-biased iteration: its rest here
            else:
                if s.stall_iterations and \
                        progress.iterations - progress.last_growth >= s.stall_iterations:
                    progress.stalled = True
                    break
                progress.iterations += 1
                progress.since_growth_nearer += 1
                schedule.controls_due(progress)
                to_goal = rng.random() < s.goal_bias
            target = prob.sample_goal(rng) if to_goal else \
                rng.uniform(sys.state_low, sys.state_high)
            if to_goal and self._connect(run):
                break
            self._expand(rng, run, target, to_goal)
        if controls is not None and controls.pending >= 0:
            # the last iteration's expansion, left to a compiled batch
            controls.run_batch(rng, tree, progress, 0)
        if progress.goal_node > 0 and s.goal_parent_tries and self.model is not None \
                and sys.params_from_costate is not None:
            self._cheaper_goal(run, termination)
        return self._result(run, time.thread_time() - cpu0, termination.elapsed())

    def _cheaper_goal(self, run: Solve, termination: TerminationCondition) -> None:
        """Choose-parent for the goal once the solve reached it
        (`connections.cheaper_goal_edge`): the cheaper path's goal edge (U's guess, or a
        shooting extremal from it) added below its node and made the goal node; then, where
        the goal funnel is on, the same through it (`FunnelConnection.cheaper`: a chain of
        funnel edges); the record in ``run.goal_parent``."""
        progress, tree = run.progress, run.tree
        found, run.goal_parent = cheaper_goal_edge(
            self.propagator, self.model, tree, progress.goal_node,
            self.settings.goal_parent_tries,
            lambda: termination(0))  # its time limits: the iterations are spent
        if found is not None:
            parent, edge, kind = found
            node = tree.add(parent, edge)
            if kind != "learned":  # (an extremal's kind unless recorded)
                tree.data.made_by[node] = kind
            progress.goal_node = node
        funnel = run.connections.get("funnel")
        if isinstance(funnel, FunnelConnection):  # the same through the goal funnel, if built
            best = run.goal_parent["cost"]
            chain, run.goal_parent["funnel_tries"] = funnel.cheaper(
                tree, best, self.settings.goal_parent_tries, lambda: termination(0))
            if chain is not None:
                node, edges = chain
                for edge in edges:
                    node = tree.add(node, edge)
                    tree.data.made_by[node] = "funnel"
                progress.goal_node = node
                run.goal_parent["cost"] = float(tree.data.cost_to_come(np.array([node]))[0])

    def narrowest_control_scale(self) -> float:
        """The least ``control_scale`` anytime planning narrows random controls to
        (`controls.RandomControls.narrowest_scale`); 1 (never narrowed) without random
        controls."""
        if self.controls is None or self.settings.control_edges is False:
            return 1.0
        return self.controls.narrowest_scale()

    def start(self, rng: np.random.Generator,
              query: int | np.random.SeedSequence | None = None) -> Solve:
        """The state of a new `solve`: the tree at the start, its node indices, the schedule
        and the goal connections on from the start (a funnel asked for is built here); the
        goal funnel's extremals from the stream of the query with seed ``query``
        (`funnel_stream`), or with None from ``rng``, when the funnel is built (a stream
        of this solve alone)."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        n = sys.n_states
        weight = np.asarray(s.metric_scale, dtype=np.float64)
        # tree nodes in nearest-neighbour structures: candidate parents by plain (weighted)
        # distance, and by distance with angles modulo a turn (extend, the wrapped goal)
        angle_low = np.full(n, np.nan)
        angle_low[list(sys.angle_dims)] = sys.state_low[list(sys.angle_dims)]
        plain = NodeIndex(weight)
        wrapped = NodeIndex(weight, angle_low) if sys.angle_dims else plain
        # learning-query start of every node: its state shifted by whole turns into the box
        shifts = np.empty((256, n))
        shifts[0] = sys.wrap_shift(prob.start[None])[0]
        tree = GrowingTree(PlannerData(prob.start, sys.n_params, n_inputs=sys.n_inputs),
                           weight, plain, wrapped, shifts, sys.wrap_shift, s.dt)
        for index in tree.indices:
            index.add(prob.start)
        if self.controls is not None:
            self.controls.start(tree)
        if self.learned is not None:
            self.learned.reset()
        # shooting starts from U's guess: not without learned functions
        can_connect = sys.params_from_costate is not None and self.model is not None
        schedule = Schedule.start(s, controls=self.controls is not None
                                  and s.control_edges is not False,
                                  learned=self.model is not None, can_connect=can_connect,
                                  goal_lqr=self.goal_lqr_off is None)
        funnel = FunnelStream(rng) if query is None else self.funnel_stream(query)
        on: dict[str, Connection | None] = {"shooting": None, "funnel": None, "lqr": None}
        for name, value in Schedule.initial(s).items():
            on[name] = self.connection(name, funnel, tree, value)
        for make in self.extra_connections:
            extra = make(self)
            on[extra.name] = extra
        return Solve(tree, Progress(best_goal=float(prob.goal_distance(prob.start)[0])),
                     schedule, on, funnel)

    def funnel_stream(self, query: int | np.random.SeedSequence) -> FunnelStream:
        """The goal funnel's stream of the query with seed ``query``, shared by the query's
        solves (`funnel.FunnelStream`). The planner keeps the last query's only: a solve of
        another query starts a new one (what it builds is the same as if built afresh, so
        plans do not depend on the order of queries), and at most one query's funnel is
        held in memory between solves."""
        if isinstance(query, np.random.SeedSequence):
            key = ("sequence", query.entropy, tuple(query.spawn_key))
        else:
            key = ("int", int(query))
        if self._funnel is None or self._funnel[0] != key:
            self._funnel = (key, FunnelStream.of_query(query))
        return self._funnel[1]

    def query_funnel(self) -> FunnelStream | None:
        """The goal funnel's stream of the last query solved (`funnel_stream`), or None."""
        return None if self._funnel is None else self._funnel[1]

    def connection(self, name: str, funnel: FunnelStream, tree: GrowingTree,
                   size: int | None = None) -> Connection:
        """The planner's goal connection ``name`` ("shooting", "funnel", "lqr"), built for a
        solve on ``tree``; the funnel of ``size`` extremals, or (None) the automatic one:
        FUNNEL_START extremals doubling up to AUTO_FUNNEL (`schedule`), its parts taken
        from ``funnel`` (built there once per query)."""
        if name == "shooting":
            return ShootingConnection(self.propagator, self.model)
        if name == "funnel":
            # where the goal admits no LQR connection the funnel is the only way in: where a
            # continuation fails, the chain along the funnel state's own extremal is tried
            # too (dynobench's second-order unicycle: parking 6/10 -> 9/10, docs/dynobench.md)
            own = self.goal_lqr_off is not None
            if size is None:
                built = FunnelConnection.build(self.propagator, funnel.draws(), tree.weight,
                                               FUNNEL_START, limit=AUTO_FUNNEL,
                                               grow_after=CONNECT_AFTER,
                                               reach=self.funnel_reach, own=own)
            else:
                built = FunnelConnection.build(self.propagator, funnel.draws(), tree.weight,
                                               int(size), reach=self.funnel_reach, own=own)
            # where no node steers, rounds of the query's search for extremals through
            # the start (the acrobot's first paths 7.2x -> 2.3x the optimum, seeds 0-9)
            built.aim(funnel)
            return built
        return LQRConnection(self.propagator, self.goal_loop)

    @cached_property
    def goal_loop(self) -> GoalLQR | str:
        """The LQR loop about the goal's equilibrium, or why there is none
        (`connections.goal_lqr`), built once per planner: each solve's LQR connection and
        the improvements' LQR tails use it."""
        return goal_lqr(self.propagator)

    def _connect(self, run: Solve) -> bool:
        """A goal-biased iteration's connections, each on tried in turn (those the schedule
        says are due switched on first); True when one reached the goal region."""
        progress, on, schedule = run.progress, run.connections, run.schedule
        progress.since_nearer += 1
        for name in schedule.connections_due(progress, on):
            on[name] = self.connection(name, run.funnel, run.tree)
        for name in list(on):
            connection = on[name]
            if connection is None:
                continue
            found = connection.connect(run.tree)
            if found is not None:
                parent, chain = found
                for edge in chain:
                    parent = run.tree.add(parent, edge)
                    run.tree.data.made_by[parent] = name
                progress.goal_node, progress.connection = parent, name
                return True
        return False

    def _expand(self, rng: np.random.Generator, run: Solve, target: np.ndarray,
                to_goal: bool) -> None:
        """One expansion toward ``target``: the learned steering, or while exploring random
        controls (also where the learned steering adds nothing); its outcome recorded."""
        prob, s = self.problem, self.settings
        tree, progress, exploring = run.tree, run.progress, run.schedule.exploring
        steering: Steering | None = self.learned
        if exploring and (self.learned is None or not to_goal or self.learned.nearest(
                tree.states, target, tree.weight, tree.wrapped)[2] > s.connect_reach):
            # while exploring, the learned steering only for goal targets within the data's
            # reach, where U has seen segments that long
            steering = None
        parent, edge = (-1, None) if steering is None else \
            steering.steer(rng, tree, target, to_goal)
        if edge is None and exploring:
            steering = self.controls
            parent, edge = steering.steer(rng, tree, target, to_goal)
        if edge is None:
            if steering.rejected is not None:  # (None: left to the next compiled batch)
                progress.outcomes[steering.rejected] += 1
            return
        progress.outcomes["added"] += 1
        progress.edges_by[steering.kind] += 1
        progress.last_growth = progress.iterations
        node = tree.add(parent, edge)
        d_goal = edge.end_distance if edge.end_distance is not None else \
            float(prob.goal_distance(edge.traj[-1:, : prob.system.n_states])[0])
        if d_goal < progress.best_goal:
            progress.best_goal, progress.since_nearer, progress.since_growth_nearer = \
                d_goal, 0, 0
        if edge.hit:
            progress.goal_node = node

    def _result(self, run: Solve, cpu: float, wall: float) -> Plan:
        """The plan: the path to the goal node, else to the node nearest the goal region,
        with what became of the iterations and, unsolved, why."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        tree, progress = run.tree.data, run.progress
        if progress.goal_node >= 0:
            status, end = "exact", progress.goal_node
        else:
            dist = prob.goal_distance(tree.states[: tree.n_nodes])
            end = int(np.argmin(dist))
            status = "approximate" if end != 0 else "timeout"
        input_low, input_high = sys.input_limits() if sys.input_limited else (None, None)
        on = [c for c in run.connections.values() if c is not None]
        diagnosis = None if progress.goal_node >= 0 else diagnose(
            progress.outcomes, progress.stalled, tree.n_nodes, prob.u_max is not None,
            (float(prob.goal_distance(prob.start)[0]), float(dist[end])))
        if diagnosis is not None:  # e.g. the LQR connection off: why
            diagnosis += "".join(f"; {note}" for c in on if (note := c.note()))
        reports = {k: v for c in on for k, v in c.report().items()}
        switched = run.schedule.switched
        plan = Plan(
            system=sys.name, start=prob.start, goal=prob.goal,
            goal_tolerance=prob.goal_tolerance, time_weight=s.time_weight, dt=s.dt,
            status=status, planning_time_s=wall, planning_cpu_s=cpu,
            iterations=progress.iterations, tree=tree, path_nodes=tree.path_to(end),
            u_max=prob.u_max, input_low=input_low, input_high=input_high,
            obstacles=[o.to_dict() for o in prob.validity.obstacles],
            goal_angles=prob.goal_angles, goal_test=prob.goal_test,
            end_goal_distance=self.propagator.end_goal_distance(tree.states[end]),
            # which edge reached the goal: the steering's, or a connection's
            extra={**({"goal_connected": progress.connection is not None,
                       "connection": progress.connection, **reports} if on else {}),
                   **({"connections_switched_on": switched} if switched else {}),
                   "outcomes": progress.outcomes, "stalled": progress.stalled,
                   **({"edges_by": progress.edges_by} if run.schedule.controls else {}),
                   **({"goal_parent": run.goal_parent} if run.goal_parent else {}),
                   **({} if diagnosis is None else {"diagnosis": diagnosis})},
        )
        plan.extra["duration_by"] = plan.duration_by
        if self.learned is not None:
            plan.extra["landing"] = self.learned.landing()
        return plan


def load_kernels(system: System, explore: bool = False, lqr: bool = False,
                 shooting: bool = False) -> None:
    """Load the system's compiled kernels that a plan calls and this process has not loaded
    yet (numba's on-disk cache; compiled and cached when absent, once per system and
    machine), so that no plan spends its time limit, or its CPU figure, on them.

    `RRTCoLearn.solve` calls it before its clock starts, with what that solve may call: the
    compiled random-control iterations (``explore``: `integrate.explore_jit`, about 9 s to
    compile), the LQR goal connection's loop (``lqr``: `integrate.closed_loop_jit`) and
    shooting's linear solve and interpolation (``shooting``: `shooting._eliminate`,
    `shooting._interpolate`; the goal connections and the learned edges' refinement).
    `pipeline` runs a throwaway solve when a model is fitted or loaded, so the first
    compiled call of a process (it also initialises numba's compiler, about 0.2 s) and the
    cache loads count as the model's load, not as the first plan's. Each kernel
    runs once, on a state and parameters in the middle of their boxes and for zero or one
    step, through the function the planner calls it by, so the very signatures a plan uses
    are loaded; a kernel that has a signature already is skipped (microseconds).
    """
    from rrtcolearn.integrate import propagate, rollout, rollout_batch

    n, m = system.n_states, system.n_inputs
    x = np.ascontiguousarray((system.state_low + system.state_high) / 2, dtype=np.float64)
    p = np.ascontiguousarray((system.param_low + system.param_high) / 2, dtype=np.float64)
    z = np.concatenate([x, np.zeros(n + 1)])
    inf = np.full(n, np.inf)
    calls = [
        (system.costate_from_params_jit,
         lambda: system.costate_from_params_jit(x, p, 1.0, np.empty(n))),
        (system.rollout_jit, lambda: rollout(system, z, 1.0, 0.01, 0)),
        (system.input_max_abs_jit, lambda: system.input_max_abs_jit(z)),
        (system.propagate_jit,
         lambda: propagate(system, x, np.zeros(m), 0.01, 0, -inf, inf)),
        (system.rollout_batch_jit,
         lambda: rollout_batch(system, z[None], 1.0, 0.01, 1, 1.0, 1.0, n)),
        (system.rollout_draws_jit,
         lambda: rollout_draws(system, x, np.zeros((1, n)), np.zeros(1, np.int64), 1.0, 0.01,
                               -inf, inf, None)),
    ]
    if explore:
        calls.append((system.explore_jit, lambda: _load_explore(system)))
    if lqr:  # the argument types `lqr.GoalLQR.run` and `lqr.GoalLQ.run` pass
        calls.append((system.closed_loop_jit, lambda: system.closed_loop_jit(
            x, x.copy(), np.zeros(m), np.zeros((1, m, n)), np.zeros((1, m)), np.zeros((n, n)),
            -np.ones(m), np.ones(m), np.zeros(n, bool), 0.01, 0, -inf, inf)))
    if shooting:
        calls += shooting_kernels(system)
    for kernel, call in calls:
        if kernel is None or getattr(kernel, "signatures", None):
            continue  # no compiled kernel (a system built by hand), or loaded already
        try:
            call()
        except Exception:  # loading is what counts, not the outcome of the call
            pass



def _load_explore(system: System) -> None:
    """`integrate.explore_jit` called for no iteration, through `RandomControls.run_batch`
    (so with the argument types a plan passes: one signature)."""
    x = (system.state_low + system.state_high) / 2
    planner = RRTCoLearn(PlanningProblem.create(system, x, x, 1.0), None,
                         PlannerSettings(control_edges=True))
    rng = np.random.default_rng(0)
    run = planner.start(rng)
    planner.controls.run_batch(rng, run.tree, run.progress, 0)

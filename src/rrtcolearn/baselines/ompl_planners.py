"""OMPL's kinodynamic planners (RRT, KPIECE1, EST) as peers, on any `System`.

The OMPL problem is the `PlanningProblem`: a real-vector state space of the system's n states
(its sampling box bounds OMPL's sampler; angle coordinates are not bounded in the validity
test, as for RRT-CoLearn, whose dynamics are periodic in them), the input box of
`input_box` (the system's limits, the problem's ``u_max``, or the planner's own bound),
piecewise-constant controls held for ``min_steps..max_steps`` propagation steps, each
propagated by `rrtcolearn.integrate.propagate` (RK4 of `System.dynamics` at ``dt``), the
state constraints (`PlanningProblem.constraint_box`) and obstacles as the validity test, and
the problem's goal test (`PlanningProblem.goal_distance`: ball, goal weights, wrapped
angles or a user goal function) as OMPL's goal region. The returned path is executed again
(`control_plan`); its status is that check, not OMPL's claim.

``ompl`` is an optional dependency and is imported only inside the functions. OMPL promises
determinism only when its process-wide seed is set before its first random generator exists,
so `OMPLPlanner` runs each plan in a fresh forked process (``isolated``).
"""

from __future__ import annotations

import atexit
import functools
import math
import multiprocessing
import operator
import os
import sys
import time
import traceback
from collections.abc import Callable

import numpy as np

from rrtcolearn.baselines.base import control_plan, input_box, input_box_reason
from rrtcolearn.integrate import propagate as rk4_propagate
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan
from rrtcolearn.planning.validity import Box, HalfPlane

PLANNERS = ("RRT", "KPIECE1", "EST")

_ran_in_this_process = False  # later runs in this process re-seed without OMPL's promise


def ompl_available() -> bool:
    """True when the OMPL Python bindings (``pip install ompl``) can be imported."""
    try:
        from ompl import base, control, util  # noqa: F401
    except ImportError:
        return False
    _silence_exit_reports()
    return True


@functools.cache
def _silence_exit_reports() -> None:
    atexit.register(_quiet_exit)  # once per process


def _quiet_exit() -> None:
    """At interpreter exit, after everything this process had to say: stderr closed, as
    the bindings' nanobind prints some 25 lines of reference-leak reports for OMPL's
    objects and types while the interpreter shuts down (`_isolated_worker` calls it too)."""
    sys.stdout.flush()
    sys.stderr.flush()
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)


def _obstacle_free(problem: PlanningProblem) -> Callable[[list], bool] | None:
    """Per-state test ``state (list of n floats) -> no obstacle contains it``; None without
    obstacles.

    OMPL asks about one state at a time, where ``problem.validity`` costs ~10 us of numpy
    overhead; boxes and half-planes are therefore tested in plain Python with the same wrap
    of angles into the sampling box. Anything else falls back to ``problem.validity``.
    """
    checker = problem.validity
    if not checker:
        return None
    if checker.user_checker is not None or not all(
            isinstance(o, Box | HalfPlane) for o in checker.obstacles):
        return lambda x: bool(checker(np.array([x]))[0])
    system = problem.system
    angles = [(j, float(system.state_low[j])) for j in system.angle_dims]
    two_pi = 2.0 * np.pi
    boxes = [(o.low.tolist(), o.high.tolist()) for o in checker.obstacles if isinstance(o, Box)]
    planes = [(o.normal.tolist(), float(o.offset)) for o in checker.obstacles
              if isinstance(o, HalfPlane)]

    def free(x: list) -> bool:
        x = list(x)
        for j, lo in angles:  # System.wrap_shift, scalar
            x[j] = x[j] + -two_pi * math.floor((x[j] - lo) / two_pi)
        for low, high in boxes:
            if all(a <= v <= b for a, v, b in zip(low, x, high, strict=True)):
                return False
        return all(sum(c * v for c, v in zip(normal, x, strict=True)) <= offset
                   for normal, offset in planes)

    return free


def _goal_distance(problem: PlanningProblem) -> Callable[[list], float]:
    """Scalar ``state -> distance to the goal region`` (`PlanningProblem.goal_distance`), in
    plain Python unless the goal is a user function."""
    if problem.goal_fn is not None:
        return lambda x: float(problem.goal_distance(np.array([x]))[0])
    goal = problem.goal.tolist()
    weights = [1.0] * len(goal) if problem.goal_weights is None else \
        problem.goal_weights.tolist()
    angles = set(problem.goal_angles)
    two_pi = 2.0 * math.pi

    def distance(x: list) -> float:
        total = 0.0
        for j, (v, g, w) in enumerate(zip(x, goal, weights, strict=True)):
            d = v - g
            if j in angles:
                d = (d + math.pi) % two_pi - math.pi
            total += (w * d) ** 2
        return math.sqrt(total)

    return distance


class OMPLPlanner:
    """One of OMPL's control-based planners (``planner`` in `PLANNERS`) as a
    `rrtcolearn.planners.Planner`.

    ``u_max`` bounds the inputs the problem leaves unbounded; ``dt`` is the RK4 step and
    ``propagation_step`` (a multiple of it) OMPL's, a control held for
    ``min_steps..max_steps`` of those. ``time_weight`` only prices the path (OMPL's planners
    ignore cost). ``isolated``: each plan in a fresh forked process, so ``seed`` fixes OMPL's
    random numbers (``seed + 1`` goes to ``ompl.util.RNG.setSeed``, since OMPL turns 0 into 1).
    OMPL stops at ``termination``'s wall or CPU time limit; its bindings count no iterations.
    """

    def __init__(self, planner: str = "RRT", *, time_weight: float = 1.0,
                 u_max: float | None = None, dt: float = 0.01, propagation_step: float = 0.02,
                 min_steps: int = 1, max_steps: int = 25, isolated: bool = True):
        if planner not in PLANNERS:
            raise ValueError(f"unknown OMPL planner {planner!r}; use one of "
                             f"{', '.join(PLANNERS)}")
        try:
            min_steps, max_steps = operator.index(min_steps), operator.index(max_steps)
        except TypeError:
            raise ValueError(f"min_steps and max_steps must be integers, got {min_steps!r}, "
                             f"{max_steps!r}") from None
        if not 1 <= min_steps <= max_steps:
            raise ValueError(f"need 1 <= min_steps <= max_steps, got {min_steps}, {max_steps}")
        k = round(propagation_step / dt)
        if k < 1 or abs(k * dt - propagation_step) > 1e-9:
            raise ValueError(f"propagation_step must be a positive multiple of dt = {dt} s, "
                             f"got {propagation_step!r}")
        self.planner = planner
        self.name = f"ompl-{planner}"
        self.time_weight = time_weight
        self.u_max = u_max
        self.dt = dt
        self.propagation_step = propagation_step
        self.min_steps = min_steps
        self.max_steps = max_steps
        self.isolated = isolated

    def supports(self, problem: PlanningProblem) -> str | None:
        """None, or why the planner cannot run on ``problem`` (no ompl, no input box)."""
        if not ompl_available():
            return "the ompl package is not installed (extra 'ompl')"
        return input_box_reason(problem, self.u_max)

    def solve(self, problem: PlanningProblem, termination: TerminationCondition,
              seed: int = 0) -> Plan:
        """Plan with OMPL until its first exact solution or ``termination``'s time limit."""
        try:
            seed = operator.index(seed)
        except TypeError:
            raise ValueError(f"seed must be an integer, got {seed!r}") from None
        if not 0 <= seed < 2**32 - 1:
            raise ValueError(f"seed must lie in [0, 2**32 - 2], got {seed}")
        if termination.time_limit is None and termination.cpu_time_limit is None:
            raise ValueError("OMPL needs a time limit (its bindings count no iterations)")
        input_box(problem, self.u_max)  # a clear error here, not in the worker
        if self.isolated:
            wait = (termination.time_limit or termination.cpu_time_limit) + 120.0
            return run_isolated(self._solve_here, problem, termination, seed,
                                process_timeout=wait)
        return self._solve_here(problem, termination, seed)

    def _solve_here(self, problem: PlanningProblem, termination: TerminationCondition,
                    seed: int) -> Plan:
        global _ran_in_this_process
        from ompl import base as ob
        from ompl import control as oc
        from ompl import util as ou

        log_level = ou.getLogLevel()
        ou.setLogLevel(ou.LOG_WARN)
        ompl_seed = seed + 1
        ou.RNG.setSeed(ompl_seed)
        seeded_first = not _ran_in_this_process and ou.RNG.getSeed() == ompl_seed
        _ran_in_this_process = True
        try:
            return self._plan(ob, oc, problem, termination,
                              {"ompl_seed": ompl_seed,
                               "seeded_before_first_rng": bool(seeded_first)})
        finally:
            ou.setLogLevel(log_level)

    def _plan(self, ob, oc, problem: PlanningProblem, termination: TerminationCondition,
              extra: dict) -> Plan:
        """Build the OMPL problem, run the planner, and execute its path again."""
        system = problem.system
        n, m = system.n_states, system.n_inputs
        low_u, high_u = input_box(problem, self.u_max)
        clow, chigh = problem.constraint_box
        cl, ch = clow.tolist(), chigh.tolist()
        obstacle_free = _obstacle_free(problem)
        check_obstacles = bool(problem.validity)
        goal_distance = _goal_distance(problem)
        dt = self.dt
        counts = {"propagate_calls": 0, "validity_calls": 0}

        space = ob.RealVectorStateSpace(n)
        bounds = ob.RealVectorBounds(n)
        for j in range(n):
            bounds.setLow(j, float(problem.state_low[j]))
            bounds.setHigh(j, float(problem.state_high[j]))
        space.setBounds(bounds)
        cspace = oc.RealVectorControlSpace(space, m)
        cbounds = ob.RealVectorBounds(m)
        for j in range(m):
            cbounds.setLow(j, float(low_u[j]))
            cbounds.setHigh(j, float(high_u[j]))
        cspace.setBounds(cbounds)
        si = oc.SpaceInformation(space, cspace)

        def is_valid(state) -> bool:
            counts["validity_calls"] += 1
            # chained comparisons are False for NaN, so non-finite states are invalid too
            for j in range(n):
                if not cl[j] <= state[j] <= ch[j]:
                    return False
            return obstacle_free is None or obstacle_free([state[j] for j in range(n)])

        # OMPL calls the propagator for every step of every edge: with the system's compiled
        # kernel it runs on buffers kept here and returns two integers (a third of the CPU
        # of `integrate.propagate`'s arrays on each call, then half again; the same states)
        kernel = system.hold_jit
        x_buf, u_buf = np.empty(n), np.empty(m)
        box = np.ascontiguousarray(np.vstack([clow, chigh]), dtype=np.float64)
        scratch, out = np.empty((5, n)), [np.empty((32, n))]
        if kernel is not None:  # loaded (or compiled once) before the timed solve
            kernel(np.zeros(n), np.zeros(m), 0, dt, box, out[0], scratch)

        def propagate(start, control, duration, result) -> None:
            # OMPL checks the state at the end of each propagation step, so the first invalid
            # RK4 state inside it is handed back instead, which makes OMPL reject the step:
            # executed paths are valid at every RK4 step.
            counts["propagate_calls"] += 1
            steps = round(duration / dt)
            if kernel is None:
                traj = rk4_propagate(system, np.array([start[j] for j in range(n)]),
                                     np.array([control[j] for j in range(m)]), dt,
                                     steps, clow, chigh)[1:]
                last = len(traj) - 1
            else:
                for j in range(n):
                    x_buf[j] = start[j]
                for j in range(m):
                    u_buf[j] = control[j]
                if steps > len(out[0]):
                    out[0] = np.empty((steps, n))
                traj = out[0]
                kept, stop = kernel(x_buf, u_buf, steps, dt, box, traj, scratch)
                last = kept if stop else kept - 1  # the last state, a stopped one
            if last < 0:  # no RK4 step: the state stays where it was
                for j in range(n):
                    result[j] = start[j]
                return
            if check_obstacles and last > 0:
                ok = problem.validity(traj[:last])
                if not ok.all():
                    last = int(np.argmin(ok))
            end = traj[last].tolist()
            for j in range(n):
                result[j] = end[j]

        si.setStateValidityChecker(is_valid)
        si.setStatePropagator(propagate)
        si.setPropagationStepSize(self.propagation_step)
        si.setMinMaxControlDuration(self.min_steps, self.max_steps)
        si.setup()

        class GoalRegion(ob.GoalRegion):
            """The problem's goal region (`PlanningProblem.goal_distance`)."""

            def distanceGoal(self, state) -> float:  # OMPL's virtual method
                return goal_distance([state[j] for j in range(n)])

        goal = GoalRegion(si)
        goal.setThreshold(problem.goal_tolerance)
        start = si.allocState()
        for j in range(n):
            start[j] = float(problem.start[j])
        pdef = ob.ProblemDefinition(si)
        pdef.addStartState(start)
        pdef.setGoal(goal)
        algo = getattr(oc, self.planner)(si)
        algo.setProblemDefinition(pdef)
        algo.setup()

        termination.start()
        ptc = ob.PlannerTerminationCondition(lambda: bool(termination(0)))
        cpu0 = time.process_time()
        status = algo.solve(ptc)
        cpu, wall = time.process_time() - cpu0, termination.elapsed()

        kind = status.getStatus()
        claimed = kind == ob.PlannerStatus.EXACT_SOLUTION and pdef.hasExactSolution()
        data = ob.PlannerData(si)
        algo.getPlannerData(data)
        controls, steps, ompl_end = np.zeros((0, m)), np.zeros(0, dtype=np.int64), None
        if pdef.hasSolution():
            sol = pdef.getSolutionPath()
            k = sol.getControlCount()
            steps = np.array([round(sol.getControlDuration(i) / dt) for i in range(k)],
                             dtype=np.int64)
            controls = np.array([[sol.getControl(i)[j] for j in range(m)] for i in range(k)],
                                dtype=np.float64).reshape(k, m)
            last = sol.getState(sol.getStateCount() - 1)
            ompl_end = np.array([last[j] for j in range(n)])
        plan = control_plan(
            problem, controls, steps, dt=dt, time_weight=self.time_weight, cpu_s=cpu,
            wall_s=wall, iterations=0, graph_states=int(data.numVertices()),
            extra={**extra, "planner": self.name, "ompl_claimed_exact": bool(claimed),
                   "ompl_status": kind.name, **counts, "input_low": low_u.tolist(),
                   "input_high": high_u.tolist(), "propagation_step": self.propagation_step,
                   "min_steps": self.min_steps, "max_steps": self.max_steps})
        if ompl_end is not None:
            plan.extra["resim_end_gap"] = float(np.linalg.norm(
                plan.tree.states[plan.path_nodes[-1]] - ompl_end))
        return plan


def _isolated_worker(conn, fn: Callable, args: tuple) -> None:
    """Child process body: run one plan, send the result back, silence exit-time warnings."""
    try:
        try:
            msg = ("ok", fn(*args))
        except Exception as exc:
            msg = ("error", exc, traceback.format_exc())
        try:
            conn.send(msg)
        except Exception as exc:  # something unpicklable: send text instead
            what = msg[1] if msg[0] == "error" else exc
            conn.send(("error", RuntimeError(f"{type(what).__name__}: {what}"),
                       msg[2] if msg[0] == "error" else traceback.format_exc()))
    finally:
        conn.close()
        _quiet_exit()  # now: a forked child exits without atexit handlers


def run_isolated(fn: Callable, *args, process_timeout: float | None = None,
                 start_method: str | None = None):
    """``fn(*args)`` in a fresh process, so OMPL's seed is set before its first generator.

    Errors in the child are re-raised here; ``process_timeout`` (default 600 s) bounds the
    wait for the child. On Linux the child is forked (about 10 ms, against about 1 s to spawn
    an interpreter and import numpy); that is fresh for OMPL as long as the calling process
    never ran a planner itself, which holds for the experiment's workers. With
    ``start_method="spawn"`` ``fn`` and ``args`` must be picklable (a problem's system built
    by ``symbolic`` is not: spawn is for other platforms' sake only).
    """
    if start_method is None:
        start_method = "fork" if sys.platform == "linux" else "spawn"
    ctx = multiprocessing.get_context(start_method)
    receiver, sender = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_isolated_worker, daemon=True, args=(sender, fn, args))
    proc.start()
    sender.close()
    wait = 600.0 if process_timeout is None else process_timeout
    try:
        if not receiver.poll(wait):
            raise TimeoutError(f"the isolated planner gave no result within {wait:g} s")
        try:
            msg = receiver.recv()
        except EOFError:
            proc.join(5.0)
            raise RuntimeError(f"the isolated planner died (exit code {proc.exitcode})") \
                from None
    finally:
        receiver.close()
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
            proc.join()
    if msg[0] == "error":
        raise msg[1] from RuntimeError(f"in the isolated worker process:\n{msg[2]}")
    return msg[1]

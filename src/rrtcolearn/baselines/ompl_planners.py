"""OMPL's kinodynamic planners (RRT, KPIECE1, EST) on the pendulum swing-up, as baselines.

The problem matches the other baselines: state box = the system's sampling box, inputs bounded
by ``u_max``, piecewise-constant controls held for ``min_steps..max_steps`` propagation steps,
RK4 with a 0.01 s sub-step inside each step, goal = Euclidean ball in (theta, omega). Every
returned path is re-simulated with ``path_metrics``; ``solved`` is that check, not OMPL's claim.

``ompl`` is an optional dependency and is imported only inside the functions. OMPL promises
determinism only when its process-wide seed is set before its first random generator exists,
so reproducible runs go through ``run_ompl_isolated`` (one fresh "spawn" process per run).
"""

from __future__ import annotations

import math
import multiprocessing
import operator
import os
import sys
import time
import traceback
from collections.abc import Callable, Sequence

import numpy as np

from rrtcolearn.baselines.base import BaselineResult, ControlPath, path_metrics, simulate_controls
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.validity import Box, HalfPlane
from rrtcolearn.systems import make

PLANNERS = ("RRT", "KPIECE1", "EST")
SUBSTEP = 0.01  # RK4 step inside a propagation step; path_metrics re-simulates with it too

_ran_in_this_process = False  # later runs in this process re-seed without OMPL's promise


def ompl_available() -> bool:
    """True when the OMPL Python bindings (``pip install ompl``) can be imported."""
    try:
        from ompl import base, control, util  # noqa: F401
    except ImportError:
        return False
    return True


def _substeps(propagation_step: float) -> int:
    """Number of 0.01 s RK4 steps in one propagation step; ValueError unless a multiple."""
    k = round(propagation_step / SUBSTEP)
    if k < 1 or abs(k * SUBSTEP - propagation_step) > 1e-9:
        raise ValueError(f"propagation_step must be a positive multiple of {SUBSTEP} s, "
                         f"got {propagation_step!r}")
    return k


def _obstacle_free(problem: PlanningProblem) -> Callable[[float, float], bool] | None:
    """Per-state test ``(theta, omega) -> no obstacle contains it``; None without obstacles.

    OMPL asks about one state at a time, where ``problem.validity`` costs ~10 us of numpy
    overhead; boxes and half-planes are therefore tested in plain Python with the same wrap
    of theta into the state box. Anything else falls back to ``problem.validity``. The
    re-simulation check of the returned path always uses ``problem.validity`` itself.
    """
    checker = problem.validity
    if not checker:
        return None
    if checker.user_checker is not None or not all(
            isinstance(o, Box | HalfPlane) for o in checker.obstacles):
        return lambda th, om: bool(checker(np.array([[th, om]]))[0])
    lo = float(problem.system.state_low[0])
    two_pi = 2.0 * np.pi
    boxes = [(float(o.low[0]), float(o.high[0]), float(o.low[1]), float(o.high[1]))
             for o in checker.obstacles if isinstance(o, Box)]
    planes = [(float(o.normal[0]), float(o.normal[1]), float(o.offset))
              for o in checker.obstacles if isinstance(o, HalfPlane)]

    def free(th: float, om: float) -> bool:
        th = th + -two_pi * math.floor((th - lo) / two_pi)  # System.wrap_shift, scalar
        for a0, b0, a1, b1 in boxes:
            if a0 <= th <= b0 and a1 <= om <= b1:
                return False
        return all(n0 * th + n1 * om <= c for n0, n1, c in planes)

    return free


def solve_ompl(planner: str, start, goal, goal_tolerance: float, *, u_max: float,
               time_limit: float = 10.0, seed: int = 0, obstacles: Sequence[dict] = (),
               time_weight: float = 1.0, propagation_step: float = 0.02, min_steps: int = 1,
               max_steps: int = 25) -> BaselineResult:
    """Plan the pendulum swing-up with OMPL's control-based ``planner`` in this process.

    Stops at the first exact solution or after ``time_limit`` wall seconds; ``cpu_s`` is the
    process CPU time of the planner's ``solve`` call. ``seed`` + 1 goes to
    ``ompl.util.RNG.setSeed`` (OMPL turns 0 into 1, which would merge seeds 0 and 1). OMPL
    only promises determinism when the seed is set before its first random generator exists
    (``extra["seeded_before_first_rng"]``); ``run_ompl_isolated`` guarantees that.
    ``time_weight`` only prices the returned path (OMPL's planners ignore cost).
    """
    global _ran_in_this_process
    if planner not in PLANNERS:
        raise ValueError(f"unknown OMPL planner {planner!r}; use one of {', '.join(PLANNERS)}")
    if u_max is None or not (np.isfinite(u_max) and u_max > 0):
        raise ValueError(f"OMPL needs control bounds: u_max must be a positive number, "
                         f"got {u_max!r}")
    try:
        min_steps, max_steps, seed = (operator.index(v) for v in (min_steps, max_steps, seed))
    except TypeError:
        raise ValueError(f"min_steps, max_steps and seed must be integers, "
                         f"got {min_steps!r}, {max_steps!r}, {seed!r}") from None
    if not 1 <= min_steps <= max_steps:
        raise ValueError(f"need 1 <= min_steps <= max_steps, got {min_steps}, {max_steps}")
    if not 0 <= seed < 2**32 - 1:
        raise ValueError(f"seed must lie in [0, 2**32 - 2], got {seed}")
    if not (np.isfinite(time_limit) and time_limit > 0):
        raise ValueError(f"time_limit must be a positive number, got {time_limit!r}")
    h = propagation_step / _substeps(propagation_step)
    system = make("pendulum")
    problem = PlanningProblem.create(system, start, goal, goal_tolerance, u_max=u_max,
                                     obstacles=list(obstacles))

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
        return _solve(ob, oc, planner, problem, time_limit, time_weight, propagation_step,
                      h, min_steps, max_steps,
                      {"ompl_seed": ompl_seed, "seeded_before_first_rng": bool(seeded_first)})
    finally:
        ou.setLogLevel(log_level)


def _solve(ob, oc, planner: str, problem: PlanningProblem, time_limit: float,
           time_weight: float, propagation_step: float, h: float, min_steps: int,
           max_steps: int, extra: dict) -> BaselineResult:
    """Build the OMPL problem, run the planner, and check its path by re-simulation."""
    system = problem.system
    lo0, lo1 = (float(v) for v in system.state_low)
    hi0, hi1 = (float(v) for v in system.state_high)
    g0, g1 = (float(v) for v in problem.goal)
    u_max = float(problem.u_max)
    check_obstacles = bool(problem.validity)
    obstacle_free = _obstacle_free(problem)
    counts = {"propagate_calls": 0, "validity_calls": 0}

    space = ob.RealVectorStateSpace(2)
    bounds = ob.RealVectorBounds(2)
    for j, (lo, hi) in enumerate(((lo0, hi0), (lo1, hi1))):
        bounds.setLow(j, lo)
        bounds.setHigh(j, hi)
    space.setBounds(bounds)
    cspace = oc.RealVectorControlSpace(space, 1)
    cbounds = ob.RealVectorBounds(1)
    cbounds.setLow(-u_max)
    cbounds.setHigh(u_max)
    cspace.setBounds(cbounds)
    si = oc.SpaceInformation(space, cspace)

    def free(th: float, om: float) -> bool:
        # chained comparisons are False for NaN, so non-finite states are invalid too
        if not (lo0 <= th <= hi0 and lo1 <= om <= hi1):
            return False
        return obstacle_free is None or obstacle_free(th, om)

    def is_valid(state) -> bool:
        counts["validity_calls"] += 1
        return free(state[0], state[1])

    def propagate(start, control, duration, result) -> None:
        # RK4 exactly as simulate_controls does it; OMPL checks the state at the end of each
        # propagation step, so an invalid intermediate sub-step state is handed back instead,
        # which makes OMPL reject the step: re-simulated paths are valid at every sub-step.
        counts["propagate_calls"] += 1
        th, om, u = start[0], start[1], control[0]
        n = round(duration / h)
        for i in range(n):
            k1t, k1o = om, math.sin(th) + u
            t2, o2 = th + 0.5 * h * k1t, om + 0.5 * h * k1o
            k2t, k2o = o2, math.sin(t2) + u
            t3, o3 = th + 0.5 * h * k2t, om + 0.5 * h * k2o
            k3t, k3o = o3, math.sin(t3) + u
            t4, o4 = th + h * k3t, om + h * k3o
            k4t, k4o = o4, math.sin(t4) + u
            th = th + h / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t)
            om = om + h / 6.0 * (k1o + 2 * k2o + 2 * k3o + k4o)
            if i < n - 1 and not free(th, om):
                break
        result[0] = th
        result[1] = om

    si.setStateValidityChecker(is_valid)
    si.setStatePropagator(propagate)
    si.setPropagationStepSize(propagation_step)
    si.setMinMaxControlDuration(min_steps, max_steps)
    si.setup()

    class BallGoal(ob.GoalRegion):
        """Euclidean ball of radius goal_tolerance around the goal in (theta, omega)."""

        def distanceGoal(self, state) -> float:  # OMPL's virtual method
            return math.hypot(state[0] - g0, state[1] - g1)

    goal = BallGoal(si)
    goal.setThreshold(problem.goal_tolerance)
    start = si.allocState()
    start[0], start[1] = (float(v) for v in problem.start)
    pdef = ob.ProblemDefinition(si)
    pdef.addStartState(start)
    pdef.setGoal(goal)
    algo = getattr(oc, planner)(si)
    algo.setProblemDefinition(pdef)
    algo.setup()

    cpu0, wall0 = time.process_time(), time.perf_counter()
    status = algo.solve(ob.timedPlannerTerminationCondition(time_limit))
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0

    kind = status.getStatus()
    exact = kind == ob.PlannerStatus.EXACT_SOLUTION and pdef.hasExactSolution()
    if exact:
        label = "exact"
    elif kind == ob.PlannerStatus.APPROXIMATE_SOLUTION:
        label = "approximate"
    else:
        label = "timeout"
    data = ob.PlannerData(si)
    algo.getPlannerData(data)
    nodes = int(data.numVertices())

    path = None
    ompl_end = None
    if pdef.hasSolution():
        sol = pdef.getSolutionPath()
        k = sol.getControlCount()
        steps = np.array([round(sol.getControlDuration(i) / propagation_step)
                          for i in range(k)], dtype=np.int64)
        controls = np.array([[sol.getControl(i)[0]] for i in range(k)], dtype=np.float64)
        path = ControlPath(problem.start.copy(), controls.reshape(k, 1),
                           steps * propagation_step)
        last = sol.getState(sol.getStateCount() - 1)
        ompl_end = np.array([last[0], last[1]])

    metrics = path_metrics(system, path, SUBSTEP, time_weight, problem.goal,
                           problem.goal_tolerance)
    resim_valid = False
    if path is not None and not len(path.durations):  # the start already lies in the goal
        gap = float(np.linalg.norm(problem.start - problem.goal))
        metrics.update(final_goal_distance=gap,
                       reaches_goal=gap <= problem.goal_tolerance + 1e-9)
        resim_valid = True
    elif path is not None:
        states = simulate_controls(system, path, SUBSTEP)
        inside = np.all((states >= system.state_low) & (states <= system.state_high), axis=1)
        resim_valid = bool(inside.all() and (not check_obstacles or problem.validity(states).all()))
        extra["resim_end_gap"] = float(np.linalg.norm(states[-1] - ompl_end))
    solved = bool(metrics["reaches_goal"] and resim_valid)
    extra.update({
        "ompl_claimed_exact": bool(exact),
        "ompl_status": kind.name,
        "solution_difference": float(pdef.getSolutionDifference()) if path is not None else None,
        "resim_valid": resim_valid,
        **metrics,
        **counts,
        "time_weight": time_weight,
        "u_max": u_max,
        "goal_tolerance": problem.goal_tolerance,
        "propagation_step": propagation_step,
        "min_steps": min_steps,
        "max_steps": max_steps,
        "time_limit": time_limit,
    })
    # The control planners' Python bindings expose no iteration counter.
    return BaselineResult(f"ompl-{planner.lower()}", solved, label, cpu, wall, 0, nodes, path,
                          extra)


def _isolated_worker(conn, planner: str, args: tuple, kwargs: dict) -> None:
    """Child process body: run one plan, send the result back, silence exit-time warnings."""
    try:
        try:
            msg = ("ok", solve_ompl(planner, *args, **kwargs))
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
        sys.stdout.flush()
        sys.stderr.flush()
        # nanobind prints reference-leak reports for OMPL objects at interpreter exit
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)


def run_ompl_isolated(planner: str, start, goal, goal_tolerance: float, *, u_max: float,
                      seed: int = 0, time_limit: float = 10.0,
                      process_timeout: float | None = None, start_method: str | None = None,
                      **kwargs) -> BaselineResult:
    """``solve_ompl`` in a fresh process, so ``seed`` fixes OMPL's random numbers.

    Same seed and arguments give the same path. ``kwargs`` go to ``solve_ompl``. Errors in
    the child are re-raised here; ``process_timeout`` (default ``time_limit + 120`` s) bounds
    the wait for the child. On Linux the child is forked (about 10 ms, against about 1 s to
    spawn an interpreter and import numpy); that is fresh for OMPL as long as the calling
    process never ran a planner itself, which holds for the experiment's workers. Pass
    ``start_method="spawn"`` otherwise (a calling script then needs a ``__main__`` guard).
    """
    if start_method is None:
        start_method = "fork" if sys.platform == "linux" else "spawn"
    ctx = multiprocessing.get_context(start_method)
    receiver, sender = ctx.Pipe(duplex=False)
    kwargs = {**kwargs, "u_max": u_max, "seed": seed, "time_limit": time_limit}
    proc = ctx.Process(target=_isolated_worker, daemon=True,
                       args=(sender, planner, (start, goal, goal_tolerance), kwargs))
    proc.start()
    sender.close()
    wait = time_limit + 120.0 if process_timeout is None else process_timeout
    try:
        if not receiver.poll(wait):
            raise TimeoutError(f"OMPL {planner} worker gave no result within {wait:g} s")
        try:
            msg = receiver.recv()
        except EOFError:
            proc.join(5.0)
            raise RuntimeError(f"OMPL {planner} worker died (exit code {proc.exitcode})") \
                from None
    finally:
        receiver.close()
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
            proc.join()
    if msg[0] == "error":
        raise msg[1] from RuntimeError(f"in the OMPL worker process:\n{msg[2]}")
    return msg[1]

"""Anytime planning: solve again with fresh seeds, improve each path, keep the cheapest.

Every planner (RRT-CoLearn and every peer) returns its first solution. `solve_with_restarts`
takes one planner's solve of one problem, ``solve(termination, seed) -> Plan`` (`RRTCoLearn`'s
own ``solve``, or ``lambda t, s: peer.solve(problem, t, s)`` for a `rrtcolearn.planners`
peer), and spends the rest of the budget on further solves with child seeds of the query's
seed. Each solved path may be passed through ``improve`` (``plan.anytime`` uses
`planning.improve.shortcut`: stretches of the path replaced by single extremals, and its
tail by single extremals or LQR chains to the goal, in the same tree), within an allowance
of the CPU its solve took, shrinking where improving does not pay. It returns the cheapest
solved plan, with its best cost against planning CPU recorded in ``plan.extra["anytime"]``
(OMPL's progress properties, the data a best-cost-over-time figure is drawn from). Without
``improve`` it is the restart baseline an anytime scheme has to beat at equal CPU
(docs/anytime.md). With ``narrowest`` below 1 (``plan.anytime``: where random-control inputs
can cost more than the time) later solves draw their random controls from an input box
narrowed towards zero after each solve cheaper than all before it, so that later solves
look for cheaper paths rather than repeat the first in expectation.

The first solve uses the query's own seed, so the first solution, and the time to it, are a
plain solve's. With an iteration budget (``TerminationCondition.max_iterations``: the
iterations of all solves together, and one per node an improvement tries) the result depends
on the seed only; with a time budget it depends, as every anytime planner's does, on how fast
the machine ran.
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan

__all__ = ["solve_with_restarts"]


def _remaining(termination: TerminationCondition, iterations: int, cpu0: float
               ) -> TerminationCondition | None:
    """What is left of ``termination``'s budget after ``iterations`` iterations and the
    process CPU since ``cpu0``; None when any part of it is spent."""
    wall = None if termination.time_limit is None else \
        termination.time_limit - termination.elapsed()
    its = None if termination.max_iterations is None else \
        termination.max_iterations - iterations
    cpu = None if termination.cpu_time_limit is None else \
        termination.cpu_time_limit - (time.process_time() - cpu0)
    if any(v is not None and v <= 0 for v in (wall, its, cpu)):
        return None
    return TerminationCondition(wall, its, cpu)


def _at_most_spent(left: TerminationCondition, termination: TerminationCondition,
                   iterations: int, cpu0: float) -> TerminationCondition:
    """``left`` cut to no more than what has been spent so far: wall time, iterations and
    process CPU since ``cpu0``, each where the budget has that part."""
    def cut(rest: float | None, spent: float) -> float | None:
        return None if rest is None else min(rest, spent)

    return TerminationCondition(cut(left.time_limit, termination.elapsed()),
                                cut(left.max_iterations, iterations),
                                cut(left.cpu_time_limit, time.process_time() - cpu0))


# ``allowance``'s default: each improvement may take this multiple of what the solves took
# (times its record's (gains + 1) / (tries + 1)). 3 rather than 1 spends more of the budget
# on improving the paths found and less on further solves: measured on the nine problems of
# bench/ablation.py, 10 seeds of 10 s each (docs/anytime.md, "The improvements' allowance")
ALLOWANCE = 3.0


def _improved(improve: Callable[[Plan, Callable[[], bool]], Plan], p: Plan, fraction: float,
              termination: TerminationCondition, iterations: int, cpu0: float,
              grown: tuple[float, int] | None = None, in_steps: bool = False
              ) -> tuple[Plan, int, float, float]:
    """``improve(p, stop)`` within ``fraction`` of what ``p``'s solve took (of ``grown``,
    the CPU and iterations given instead), and the iterations, thread CPU and wall time it
    spent. With an iteration budget (or ``in_steps``) the allowance is in iterations, each
    step of the improvement (a ``stop()`` call) counting as one, so that the result stays a
    function of the seed; else in CPU seconds."""
    t0, c0 = time.perf_counter(), time.thread_time()
    grown_cpu, grown_its = grown if grown is not None else (p.planning_cpu_s, p.iterations)
    cpu_share = grown_cpu * fraction
    its_share = max(1, grown_its) * fraction
    steps = 0

    def stop() -> bool:
        nonlocal steps
        steps += 1
        if in_steps or termination.max_iterations is not None:
            return steps > its_share or \
                _remaining(termination, iterations + steps, cpu0) is None
        return time.thread_time() - c0 >= cpu_share or \
            _remaining(termination, iterations, cpu0) is None

    out = improve(p, stop)
    return out, steps, time.thread_time() - c0, time.perf_counter() - t0


def _takes_query(solve: Callable[..., Plan]) -> bool:
    """Whether ``solve`` has a parameter ``query`` (the query's seed)."""
    try:
        return "query" in inspect.signature(solve).parameters
    except (TypeError, ValueError):  # (a callable without a signature to inspect)
        return False


def solve_with_restarts(solve: Callable[..., Plan],
                        termination: TerminationCondition, seed: int = 0,
                        improve: Callable[[Plan, Callable[[], bool]], Plan] | None = None,
                        narrowest: float = 1.0,
                        first: Callable[[Plan, Callable[[], bool]], Plan] | None = None,
                        solves: int | None = None, allowance: float = ALLOWANCE,
                        in_steps: bool = False,
                        accept: Callable[[Plan], bool] | None = None) -> Plan:
    """Call ``solve`` until ``termination``'s whole budget is spent, each solve after the
    first with a fresh child seed of ``seed``, each solved plan then passed through
    ``improve(plan, stop)`` if given (e.g. `planning.improve.shortcut`; ``stop()`` is true once
    the budget is spent); the cheapest solved plan (or, with none solved, the first plan),
    with ``extra["anytime"]``: the scheme, the number of solves, and ``progress``, [planning
    CPU so far, best cost] at each improvement.

    ``narrowest`` < 1 (`controls.RandomControls.narrowest_scale`): later solves draw their
    random controls from a narrower input box, ``solve(termination, seed, scale)``
    (`RRTCoLearn.solve`'s ``control_scale``), where held inputs cost less. The scale halves
    (down to ``narrowest``) after a solve that found a cheaper path and doubles (up to 1)
    after one at a scale below 1 that did not; such a solve gets at most the budget spent
    so far (CPU, wall time, iterations: whichever the budget has), so a box too narrow to
    reach the goal costs at most as much as all before it. The first solve is the plain
    one (scale 1), and so is every solve at scale 1.

    ``first(plan, stop)`` (e.g. `planning.improve.multiple_shooting`) runs before
    ``improve`` on each solved path cheaper than every path before it (so never twice on
    one path), with an allowance of its own: the CPU (iterations) of all solves so far
    times (its gains + 1) / (its tries + 1); ``improve``'s allowance and record do not
    count it.
    ``extra["anytime"]["first"]`` has its tries and gains.

    ``solves``: stop after that many solves (each with its improvements) even with budget
    left; ``solves=1`` is one improvement round on the first solution (``plan.polish``:
    `first` then `improve` once each; docs/anytime.md). ``allowance`` scales both
    allowances (1: each up to what the solves took; by default `ALLOWANCE`). ``in_steps``:
    the allowances in improvement steps (``allowance`` x the solves' iterations) under any
    budget, so that the improvements do not depend on the machine's speed (under a time
    budget the solves still do where the budget runs out).

    A ``solve`` that takes ``query`` (`RRTCoLearn.solve`) is told the query's seed in every
    solve after the first: its goal funnel is drawn from that seed's stream and built once
    for all the query's solves (`planning.funnel.FunnelStream`; docs/anytime.md, "One
    funnel per query"); the first solve, not told, begins the run (the search through the
    start that ``improve`` may keep from solve to solve starts afresh), so a second run of
    the seed on the same planner is the first again.

    ``accept(plan)``: whether a solved plan may be the best (`pipeline.plan`: its step
    resolves it, `evaluate.step_check`). An accepted plan beats every plan not accepted,
    the cheaper of two alike; asked only of a plan that would otherwise become the best.
    ``extra["anytime"]["not_accepted"]`` counts the plans it turned down (``progress`` then
    records the best's cost each time it changes, which may rise once from an unaccepted
    plan to an accepted one)."""
    if solves is None and termination.time_limit is None and \
            termination.max_iterations is None and termination.cpu_time_limit is None:
        raise ValueError("an anytime plan needs a budget: a time, CPU time or iteration limit")
    if solves is not None and solves < 1:
        raise ValueError(f"solves must be at least 1, not {solves}")
    # the solves after the first are told the query's seed; the first, without it, begins
    # the query's run (`RRTCoLearn.solve`)
    later = partial(solve, query=seed) if _takes_query(solve) else solve
    termination.start()
    cpu0 = time.process_time()
    children = np.random.SeedSequence(seed)
    best: Plan | None = None
    progress: list[list[float]] = []
    runs, iterations, cpu, wall = 0, 0, 0.0, 0.0
    # improvements run, and those that made their path cheaper: ``improve``'s, ``first``'s
    record_, first_record = [0, 0], [0, 0]
    solves_cpu, solves_its = 0.0, 0  # what all solves so far took
    scale, scales = 1.0, []  # the random controls' input box (1: the whole box)
    cheapest_solve = np.inf  # the cheapest path a solve found (before any improvement)
    best_ok, turned_down = False, 0  # whether ``accept`` took the best; plans it did not

    def better(q: Plan) -> bool:
        """Whether the solved ``q`` replaces the best (``accept``'s verdict kept for it)."""
        nonlocal best_ok, turned_down
        if best is not None and best.solved and best_ok and q.path_cost >= best.path_cost:
            return False  # (without ``accept`` every plan is accepted)
        ok = True if accept is None else bool(accept(q))
        turned_down += not ok
        if best is None or not best.solved or ok > best_ok or \
                (ok == best_ok and q.path_cost < best.path_cost):
            best_ok = ok
            return True
        return False
    while (solves is None or runs < solves) and \
            (left := _remaining(termination, iterations, cpu0)) is not None:
        child = seed if runs == 0 else int(children.spawn(1)[0].generate_state(1)[0])
        scales.append(scale)
        run_solve = solve if runs == 0 else later
        p = run_solve(left, child) if scale == 1.0 else \
            run_solve(_at_most_spent(left, termination, iterations, cpu0), child, scale)
        if narrowest < 1.0:
            if p.solved and p.path_cost < cheapest_solve:
                scale = max(narrowest, 0.5 * scale)
            elif scale < 1.0:
                scale = min(1.0, 2.0 * scale)
        runs += 1
        if p.solved:
            cheapest_solve = min(cheapest_solve, p.path_cost)
        iterations += max(1, p.iterations)
        cpu += p.planning_cpu_s
        solves_cpu += p.planning_cpu_s
        solves_its += max(1, p.iterations)
        wall += p.planning_time_s
        best_before = best.path_cost if best is not None and best.solved else np.inf
        if p.solved and better(p):
            best = p
            progress.append([round(cpu, 6), p.path_cost])
        elif best is None:
            best = p
        if not p.solved and runs == 1:
            break  # the budget did not even give a first solution
        # ``first`` on a path cheaper than every earlier one, then ``improve``, each within
        # at most what the solve took, times (gains + 1) / (tries + 1) of its own earlier
        # runs (1 at first): where improving pays it gets as much as growing trees, where
        # it fails ever less
        new_best = p.path_cost < best_before
        for step, record, run in ((first, first_record, new_best), (improve, record_, True)):
            if not (p.solved and step is not None and run):
                continue
            before, unchanged = p.path_cost, p
            p, its, c, t = _improved(step, p,
                                     allowance * (record[1] + 1) / (record[0] + 1),
                                     termination, iterations, cpu0,
                                     (solves_cpu, solves_its) if step is first else None,
                                     in_steps)
            iterations, cpu, wall = iterations + its, cpu + c, wall + t
            record[0] += 1
            record[1] += p.path_cost < before
            if p is not unchanged and better(p):
                best = p
                progress.append([round(cpu, 6), p.path_cost])
    # a function's name, or a functools.partial's function's
    name = getattr(improve, "__name__", None) or getattr(getattr(improve, "func", None),
                                                         "__name__", "improve")
    scheme = "restarts" if improve is None else f"restarts+{name}"
    best.extra["anytime"] = {"scheme": scheme, "solves": runs, "progress": progress,
                             **({"control_scales": scales} if narrowest < 1.0 else {}),
                             **({"first": {"tries": first_record[0], "gains": first_record[1]}}
                                if first is not None else {}),
                             **({"not_accepted": turned_down} if accept is not None else {}),
                             "iterations": iterations, "planning_cpu_s": round(cpu, 6),
                             "first_solution_cpu_s": progress[0][0] if progress else None,
                             "first_solution_cost": progress[0][1] if progress else None}
    best.planning_cpu_s, best.planning_time_s = cpu, wall
    return best

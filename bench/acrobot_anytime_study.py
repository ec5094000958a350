"""Where the anytime scheme's budget goes on one problem of bench/ablation.py, and why
multiple shooting does not relax its paths (docs/anytime.md, "The shipped acrobot's anytime
paths").

``breakdown``: bench/ablation.py's anytime plan (`ablation.anytime_plan`: restarts, multiple
shooting of each new best path, goal and interior shortcuts) with every step timed: each
solve's CPU, cost, duration and edges (kind: duration / cost), each multiple-shooting try's
record, each goal walk's and interior search's record, CPU and cost after it.

``ms``: `planning.improve.multiple_shooting` alone on first solutions, with the segments,
the initial costates and the solver varied (study variants, not shipped):
- ``--lengths``: the longest segment (s) instead of the data's longest extremal
  (``max_duration``); 0 makes every path node a segment start;
- ``--costates zero``: every segment's initial costate 0 instead of its first edge's (or U's);
- ``--solver fixed``: the conditions but H* = 0 solved first with the path's durations fixed,
  then the free-time solve from there. (A Newton homotopy from the path, r(v) =
  (1 - s) r(v_path) for s from 0 to 1, ran at 16413b0 with ``--solver homotopy``: it needs a
  residual shift in `shooting._ms_newton` that was not kept; docs/anytime.md.)

``funnel``: a goal funnel of ``--funnel`` extremals (its own generator, seeded by the seed)
and, from every node of a first solution's path, the funnel connection's tail
(`connections.FunnelConnection`: continuation from each of the nearest funnel states within
``--radius`` times ``funnel_radius``, then the edge checked as the planner checks it); the
cheapest path so found (cost to come + tail), and the CPU of the build and the walk.

``landed``: `planning.improve.landed_shortcuts` alone on first solutions, and after the goal
walk and the interior shortcuts (`shortcut` as the anytime scheme runs it, without its
allowance): cost over the optimum and thread CPU of each.

    PYTHONPATH=src python bench/acrobot_anytime_study.py breakdown --seeds 0,1,2
    PYTHONPATH=src python bench/acrobot_anytime_study.py ms --seeds 0-4 --lengths 6.69,0.5,0
        [--costates zero] [--solver fixed] [--problem acrobot] [--models DIR]
    PYTHONPATH=src python bench/acrobot_anytime_study.py funnel --seeds 0-4 --radius 3
    PYTHONPATH=src python bench/acrobot_anytime_study.py landed --seeds 0-7
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ablation as ab


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = (int(v) for v in text.split("-"))
        return list(range(a, b + 1))
    return [int(v) for v in text.split(",")]


def _edges(p) -> str:
    """The path's edges as kind:duration/cost (kind's first two letters; le = learned)."""
    t, path = p.tree, p.path_nodes
    return " ".join(f"{t.made_by.get(k, 'learned')[:2]}:{t.durations[k]:.2f}/{t.costs[k]:.1f}"
                    for k in path[1:])


def _first_solution(planner, seed: int, limit: float):
    """The planner's first solution for ``seed`` within ``limit`` CPU seconds."""
    from rrtcolearn.planning.termination import TerminationCondition

    return planner.solve(TerminationCondition(None, None, limit), seed)


def _first_solutions(planner, seeds: list[int], limit: float, unsolved=None):
    """(seed, first solution) of each seed whose solve within ``limit`` CPU s solved; a seed
    that did not is announced by ``unsolved(seed)`` when given, else passed over."""
    for seed in seeds:
        p = _first_solution(planner, seed, limit)
        if p.solved:
            yield seed, p
        elif unsolved is not None:
            unsolved(seed)


def breakdown(planner, seeds: list[int], budget: float, opt: float) -> None:
    from rrtcolearn.anytime import solve_with_restarts
    from rrtcolearn.planning import improve as imp
    from rrtcolearn.planning.termination import TerminationCondition

    log: list[str] = []
    for seed in seeds:
        log.clear()

        def solve(term, child, *a):
            c0 = time.process_time()
            p = planner.solve(term, child, *a)
            cpu = time.process_time() - c0
            log.append(f"solve {cpu:.2f} s: " + (f"{p.path_cost:.1f} T {p.path_duration:.2f} "
                                                  f"[{_edges(p)}]" if p.solved else "unsolved"))
            return p

        def first(p, stop):
            c0 = time.thread_time()
            q = imp.multiple_shooting(planner, p, stop)
            log.append(f"  multiple shooting {time.thread_time() - c0:.2f} s: "
                       f"{q.extra['multiple_shooting']} -> {q.path_cost:.1f}")
            return q

        def improve(p, stop):
            c0 = time.thread_time()
            q = imp.goal_shortcuts(planner, p, stop)
            c1 = time.thread_time()
            r = imp.interior_shortcuts(planner, q, stop)
            log.append(f"  goal walk {c1 - c0:.2f} s: {q.extra.get('shortcuts')} -> "
                       f"{q.path_cost:.1f}; interior {time.thread_time() - c1:.2f} s: "
                       f"{r.extra.get('interior')} -> {r.path_cost:.1f}")
            return r

        p = solve_with_restarts(solve, TerminationCondition(None, None, budget), seed,
                                improve=improve, narrowest=planner.narrowest_control_scale(),
                                first=first)
        print(f"== seed {seed}: best {p.path_cost:.2f} ({p.path_cost / opt:.2f}x the optimum), "
              f"{p.extra['anytime']['solves']} solves, T {p.path_duration:.2f}")
        print("\n".join(f"   {row}" for row in log))
        print(f"   best: [{_edges(p)}]", flush=True)


def _fixed_first(info: dict, system, x0, costates, states, durations, terminal, *,
                 time_weight, dt, max_duration, tolerance=1e-6, grid_tolerance=1e-8,
                 max_iterations=30, stop=None):
    """`shooting.multiple_shoot` after a solve with the path's durations fixed."""
    from rrtcolearn.planning.shooting import _ms_newton, multiple_shoot

    x0 = np.asarray(x0, dtype=float)
    lams = np.asarray(costates, dtype=float)
    xs = np.asarray(states, dtype=float).reshape(len(lams) - 1, len(x0))
    fixed = _ms_newton(system, x0, lams, xs, np.asarray(durations, dtype=float), terminal,
                       False, float(time_weight), dt, max_duration, tolerance, max_iterations,
                       stop)
    info["fixed"] = fixed is not None
    if fixed is None:
        return None
    return multiple_shoot(system, x0, fixed[0], fixed[1], durations, terminal,
                          time_weight=time_weight, dt=dt, max_duration=max_duration,
                          tolerance=tolerance, grid_tolerance=grid_tolerance,
                          max_iterations=max_iterations, stop=stop)


def ms(planner, seeds: list[int], lengths: list[float], costates: str, solver: str,
       limit: float, opt: float) -> None:
    from rrtcolearn.planning import improve as imp
    from rrtcolearn.planning import shooting

    info: dict = {}
    inner = {"plain": shooting.multiple_shoot, "fixed": partial(_fixed_first, info)}[solver]

    def patched(system, x0, lams, *a, **k):
        return inner(system, x0, lams * 0.0 if costates == "zero" else lams, *a, **k)

    s0 = planner.settings
    print("| seed | first / opt | T | longest segment | segments | converged | kept (why not) "
          "| after / opt | CPU (s) | study |\n|---|---|---|---|---|---|---|---|---|---|")
    imp.multiple_shoot = patched
    try:
        for seed, p in _first_solutions(
                planner, seeds, limit,
                unsolved=lambda seed: print(f"| {seed} | unsolved |" + " |" * 8)):
            for length in lengths:
                planner.settings = replace(s0, max_duration=length if length > 0 else 1e-9)
                info.clear()
                c0 = time.thread_time()
                try:
                    q = imp.multiple_shooting(planner, p)
                finally:
                    planner.settings = s0
                r = q.extra["multiple_shooting"]
                study = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                  for k, v in info.items())
                print(f"| {seed} | {p.path_cost / opt:.2f} | {p.path_duration:.2f} | "
                      f"{length:g} | {r['segments']} | {r['converged']} | {r['kept']}"
                      f"{'' if r['kept'] else ' (' + str(r['why']) + ')'} | "
                      f"{q.path_cost / opt:.2f} | {time.thread_time() - c0:.2f} | {study} |",
                      flush=True)
    finally:
        imp.multiple_shoot = shooting.multiple_shoot


def funnel_walk(planner, seeds: list[int], size: int, radius: float, limit: float,
                opt: float) -> None:
    from rrtcolearn.planning.connections import (
        FUNNEL_POINTS,
        FUNNEL_STRETCH,
        FunnelConnection,
        shoot_edge,
    )

    prop, s = planner.propagator, planner.settings
    prob, system = planner.problem, planner.problem.system
    n = system.n_states
    lam, z0 = np.empty(n), np.empty(2 * n + 1)
    longest = FUNNEL_STRETCH * s.funnel_duration
    print("| seed | first / opt | build (s) | walk (s) | nodes with a funnel state near | "
          "tails (from path position: costs) | best / opt |\n|---|---|---|---|---|---|---|")
    for seed, p in _first_solutions(planner, seeds, limit):
        c0 = time.process_time()
        conn = FunnelConnection.build(prop, np.random.default_rng(seed),
                                      np.asarray(s.metric_scale, dtype=float), size)
        c1 = time.process_time()
        tree, path = p.tree, p.path_nodes
        come = np.concatenate([[0.0], np.cumsum(tree.costs[path[1:]])])
        offsets = prob.goal_offset(tree.states[path])
        dist, index = conn.nearest(offsets, radius * s.funnel_radius)
        found, best = {}, come[-1]
        for pos in range(len(path) - 1):
            x0 = tree.states[path[pos]]
            for q in range(FUNNEL_POINTS):
                if not np.isfinite(dist[pos, q]):
                    break
                guess = conn.steer(offsets[pos], int(index[pos, q]), longest)
                if guess is None:
                    continue
                params = system.params_from_costate(x0[None], guess[0][None])[0]
                edge = prop.goal_extremal(
                    x0, np.append(params, max(1, round(guess[1] / s.dt)) * s.dt), lam, z0) \
                    or shoot_edge(prop, x0, params, guess[1], longest, lam, z0)
                if edge is not None:
                    found.setdefault(pos, []).append(round(edge.cost, 1))
                    best = min(best, come[pos] + edge.cost)
        near = int(np.isfinite(dist[:-1, 0]).sum())
        print(f"| {seed} | {come[-1] / opt:.2f} | {c1 - c0:.2f} | {time.process_time() - c1:.2f} "
              f"| {near} of {len(path) - 1} | {found} | {best / opt:.2f} |", flush=True)


def landed(planner, seeds: list[int], limit: float, opt: float) -> None:
    from rrtcolearn.planning import improve as imp

    print("| seed | first / opt | landed alone (CPU s) | its record | goal walk + interior "
          "(CPU s) | + landed (CPU s) |\n|---|---|---|---|---|---|")
    for seed, p in _first_solutions(planner, seeds, limit):
        first = p.path_cost
        c0 = time.thread_time()
        a = imp.landed_shortcuts(planner, p)
        c1 = time.thread_time()
        q = _first_solution(planner, seed, limit)  # a fresh tree
        c2 = time.thread_time()
        q = imp.interior_shortcuts(planner, imp.goal_shortcuts(planner, q))
        c3 = time.thread_time()
        r = imp.landed_shortcuts(planner, q)
        c4 = time.thread_time()
        print(f"| {seed} | {first / opt:.2f} | {a.path_cost / opt:.2f} ({c1 - c0:.2f}) | "
              f"{a.extra['landed']} | {q.path_cost / opt:.2f} ({c3 - c2:.2f}) | "
              f"{r.path_cost / opt:.2f} ({c4 - c3:.2f}) |", flush=True)


def main(argv: list[str] | None = None) -> None:
    from rrtcolearn.planning.termination import TerminationCondition

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("breakdown", "ms", "funnel", "landed"))
    ap.add_argument("--problem", default="acrobot", choices=sorted(ab.PROBLEMS))
    ap.add_argument("--models", type=Path, default=Path("/tmp/rrtcolearn_ablation_models"))
    ap.add_argument("--seeds", default="0-2")
    ap.add_argument("--anytime", type=float, default=10.0, help="process CPU s per seed")
    ap.add_argument("--limit", type=float, default=30.0, help="a first solution's CPU s")
    ap.add_argument("--lengths", default="0", help="longest segments (s); 0: every node")
    ap.add_argument("--costates", choices=("path", "zero"), default="path")
    ap.add_argument("--solver", choices=("plain", "fixed"), default="plain")
    ap.add_argument("--funnel", type=int, default=20_000, help="the funnel's extremals")
    ap.add_argument("--radius", type=float, default=1.0, help="times plan.funnel_radius")
    args = ap.parse_args(argv)
    problem = ab.PROBLEMS[args.problem]
    case, model, _ = ab.model_for(problem, args.models)
    planning = ab.planning_problem(args.problem, problem, case, model)
    opt = ab.optimum(problem, planning, model)["value"]
    planner = ab.make_planner(planning, model, "default")
    planner.solve(TerminationCondition(None, 50), 10_000)  # kernels loaded, as ablation.run
    if args.what == "breakdown":
        breakdown(planner, _seeds(args.seeds), args.anytime, opt)
    elif args.what == "landed":
        landed(planner, _seeds(args.seeds), args.limit, opt)
    elif args.what == "funnel":
        funnel_walk(planner, _seeds(args.seeds), args.funnel, args.radius, args.limit, opt)
    else:
        ms(planner, _seeds(args.seeds), [float(v) for v in args.lengths.split(",")],
           args.costates, args.solver, args.limit, opt)


if __name__ == "__main__":
    main()

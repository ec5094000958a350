"""Reference optima (direct collocation, `rrtcolearn.baselines.collocation`) of the standard
queries: the pendulum swing-up, sparse_rrt's cart-pole and acrobot (examples/), the shipped
cart-pole and acrobot swing-ups (unbounded and at the README's input limits).

Each problem is the query a planner gets (`pipeline.make_problem` with the system's
recommended configuration: start, goal, tolerance, wrap_goal, state constraints = the
system's box in the non-angle coordinates, input limits); w = 1.

    python bench/collocation.py [--problems NAME,...] [--n-intervals N] [--durations 2,4,8]
                                [--search-intervals M] [--refine-best K]
                                [--turns -1,0,1] [--json FILE] [--path-file NPZ]

Prints one line per problem (cost, T, N, guesses, CPU, re-simulation errors) and, with
--json, writes every result's summary and attempts.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # examples/


def acrobot_task_distance(x):
    """CasADi twin of examples.sparse_rrt_acrobot.task_goal_distance (end effector, L = 20)."""
    import casadi as ca
    from examples.sparse_rrt_acrobot import GOAL, LINK_LENGTH_TASK, end_effector

    gx, gy = (float(v) for v in end_effector(GOAL[0], GOAL[1]))
    t1 = x[0] - math.pi / 2
    t2 = x[1]
    ex = LINK_LENGTH_TASK * (ca.cos(t1) + ca.cos(t1 + t2))
    ey = LINK_LENGTH_TASK * (ca.sin(t1) + ca.sin(t1 + t2))
    # + 1e-12: differentiable at distance 0 too (a guess may end at the goal's point); it
    # moves the boundary at distance 2 by 2.5e-13
    return ca.sqrt((ex - gx) ** 2 + (ey - gy) ** 2 + 1e-12)


def _problem(system, u_max=None):
    """The system's standard query as `pipeline.make_problem` makes it under the system's
    recommended configuration (the registry's, or its defaults' "config")."""
    from rrtcolearn import pipeline
    from rrtcolearn.config import validate
    from rrtcolearn.systems import list_systems, recommended_config

    cfg = validate(recommended_config(system.name) if system.name in list_systems()
                   else system.defaults.get("config", {}))
    d = system.defaults
    return pipeline.make_problem(system, cfg, d["start"], d["goal"], cfg.plan.goal_tolerance,
                                 u_max=u_max)


def problems():
    """name -> (problem factory, goal_distance, default durations)."""
    from examples.sparse_rrt_acrobot import make_acrobot as sparse_acrobot
    from examples.sparse_rrt_cartpole import make_cartpole as sparse_cartpole

    from rrtcolearn.systems import make

    return {
        "sparse-cartpole": (lambda: _problem(sparse_cartpole()), None, (2, 5, 10, 20, 40, 80)),
        "sparse-acrobot": (lambda: _problem(sparse_acrobot()), acrobot_task_distance,
                           (2, 4, 8, 16, 32)),
        "cartpole": (lambda: _problem(make("cartpole")), None, (1, 2, 4, 8, 16)),
        "cartpole-u219.9": (lambda: _problem(make("cartpole"), 219.9), None,
                            (1, 2, 4, 8, 16)),
        "cartpole-u109.9": (lambda: _problem(make("cartpole"), 109.9), None,
                            (1, 2, 4, 8, 16)),
        "acrobot": (lambda: _problem(make("acrobot")), None, (1, 2, 4, 8, 16)),
        "acrobot-u25.2": (lambda: _problem(make("acrobot"), 25.2), None, (1, 2, 4, 8, 16)),
        "acrobot-u12.6": (lambda: _problem(make("acrobot"), 12.6), None, (1, 2, 4, 8, 16)),
    }


def _options(args, durations) -> dict:
    kwargs = {"durations": durations, "turns": [int(k) for k in args.turns.split(",")]}
    if args.n_intervals:
        kwargs["n_intervals"] = args.n_intervals
    if args.search_intervals:
        kwargs["search_intervals"] = args.search_intervals
        kwargs["refine_best"] = args.refine_best
    if args.t_max:
        kwargs["t_max"] = args.t_max
    return kwargs


def main(argv=None) -> None:
    from rrtcolearn.baselines.collocation import problem_optimum

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", default=",".join(problems()))
    ap.add_argument("--n-intervals", type=int, default=None)
    ap.add_argument("--search-intervals", type=int, default=None)
    ap.add_argument("--refine-best", type=int, default=2)
    ap.add_argument("--durations", default=None)
    ap.add_argument("--turns", default="0")
    ap.add_argument("--t-max", type=float, default=None)
    ap.add_argument("--path-from", default=None,
                    help="solve this problem first (same settings) and add its solution as "
                         "the path guess of every problem (e.g. a tighter input bound's)")
    ap.add_argument("--path-file", default=None,
                    help="a path guess for every problem: an npz of t, state, input (a "
                         "planner's path, e.g. bench/anytime_systems.py --path-out)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    table = problems()
    out = {}
    seed = None
    if args.path_from:
        make_problem, goal_distance, durations = table[args.path_from]
        if args.durations:
            durations = [float(v) for v in args.durations.split(",")]
        seed = problem_optimum(make_problem(), goal_distance=goal_distance,
                               **_options(args, durations))
        print(f"path guess: {args.path_from}, cost {seed.cost:.6g}, T {seed.duration:.4g} s, "
              f"N {seed.n_intervals}, {seed.status}", flush=True)
    if args.path_file:
        with np.load(args.path_file) as f:
            seed = (f["t"], f["state"], f["input"][:-1])
        print(f"path guess: {args.path_file}, T {float(seed[0][-1]):.4g} s", flush=True)
    for name in args.problems.split(","):
        make_problem, goal_distance, durations = table[name]
        if args.durations:
            durations = [float(v) for v in args.durations.split(",")]
        kwargs = _options(args, durations)
        if seed is not None:
            kwargs["path"] = seed
        problem = make_problem()
        res = problem_optimum(problem, goal_distance=goal_distance, **kwargs)
        s = res.summary()
        converged = sum(a["success"] for a in res.attempts)
        print(f"{name}: cost {s['cost']:.6g}, T {s['duration']:.4g} s, N {s['n_intervals']}, "
              f"{converged}/{s['guesses']} converged, best from '{s['guess']}', "
              f"CPU {s['cpu_s']:.1f} s, status {s['status']}, max |u| "
              f"{np.abs(res.controls).max():.4g}; re-simulation: interval error "
              f"{s['interval_error']:.2g}, open-loop end error {s['resim_error']:.2g} "
              f"(held 0.01 s: {s['held_error']:.2g}), goal distance "
              f"{s['resim_goal_distance']:.3g} (tolerance {problem.goal_tolerance:g}), "
              f"exact cost {s['resim_cost']:.6g}", flush=True)
        out[name] = s | {"attempts": res.attempts, "max_abs_u": float(np.abs(res.controls).max())}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()

"""Anytime schemes on a fitted run's standard query: plain restarts, restarts with goal
shortcuts only (`planning.improve.goal_shortcuts`) and restarts with interior and goal
shortcuts (`planning.improve.shortcut`, what ``plan.anytime`` runs), at equal CPU, seed by
seed.

    python bench/anytime_systems.py RUN_DIR [--budget 10] [--queries 10] [--optimum C]
                                    [--path-out FILE] [--schemes restarts,goal,shortcut]
                                    [--dynobench PROBLEM]

RUN_DIR is a `rrtcolearn run` directory (e.g. of examples.sparse_rrt_cartpole:make_cartpole;
run from the repository root so that ``examples`` imports). The query is the system's
default (start, goal, the config's tolerance), or with ``--dynobench`` that problem of
dynobench's (`rrtcolearn.dynobench`, tolerance 0.1, the exact body; RUN_DIR that robot's
run): its paths' durations are printed beside the reference solution's. ``--optimum`` is
the collocation optimum of that query (docs/collocation.md), for the ratios and the share
of the gap closed. ``--path-out`` writes the cheapest path found (re-simulated: ``t``,
``state``, ``input``; npz) for `bench/collocation.py --path-file`, the collocation started
from the planner's path. Prints one line per query and scheme (first cost, final cost,
solves, final duration, the final path's share of duration by edge kind, the interior
shortcuts' record), then one JSON line of medians (and mean shares by kind). ``--once``:
no restarts, each first solution improved once by each scheme's improvement.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from functools import partial

import numpy as np

from rrtcolearn import pipeline
from rrtcolearn.anytime import solve_with_restarts
from rrtcolearn.evaluate import sample_path
from rrtcolearn.planning.improve import goal_shortcuts, shortcut
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--budget", type=float, default=10.0, help="CPU seconds per query")
    ap.add_argument("--queries", type=int, default=10)
    ap.add_argument("--optimum", type=float, default=None)
    ap.add_argument("--path-out", default=None, help="npz of the cheapest path found")
    ap.add_argument("--dynobench", default=None, help="a dynobench problem, e.g. "
                    "unicycle1_v0/parallelpark_0, instead of the system's default query")
    ap.add_argument("--once", action="store_true", help="no restarts: each query's first "
                    "solution improved once by each scheme's improvement (process CPU)")
    ap.add_argument("--schemes", default="restarts,goal,shortcut",
                    help="comma-separated: restarts, goal (goal shortcuts only), shortcut")
    args = ap.parse_args(argv)
    m = pipeline.load_model(args.run_dir)
    d = m.system.defaults
    if args.dynobench:
        from rrtcolearn import dynobench as db

        read = db.read_problem(args.dynobench)
        problem = db.planning_problem(read, m.system, 0.1)
        print("dynobench references (duration, s):", db.references(read), flush=True)
    else:
        problem = pipeline.make_problem(m.system, m.config, d["start"], d["goal"],
                                        m.config.plan.goal_tolerance)
    planner = RRTCoLearn(problem, m.functions, m.planner_settings())
    every = {"restarts": None, "restarts+goal_shortcuts": partial(goal_shortcuts, planner),
             "restarts+shortcut": partial(shortcut, planner)}
    chosen = {"restarts": "restarts", "goal": "restarts+goal_shortcuts",
              "shortcut": "restarts+shortcut"}
    schemes = {chosen[k]: every[chosen[k]] for k in args.schemes.split(",")}
    if args.once:
        return improve_once(planner, schemes, args)
    rows: dict[str, list[tuple[float, float, int]]] = {k: [] for k in schemes}
    shares: dict[str, list[dict]] = {k: [] for k in schemes}
    cheapest = None
    for seed in range(args.queries):
        for name, improve in schemes.items():
            p = solve_with_restarts(planner.solve, TerminationCondition(None, None, args.budget),
                                    seed, improve=improve)
            a = p.extra["anytime"]
            by = {k: round(v, 3) for k, v in p.duration_by.items()} if p.solved else {}
            print(name, seed, a["first_solution_cost"], p.path_cost if p.solved else None,
                  a["solves"], round(p.path_duration, 3), by, p.extra.get("interior"),
                  flush=True)
            if a["first_solution_cost"] is not None:
                rows[name].append((a["first_solution_cost"], p.path_cost, a["solves"]))
                shares[name].append(by)
                if cheapest is None or p.path_cost < cheapest.path_cost:
                    cheapest = p
    out = {}
    for name, r in rows.items():
        first = statistics.median(x[0] for x in r)
        best = statistics.median(x[1] for x in r)
        row = {"solved": f"{len(r)}/{args.queries}", "first_cost_median": round(first, 4),
               "best_cost_median": round(best, 4),
               "best_over_first_median": round(statistics.median(x[1] / x[0] for x in r), 4),
               "solves_median": statistics.median(x[2] for x in r)}
        kinds = sorted({k for by in shares[name] for k in by})
        row["duration_share_mean"] = {k: round(statistics.mean(by.get(k, 0.0)
                                                               for by in shares[name]), 3)
                                      for k in kinds}
        if args.optimum:
            row["best_over_optimum"] = round(best / args.optimum, 4)
            row["gap_closed"] = round((first - best) / (first - args.optimum), 4)
        out[name] = row
        print(f"{name}: " + " ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    if args.path_out and cheapest is not None:
        sp = sample_path(m.system, cheapest)
        np.savez(args.path_out, t=sp["t"], state=sp["state"], input=sp["input"],
                 cost=cheapest.path_cost)
        print(f"cheapest path ({cheapest.path_cost:.6g}) -> {args.path_out}")
    print(json.dumps(out))
    return out


def improve_once(planner: RRTCoLearn, schemes: dict, args: argparse.Namespace) -> dict:
    """``--once``: per query the first solution (``--budget`` CPU seconds at most), then for
    each scheme with an improvement a fresh solve of the same seed improved once, without
    an allowance; the costs, the improvement's process CPU and the duration shares."""
    rows: dict[str, list[tuple[float, float, float]]] = {k: [] for k in schemes if schemes[k]}
    for seed in range(args.queries):
        for name, improve in schemes.items():
            if improve is None:
                continue
            p = planner.solve(TerminationCondition(None, None, args.budget), seed)
            if not p.solved:
                print(name, seed, "unsolved", flush=True)
                continue
            first, cpu = p.path_cost, time.process_time()
            q = improve(p)
            cpu = time.process_time() - cpu
            by = {k: round(v, 3) for k, v in q.duration_by.items()}
            print(name, seed, round(p.planning_cpu_s, 3), first, q.path_cost, round(cpu, 3),
                  by, q.extra.get("interior"), flush=True)
            rows[name].append((first, q.path_cost, cpu))
    out = {}
    for name, r in rows.items():
        if not r:
            continue
        row = {"solved": f"{len(r)}/{args.queries}",
               "first_cost_median": round(statistics.median(x[0] for x in r), 4),
               "improved_cost_median": round(statistics.median(x[1] for x in r), 4),
               "improve_cpu_median": round(statistics.median(x[2] for x in r), 4)}
        if args.optimum:
            row["improved_over_optimum"] = round(row["improved_cost_median"] / args.optimum, 4)
        out[name] = row
        print(f"{name}: " + " ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()

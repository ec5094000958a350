"""Time to a first solution of a saved model's own query: planning CPU per seed.

Plans the query a run directory's model was made for (its configured or the system's default
start, goal, tolerance and goal region; goal connections as configured) once per seed and
prints one JSON line per seed (status, nodes, iterations, planning CPU, the path's last
nodes) and then the median and total CPU. Run it with another checkout's code on
``PYTHONPATH`` to compare commits on the same trees. Usage: python bench/first_solution.py
--model RUN_DIR [--seeds 0-19] [--time-limit 60]
"""
from __future__ import annotations

import argparse
import json
import statistics

from rrtcolearn import pipeline


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, metavar="RUN_DIR")
    ap.add_argument("--seeds", default="0-19", help="first-last")
    ap.add_argument("--time-limit", type=float, default=60.0)
    args = ap.parse_args(argv)
    first, _, last = args.seeds.partition("-")
    seeds = range(int(first), int(last or first) + 1)
    model = pipeline.load_model(args.model)
    start, goal = pipeline.query_states(model.config, model.system)
    tol = model.config.plan.goal_tolerance
    rows = []
    for seed in seeds:
        p = pipeline.plan(model, start, goal, tol, seed, time_limit=args.time_limit)
        rows.append({"seed": seed, "status": p.status, "nodes": int(p.tree.n_nodes),
                     "iterations": int(p.iterations), "cpu_s": round(p.planning_cpu_s, 4),
                     "path_end": p.path_nodes[-3:]})
        print(json.dumps(rows[-1]), flush=True)
    cpu = [r["cpu_s"] for r in rows]
    out = {"solved": sum(r["status"] == "exact" for r in rows), "queries": len(rows),
           "median_cpu_s": round(statistics.median(cpu), 4), "total_cpu_s": round(sum(cpu), 3)}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()

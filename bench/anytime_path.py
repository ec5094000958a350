"""Re-run bench/ablation.py's default-mode anytime plan (same model, query, seed and budget)
for some seeds of one problem, and write the cheapest path, re-simulated (npz of ``t``,
``state``, ``input``, ``cost``), for `bench/collocation.py --path-file`: the collocation
started from the planner's best path (docs/collocation.md).

    PYTHONPATH=src:. python bench/anytime_path.py PROBLEM SEEDS OUT.npz [--models DIR]
        [--anytime 10]

PROBLEM is a key of bench/ablation.py's PROBLEMS, SEEDS comma-separated (e.g. the cheapest
seeds of a results file). The plan is `ablation.anytime`'s, so its costs are the results
file's where the budget was not the binding limit of a restart (they were, seed for seed,
for the a683e65 run's cheapest seeds).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ablation


def main(argv: list[str] | None = None) -> float:
    """Plan the seeds, save the cheapest solved path; returns its cost."""
    from rrtcolearn.evaluate import sample_path
    from rrtcolearn.planning.termination import TerminationCondition

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("problem", choices=sorted(ablation.PROBLEMS))
    ap.add_argument("seeds")
    ap.add_argument("out")
    ap.add_argument("--models", type=Path, default=Path("/tmp/rrtcolearn_ablation_models"))
    ap.add_argument("--anytime", type=float, default=10.0, help="process CPU s per seed")
    args = ap.parse_args(argv)
    problem = ablation.PROBLEMS[args.problem]
    case, model, _ = ablation.model_for(problem, args.models)
    planning = ablation.planning_problem(args.problem, problem, case, model)
    planner = ablation.make_planner(planning, model, "default")
    planner.solve(TerminationCondition(None, 50), 10_000)  # as ablation.run does
    best = None
    for seed in (int(s) for s in args.seeds.split(",")):
        p = ablation.anytime_plan(planner, seed, args.anytime)
        print(args.problem, seed, "cost", p.path_cost if p.solved else None,
              "T", p.path_duration, flush=True)
        if p.solved and (best is None or p.path_cost < best.path_cost):
            best = p
    if best is None:
        raise SystemExit("no seed solved")
    sp = sample_path(model.system, best)
    np.savez(args.out, t=sp["t"], state=sp["state"], input=sp["input"], cost=best.path_cost)
    print(f"cheapest path ({best.path_cost:.6g}, T {best.path_duration:.4g} s) -> {args.out}")
    return float(best.path_cost)


if __name__ == "__main__":
    main()

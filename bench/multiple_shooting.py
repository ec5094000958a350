"""Indirect multiple shooting (`planning.improve.multiple_shooting`) on its own, on first
solutions: per problem of bench/ablation.py (its small k-NN models and optima) and seed, the
default planner's first solution within ``--limit`` s of process CPU, then the
multiple-shooting step on it alone (no allowance), and after the goal walk
(`goal_shortcuts`): segments, whether it converged and was kept, cost over the optimum,
thread CPU of the step.

    PYTHONPATH=src python bench/multiple_shooting.py --models DIR [--seeds 3]
        [--problems a,b] [--limit 30]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import ablation as ab  # bench/ on the path first


def main(argv: list[str] | None = None) -> None:
    from rrtcolearn.planning.improve import goal_shortcuts, multiple_shooting
    from rrtcolearn.planning.termination import TerminationCondition

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("/tmp/rrtcolearn_ablation_models"))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--limit", type=float, default=30.0)
    ap.add_argument("--problems", default="pendulum_u1,quadrotor,sparse_rrt_acrobot,"
                    "sparse_rrt_cartpole,kink,cartpole,acrobot")
    args = ap.parse_args(argv)
    print("| problem | seed | on | first / opt | segments | converged | kept | after / opt "
          "| CPU (s) |\n|---|---:|---|---:|---:|---|---|---:|---:|")
    for name in args.problems.split(","):
        problem = ab.PROBLEMS[name]
        case, model, _ = ab.model_for(problem, args.models)
        planning = ab.planning_problem(name, problem, case, model)
        opt = ab.optimum(problem, planning, model)["value"]
        planner = ab.make_planner(planning, model, "default")
        for seed in range(args.seeds):
            for on in ("first", "goal walk"):
                p = planner.solve(TerminationCondition(None, None, args.limit), seed)
                if not p.solved:
                    print(f"| {name} | {seed} | {on} | unsolved |" + " |" * 5)
                    break
                if on == "goal walk":
                    p = goal_shortcuts(planner, p)
                before = p.path_cost
                c0 = time.thread_time()
                q = multiple_shooting(planner, p)
                cpu = time.thread_time() - c0
                r = q.extra["multiple_shooting"]
                print(f"| {name} | {seed} | {on} | {before / opt:.3g} | {r['segments']} | "
                      f"{r['converged']} | {r['kept']} | {q.path_cost / opt:.3g} | "
                      f"{cpu:.2f} |", flush=True)


if __name__ == "__main__":
    main()

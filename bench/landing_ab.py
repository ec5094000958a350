"""Learned edges that land: the planner with the Newton refinement of learned edges off and on
(`planning.learned.LearnedSteering.refine`, ``PlannerSettings.refine_iterations``), same
models, seeds and iteration budget, side by side in one process.

Models are small k-NN fits (the hashed cases' data settings, tests/tree_cases.py), fitted
once into ``--models`` and loaded from there afterwards. Per problem and setting, over the
seeds: plans solved, median process CPU of a plan (to its first solution: the planner stops
there), the median share of the solved paths' duration made by learned edges
(``duration_by``), the median path cost, and the median over plans of the median landing
error of learned edges (distance of an edge's end to its aim, state units; 0 for an edge in
the goal region), the share of learned edges ending within the landing tolerance of their
aim (``LAND_FRACTION`` of the goal tolerance; in the goal region counts), and the
refinements tried and kept.

    python bench/landing_ab.py --models /tmp/landing_models [--seeds 10] [--refine 6]
                               [--steering mean,local_linear,mlp]
                               [--problems pendulum,pendulum_u1,sparse_rrt_cartpole,acrobot,
                                           cartpole,quadrotor]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from itertools import product
from pathlib import Path

import numpy as np

ROOT = Path(__file__).parents[1]
sys.path.insert(0, str(ROOT))

# problem: (tree case whose model settings it uses, plan overrides, iteration budget)
PROBLEMS = {
    "pendulum": ("pendulum_auto", {"goal_tolerance": 0.05}, 3000),
    "pendulum_u1": ("pendulum_u1", {"goal_tolerance": 0.1}, 5000),
    "sparse_rrt_cartpole": ("sparse_rrt_cartpole", {}, 5000),
    "acrobot": ("acrobot", {}, 5000),
    # the shipped cart-pole and quadrotor (not in docs/landing.md's table; docs/predictors.md)
    "cartpole": ("cartpole", {}, 3000),
    "quadrotor": ("quadrotor", {}, 3000),
}


def model_for(case_name: str, models: Path):
    from tests.tree_cases import CASES, fit_model, load_model

    case = next(c for c in CASES if c.name == case_name)
    target = models / case_name
    if (target / "model.json").exists():
        return case, load_model(case, target)
    return case, fit_model(case, target)


def functions_for(model, run_dir: Path, steering: str):
    """The model's functions with U's predictor ``steering``: a k-NN predictor
    (`LearnedFunctions.set_steering`), or "mlp": J and U from networks fitted on the same
    cleaned data (V stays the k-NN classifier), kept in the run as ``functions-mlp.npz``."""
    from rrtcolearn import pipeline
    from rrtcolearn.data.store import load_dataset
    from rrtcolearn.learn.models import LearnedFunctions

    if steering != "mlp":
        return model.functions.set_steering(steering)
    path = run_dir / "functions-mlp.npz"
    if path.exists():
        return LearnedFunctions.load(path)[0]
    data, _ = load_dataset(run_dir / pipeline.CLEANED_FILE, model.system.name)
    cfg = model.config
    cfg = cfg.model_copy(update={"learn": cfg.learn.model_copy(update={"learner": "mlp"})})
    functions = pipeline.fit_functions(model.system, data, cfg)
    functions.save(path)
    return functions


def run(problem: str, models: Path, seeds: int, refine: int,
        steerings: tuple[str, ...] = ("mean",), iterations: int | None = None) -> list[dict]:
    """Rows for ``problem``: per U predictor (``steerings``, `functions_for`) refinement off
    and on, each over ``seeds`` seeds."""
    from rrtcolearn import pipeline
    from rrtcolearn.planning.rrt import RRTCoLearn
    from rrtcolearn.planning.termination import TerminationCondition

    case_name, query, budget = PROBLEMS[problem]
    case, model = model_for(case_name, models)
    cfg = model.config
    start, goal = pipeline.query_states(cfg, model.system)
    if case.start is not None:
        start, goal = list(case.start), list(case.goal)
    tol = query.get("goal_tolerance", cfg.plan.goal_tolerance)
    prob = pipeline.make_problem(model.system, cfg, start, goal, tol)
    base = model.planner_settings(cfg)
    rows = []
    if iterations:
        budget = iterations
    for steering, k in product(steerings, (0, refine) if refine else (0,)):
        functions = functions_for(model, models / case_name, steering)
        planner = RRTCoLearn(prob, functions, replace(base, refine_iterations=k))
        planner.solve(TerminationCondition(None, 50), 10_000)  # warm the kernels
        plans, cpu = [], []
        for seed in range(seeds):
            t = time.process_time()
            plans.append(planner.solve(TerminationCondition(None, budget), seed))
            cpu.append(time.process_time() - t)
        solved = [p for p in plans if p.solved]
        land = [p.extra["landing"] for p in plans]
        errors = [x["median_error"] for x in land if x["median_error"] is not None]
        rows.append({
            "problem": problem, "steering": steering, "refine": k, "iterations": budget,
            "solved": f"{len(solved)}/{seeds}",
            "cpu_s": float(np.median(cpu)),
            "learned_share": float(np.median([p.extra["duration_by"].get("learned", 0.0)
                                               for p in solved])) if solved else float("nan"),
            "cost": float(np.median([p.path_cost for p in solved])) if solved else float("nan"),
            "landing_error": float(np.median(errors)) if errors else float("nan"),
            "refined": sum(x["refined"] for x in land), "landed": sum(x["landed"] for x in land),
            "on_aim": sum(x["on_aim"] for x in land) / max(1, sum(x["edges"] for x in land)),
        })
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("/tmp/landing_models"))
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--refine", type=int, default=6,
                    help="Newton iterations when on (0: refinement off only)")
    ap.add_argument("--iterations", type=int, default=None,
                    help="iteration budget of every problem (default: each problem's own)")
    ap.add_argument("--problems", default="pendulum,pendulum_u1,sparse_rrt_cartpole,acrobot",
                    help=f"comma-separated, of {','.join(PROBLEMS)}")
    ap.add_argument("--steering", default="mean",
                    help="U's predictors to compare, comma-separated (mean, local_linear, mlp)")
    args = ap.parse_args()
    args.models.mkdir(parents=True, exist_ok=True)
    rows = [r for p in args.problems.split(",") for r in run(p, args.models, args.seeds,
                                                             args.refine,
                                                             tuple(args.steering.split(",")),
                                                             args.iterations)]
    print("\n| problem | U | refine | solved | CPU median (s) | learned share of duration "
          "| path cost | landing error | edges on aim | refined / landed |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['problem']} | {r['steering']} | {r['refine']} | {r['solved']} | "
              f"{r['cpu_s']:.3f} | "
              f"{r['learned_share']:.2f} | {r['cost']:.3g} | {r['landing_error']:.3g} | "
              f"{100 * r['on_aim']:.0f}% | {r['refined']} / {r['landed']} |")


if __name__ == "__main__":
    main()

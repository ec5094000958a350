"""Anytime planning with and without the narrowing input box (docs/anytime.md), side by side:
today's restarts + shortcuts (every solve draws its random controls from the whole input box)
against the same with later solves drawing from a box narrowed after each cheaper path
(`anytime.solve_with_restarts`' ``narrowest``), on bench/ablation.py's problems and models,
the default planner, the same seeds, the schemes alternated seed by seed.

    PYTHONPATH=src python bench/narrowing_ab.py [--models DIR] [--out FILE] [--seeds 5]
        [--anytime 10] [--problems a,b] [--schemes whole,narrowing]
    python bench/narrowing_ab.py --table docs/narrowing_ab.json

Per problem and scheme: the median best cost after ``--anytime`` s of process CPU over the
problem's optimum (bench/ablation.py's), the median number of solves, the medians of the
final paths' share of duration made by random-control edges. Results go to ``--out`` (JSON,
written after every query; a rerun with the same settings resumes from it).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import ablation  # noqa: E402  (bench/ablation.py: problems, models, optima)


def run_one(planner, seed: int, budget: float, narrowing: bool) -> dict:
    """``budget`` s of process CPU of anytime planning, the whole box or narrowing."""
    from rrtcolearn.anytime import solve_with_restarts
    from rrtcolearn.planning.improve import shortcut
    from rrtcolearn.planning.termination import TerminationCondition

    narrowest = planner.narrowest_control_scale() if narrowing else 1.0
    p = solve_with_restarts(planner.solve, TerminationCondition(None, None, budget), seed,
                            improve=partial(shortcut, planner), narrowest=narrowest)
    a = p.extra["anytime"]
    return {"solved": bool(p.solved), "cost": float(p.path_cost) if p.solved else None,
            "first_cost": a["first_solution_cost"], "solves": a["solves"],
            "narrowest": narrowest, "scales": a.get("control_scales"),
            "progress": a["progress"],
            "duration": float(p.path_duration) if p.solved else None,
            "duration_by": p.extra.get("duration_by", {}) if p.solved else {}}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=ROOT / "runs" / "ablation-models")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "narrowing_ab.json")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--anytime", type=float, default=10.0, help="process CPU s per query")
    ap.add_argument("--problems", default="sparse_rrt_cartpole,quadrotor,sparse_rrt_acrobot")
    ap.add_argument("--schemes", default="whole,narrowing")
    ap.add_argument("--table", type=Path, default=None, help="print a results file's table")
    args = ap.parse_args(argv)
    if args.table:
        results = json.loads(args.table.read_text())
        print(table(results))
        return results
    settings = {"anytime": args.anytime}
    results = {"settings": settings, "problems": {}}
    if args.out.exists():
        old = json.loads(args.out.read_text())
        if old.get("settings") == settings:
            results = old
    from rrtcolearn.planning.termination import TerminationCondition

    for name in args.problems.split(","):
        problem = ablation.PROBLEMS[name]
        case, model, _ = ablation.model_for(problem, args.models)
        planning = ablation.planning_problem(name, problem, case, model)
        entry = results["problems"].setdefault(name, {"runs": {}})
        if "optimum" not in entry:
            entry["optimum"] = ablation.optimum(problem, planning, model)["value"]
        planner = ablation.make_planner(planning, model, "default")
        planner.solve(TerminationCondition(None, 50), 10_000)  # kernels loaded: not timed
        for seed in range(args.seeds):
            for scheme in args.schemes.split(","):
                runs = entry["runs"].setdefault(scheme, {})
                if str(seed) in runs:
                    continue
                runs[str(seed)] = run_one(planner, seed, args.anytime, scheme == "narrowing")
                r = runs[str(seed)]
                print(name, scheme, seed, r["first_cost"], "->", r["cost"], "solves",
                      r["solves"], "scales", (r["scales"] or [])[-8:], flush=True)
                ablation._write_json(args.out, results)
    print(table(results))
    return results


def table(results: dict) -> str:
    """Medians per problem and scheme."""
    lines = ["| problem | scheme | seeds | best after budget / optimum, median | per seed | "
             "solves, median | control share of the final path, median |",
             "|---|---|---|---|---|---|---|"]
    for name, entry in results["problems"].items():
        opt = entry["optimum"]
        for scheme, runs in entry["runs"].items():
            rs = [runs[k] for k in sorted(runs, key=int)]
            ratios = [r["cost"] / opt for r in rs if r["solved"]]
            med = statistics.median(ratios) if ratios else float("nan")
            share = [r["duration_by"].get("control", 0.0) for r in rs if r["solved"]]
            lines.append(f"| {name} | {scheme} | {len(rs)} | {med:.3g} | "
                         f"{', '.join(f'{x:.3g}' for x in ratios)} | "
                         f"{statistics.median(r['solves'] for r in rs):g} | "
                         f"{statistics.median(share) if share else float('nan'):.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()

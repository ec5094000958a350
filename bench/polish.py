"""One improvement round on the first solution (issue 31; docs/anytime.md, "Polishing the
first solution"): what `multiple_shooting` then `shortcut`, once each, within ``f`` times the
solve's CPU, buy and cost on every problem of bench/ablation.py (default planner).

Per problem and seed: the first solve within ``--limit`` s of process CPU (its cost over the
optimum, its process CPU), then, for each ``f`` of ``--fractions``, the same first plan
(deep-copied, so each f starts from the same tree) passed through
`anytime.solve_with_restarts(..., solves=1, allowance=f)` -- the code ``plan.polish`` runs --
with the budget the solve left; its cost over the optimum and the total process CPU (solve +
polish). ``--steps`` gives the polish an iteration-type allowance (f x the solve's
iterations, one per improvement step, deterministic) instead of CPU seconds.

The optima are bench/ablation.py's: its fixed values and dynobench references, and the
collocation optima recorded in ``--optima`` (docs/ablation.json) instead of solving again.

    PYTHONPATH=src python bench/polish.py [--models DIR] [--out FILE] [--seeds 5]
        [--limit 60] [--fractions 0.25,1] [--problems a,b] [--steps]
    python bench/polish.py --table FILE
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import sys
import time
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

import ablation  # noqa: E402  (bench/ablation.py: problems, models, optima)


def polished(planner, raw, limit: float, fraction: float, steps: bool):
    """``raw`` (a first plan of ``planner``) after one improvement round within ``fraction``
    of its solve (`solve_with_restarts` with ``solves=1``), and the round's process CPU."""
    from rrtcolearn.anytime import solve_with_restarts
    from rrtcolearn.planning.improve import multiple_shooting, shortcut
    from rrtcolearn.planning.termination import TerminationCondition

    copied = copy.deepcopy(raw)  # not timed: the tree as the solve left it
    left = max(limit - raw.planning_cpu_s, 1e-3)
    c0 = time.process_time()
    p = solve_with_restarts(lambda t, s: copied, TerminationCondition(None, None, left), 0,
                            improve=partial(shortcut, planner),
                            first=partial(multiple_shooting, planner),
                            solves=1, allowance=fraction, in_steps=steps)
    return p, time.process_time() - c0


def run(args) -> dict:
    from rrtcolearn.planning.termination import TerminationCondition

    settings = {"seeds": args.seeds, "limit": args.limit, "fractions": args.fractions,
                "steps": args.steps}
    results = {"settings": settings, "problems": {}}
    if args.out.exists():
        old = json.loads(args.out.read_text())
        if old.get("settings") == settings:
            results = old  # resume
    recorded = json.loads(args.optima.read_text())["problems"] if args.optima.exists() else {}
    for name in args.problems.split(","):
        problem = ablation.PROBLEMS[name]
        entry = results["problems"].setdefault(name, {"seeds": {}})
        case, model, _ = ablation.model_for(problem, args.models)
        planning = ablation.planning_problem(name, problem, case, model)
        if "optimum" not in entry:
            if problem.optimum == "collocation" and name in recorded:
                entry["optimum"] = {**recorded[name]["optimum"],
                                    "note": f"{args.optima}: "
                                            + recorded[name]["optimum"]["note"]}
            else:
                entry["optimum"] = ablation.optimum(problem, planning, model)
        planner = ablation.make_planner(planning, model, "default")
        # kernels loaded, the improvements' too where a short solve finds a path: not timed
        warm = planner.solve(TerminationCondition(None, None, min(args.limit, 2.0)), 10_000)
        if warm.solved:
            polished(planner, warm, args.limit, 1.0, args.steps)
        for seed in range(args.seeds):
            if str(seed) in entry["seeds"]:
                continue
            c0 = time.process_time()
            raw = planner.solve(TerminationCondition(None, None, args.limit), seed)
            row = {"solved": bool(raw.solved), "cpu_s": time.process_time() - c0,
                   "iterations": int(raw.iterations),
                   "cost": float(raw.path_cost) if raw.solved else None, "polished": {}}
            for f in args.fractions:
                p, cpu = polished(planner, raw, args.limit, f, args.steps)
                a = p.extra["anytime"]
                row["polished"][str(f)] = {
                    "cost": float(p.path_cost) if p.solved else None, "cpu_s": cpu,
                    "improve_cpu_s": a["planning_cpu_s"] - raw.planning_cpu_s,
                    "steps": a["iterations"] - max(1, raw.iterations),
                    "multiple_shooting": p.extra.get("multiple_shooting", {}).get("kept")}
            entry["seeds"][str(seed)] = row
            print(name, seed, row, flush=True)
            ablation._write_json(args.out, results)
    return results


def _median(v) -> float:
    v = [x for x in v if x is not None]
    return float(statistics.median(v)) if v else float("nan")


def table(results: dict) -> str:
    s = results["settings"]
    lines = [f"{s['seeds']} seeds, first solution within {s['limit']:g} s process CPU; "
             f"polish allowance f x the solve's {'iterations' if s['steps'] else 'CPU'}", "",
             "| problem | solved | first CPU (s) | first cost / opt | "
             + " | ".join(f"f={f:g}: cost / opt | f={f:g}: CPU (s) | f={f:g}: CPU ratio"
                          for f in s["fractions"]) + " |",
             "|---|---|---|---|" + "---|---|---|" * len(s["fractions"])]
    for name, e in results["problems"].items():
        rows = list(e["seeds"].values())
        opt = e["optimum"]["value"]
        ok = [r for r in rows if r["solved"]]
        cpu = _median(r["cpu_s"] if r["solved"] else s["limit"] for r in rows)
        cells = [f"{len(ok)}/{len(rows)}", f"{cpu:.3g}",
                 f"{_median(r['cost'] / opt for r in ok):.3g}"]
        for f in s["fractions"]:
            k = str(f)
            total = [r["cpu_s"] + r["polished"][k]["cpu_s"] if r["solved"] else s["limit"]
                     for r in rows]
            ratio = [(r["cpu_s"] + r["polished"][k]["cpu_s"]) / r["cpu_s"] for r in ok]
            cells += [f"{_median(r['polished'][k]['cost'] / opt for r in ok):.3g}",
                      f"{_median(total):.3g}", f"{_median(ratio):.2f}"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("/tmp/rrtcolearn_ablation_models"))
    ap.add_argument("--out", type=Path, default=Path("runs/polish.json"))
    ap.add_argument("--optima", type=Path, default=ROOT / "docs" / "ablation.json")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--limit", type=float, default=60.0, help="process CPU s per plan")
    ap.add_argument("--fractions", type=lambda v: [float(x) for x in v.split(",")],
                    default=[0.25, 1.0])
    ap.add_argument("--problems", default=",".join(ablation.PROBLEMS))
    ap.add_argument("--steps", action="store_true",
                    help="allowance in improvement steps (f x the solve's iterations)")
    ap.add_argument("--table", type=Path, default=None, metavar="JSON")
    args = ap.parse_args(argv)
    results = json.loads(args.table.read_text()) if args.table else run(args)
    print(table(results))
    return results


if __name__ == "__main__":
    main()

"""Does the plan's step resolve its path? `evaluate.step_check` on the first solutions of
bench/ablation.py's problems (the default planner, its models), or with ``--anytime S`` on
the plans of S s of anytime planning (as `pipeline.plan` plans: the cheapest path its step
resolves, beside the cheapest path of a second run that does not ask): each path replayed
from the start at the plan's step and at half of it (docs/formats.md, "Does the step
resolve the path?").

    PYTHONPATH=src python bench/step_check.py [--models DIR] [--seeds 3] [--problems a,b]
        [--anytime S]

Per plan: its edges, duration, the goal tolerance, the half step's end from the goal and from
the plan's end, and whether the half step's replay still reaches the goal region.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

import ablation  # noqa: E402  (bench/ablation.py: problems, models)


def main(argv: list[str] | None = None) -> list[dict]:
    from rrtcolearn.evaluate import step_check
    from rrtcolearn.planning.termination import TerminationCondition

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=ROOT / "runs" / "ablation-models")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--limit", type=float, default=60.0, help="process CPU s per plan")
    ap.add_argument("--problems", default=",".join(ablation.PROBLEMS))
    ap.add_argument("--anytime", type=float, default=None,
                    help="check the plans of this many s of anytime planning instead")
    args = ap.parse_args(argv)
    rows = []
    print(f"{'problem':<20} {'seed':>4} {'edges':>5} {'T':>6} {'tol':>5} {'goal@dt/2':>9} "
          f"{'goal gap':>8} {'valid':>5}  resolved")
    for name in args.problems.split(","):
        prob = ablation.PROBLEMS[name]
        case, model, _ = ablation.model_for(prob, args.models)
        planning = ablation.planning_problem(name, prob, case, model)
        planner = ablation.make_planner(planning, model, "default")
        for seed in range(args.seeds):
            if args.anytime is not None:  # the cheapest path, then the cheapest resolved
                was = ablation.anytime_plan(planner, seed, args.anytime, resolved=False)
                p = ablation.anytime_plan(planner, seed, args.anytime)
                w = step_check(planning, was) if was.solved else None
                print(f"{'':<20} {seed:>4} cheapest path: cost {was.path_cost:.4g}, "
                      f"resolved {w and w['resolved']}; cheapest resolved: cost "
                      f"{p.path_cost:.4g} ({p.path_cost / was.path_cost:.3g}x), not accepted "
                      f"{p.extra['anytime'].get('not_accepted')}", flush=True)
            else:
                p = planner.solve(TerminationCondition(None, None, args.limit), seed)
            if not p.solved:
                print(f"{name:<20} {seed:>4} unsolved")
                continue
            c = step_check(planning, p)
            rows.append({"problem": name, "seed": seed, "tolerance": planning.goal_tolerance,
                         **c})
            print(f"{name:<20} {seed:>4} {len(p.edges()):>5} {p.path_duration:>6.2f} "
                  f"{planning.goal_tolerance:>5.3g} {c['goal_distance']:>9.3g} "
                  f"{c['goal_gap']:>8.2g} {'yes' if c['valid'] else 'no':>5}  "
                  f"{'yes' if c['resolved'] else 'NO'}", flush=True)
    print(f"{len(rows)} plans: {sum(not r['resolved'] for r in rows)} not resolved by their "
          f"step, {sum(r['goal_distance'] > r['tolerance'] for r in rows)} with the half "
          f"step's end outside the goal region, {sum(not r['valid'] for r in rows)} with a "
          f"half step's state in an obstacle or out of bounds, "
          f"{sum(not r['replays'] for r in rows)} not re-simulating to their own path")
    return rows


if __name__ == "__main__":
    main()

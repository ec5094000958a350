"""dynobench's problems read as the package ships them, planned by RRT-CoLearn (docs/dynobench.md).

Per robot one offline model, `rrtcolearn run --dynobench <robot>/<first problem>` (its
summary.json gives the offline CPU; an existing run is reused with ``--runs DIR``, the
robot's run in DIR/<robot>). Per problem ``--seeds`` seeded plans of at most ``--time-limit``
s (wall; the table names CPU): success, the median CPU to the first solution and median
path duration, beside the durations and times of the reference solutions the package
ships (iDb-A* and RRT + trajectory optimisation, timed by dynobench's authors on another
machine: ratios only indicate). Every solved path is exported in dynobench's result format
(`dynobench.result`, on its 0.1 s grid) and every exported state and every RK4 step of it
is checked by dynobench's own collision checker (its bindings, fcl; the count in collision
is printed), and re-integrated from the start (`evaluate.replay`: valid, reaches the goal).
With ``--inflation PROBLEMS`` the same seeds plan a point among boxes grown by the body's
half-diagonal (`Workspace.inflated`), the conservative stand-in. Last, the collision test's
cost per RK4 step on the states of the solved paths, edge by edge (50 states a call):
compiled (`Workspace.contains`), shapely 2's vectorised ``intersects`` (if installed) and
dynobench's fcl checker (one call per state), process CPU.

    python bench/dynobench_bench.py [--problems unicycle1_v0/parallelpark_0,...] [--seeds 10]
        [--time-limit 60] [--runs DIR] [--inflation unicycle1_v0/parallelpark_0,...]

Prints the tables and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from rrtcolearn import dynobench as db
from rrtcolearn import pipeline
from rrtcolearn.evaluate import replay, sample_path
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

PROBLEMS = "unicycle1_v0/parallelpark_0,unicycle1_v0/kink_0,unicycle1_v0/bugtrap_0"
TOLERANCE = 0.1


def model_for(robot: str, first: str, runs: Path) -> tuple[object, float]:
    """The robot's fitted run (made by the CLI if absent) and its offline CPU."""
    run_dir = runs / robot
    if not (run_dir / "model.json").is_file():
        subprocess.run([sys.executable, "-m", "rrtcolearn.cli", "run", "--dynobench", first,
                        "--out", str(run_dir)], check=True)
    summary = json.loads((run_dir / "summary.json").read_text())
    return pipeline.load_model(run_dir), float(summary["offline_cpu_s"])


def plan_seeds(fitted, read, seeds: int, limit: float, inflated: bool) -> dict:
    """Plan ``seeds`` seeds; the solved paths checked by dynobench's checker and replay."""
    problem = db.planning_problem(read, fitted.system, TOLERANCE, inflated=inflated)
    exact = db.planning_problem(read, fitted.system, TOLERANCE)  # the check: exact body
    settings = fitted.planner_settings()
    rows = []
    for seed in range(seeds):
        plan = RRTCoLearn(problem, fitted.functions, settings).solve(
            TerminationCondition(time_limit=limit), seed)
        row = {"seed": seed, "solved": plan.solved, "cpu_s": plan.planning_cpu_s}
        if plan.solved:
            samples = sample_path(fitted.system, plan)
            res = db.result(read, samples)
            exported = np.array(res["states"])
            row |= {"duration": plan.path_duration,
                    "dynobench_in_collision": int(np.sum(db.dynobench_distances(
                        read, exported) <= 0)),
                    "dynobench_steps_in_collision": int(np.sum(db.dynobench_distances(
                        read, samples["state"]) <= 0)),
                    "exported_states": len(exported), "steps": len(samples["state"]),
                    "replay_ok": bool(replay(exact, plan)["reaches_goal"]),
                    "states": samples["state"]}
        rows.append(row)
    return {"rows": rows}


def summarise(rows: list[dict]) -> dict:
    solved = [r for r in rows if r["solved"]]
    med = (lambda k: float(np.median([r[k] for r in solved])) if solved else float("nan"))  # noqa: E731
    return {"solved": len(solved), "seeds": len(rows), "cpu_median_s": med("cpu_s"),
            "duration_median_s": med("duration"),
            "dynobench_in_collision": sum(r["dynobench_in_collision"] for r in solved),
            "dynobench_steps_in_collision": sum(r["dynobench_steps_in_collision"]
                                                for r in solved),
            "exported_states": sum(r["exported_states"] for r in solved),
            "steps": sum(r["steps"] for r in solved),
            "replay_ok": sum(r["replay_ok"] for r in solved)}


def collision_cost(read, states: np.ndarray, per_call: int = 50) -> dict:
    """CPU per RK4 step of the collision test, ``per_call`` states a call (an edge)."""
    ws = db.workspace(read)
    chunks = [states[i:i + per_call] for i in range(0, len(states), per_call)]
    out = {}
    ws.contains(chunks[0])  # compiled before timing
    t = time.process_time()
    mine = np.concatenate([ws.contains(c) for c in chunks])
    out["compiled_us"] = 1e6 * (time.process_time() - t) / len(states)
    try:
        import shapely
    except ImportError:
        shapely = None
    if shapely is not None:
        obstacles = [shapely.Polygon(o.vertices()) for o in read.obstacles]
        local = db.body(read).shapes[0].vertices()

        def library(x):
            c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
            px = x[:, None, 0] + c[:, None] * local[:, 0] - s[:, None] * local[:, 1]
            py = x[:, None, 1] + s[:, None] * local[:, 0] + c[:, None] * local[:, 1]
            bodies = shapely.polygons(np.stack([px, py], -1))
            return shapely.intersects(bodies[:, None], np.array(obstacles)[None]).any(1)

        library(chunks[0])
        t = time.process_time()
        theirs = np.concatenate([library(c) for c in chunks])
        out["shapely_us"] = 1e6 * (time.process_time() - t) / len(states)
        out["shapely_disagree"] = int(np.sum(theirs != mine))
    db.dynobench_distances(read, states[:2])
    t = time.process_time()
    fcl = db.dynobench_distances(read, states) <= 0
    out["fcl_us"] = 1e6 * (time.process_time() - t) / len(states)
    out["fcl_disagree"] = int(np.sum(fcl != mine))
    out["states"] = len(states)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problems", default=PROBLEMS)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--time-limit", type=float, default=60.0)
    ap.add_argument("--runs", type=Path, default=Path("runs/dynobench"))
    ap.add_argument("--inflation", default="unicycle1_v0/parallelpark_0,unicycle1_v0/kink_0")
    args = ap.parse_args()
    problems = [p for p in args.problems.split(",") if p]
    models, report = {}, {"w": None, "tolerance": TOLERANCE, "problems": {}}
    all_states = {}
    for name in problems:
        read = db.read_problem(name)
        if read.robot not in models:
            models[read.robot] = model_for(read.robot, name, args.runs)
        fitted, offline = models[read.robot]
        report["w"] = fitted.config.system.time_weight
        entry = {"robot": read.robot, "offline_cpu_s": offline,
                 "references": db.references(read)}
        variants = [False] + ([True] if name in args.inflation.split(",") else [])
        for inflated in variants:
            got = plan_seeds(fitted, read, args.seeds, args.time_limit, inflated)
            entry["inflated" if inflated else "exact"] = summarise(got["rows"])
            if not inflated:
                solved = [r["states"] for r in got["rows"] if r["solved"]]
                if solved:
                    all_states[name] = (read, np.concatenate(solved))
        report["problems"][name] = entry
        print(name, json.dumps(entry), flush=True)
    report["collision_cost"] = {n: collision_cost(r, s) for n, (r, s) in all_states.items()}
    print_tables(report)
    print(json.dumps(report))


def print_tables(report: dict) -> None:
    print(f"\nw = {report['w']:g}, goal tolerance {report['tolerance']} (weighted, angle "
          "wrapped); references timed by dynobench's authors on another machine")
    print("| problem | body | solved | CPU median s | duration median s | iDb-A* duration (s) "
          "/ time (ms) | RRT+TO duration | ratio to iDb-A* | dynobench collisions "
          "(exported / steps) | replay ok | offline CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, e in report["problems"].items():
        ref = e["references"].get("idbastar_v0_solution_v0", {})
        rrt = e["references"].get("rrt_to_v0_solution_v0", {})
        for body in ("exact", "inflated"):
            if body not in e:
                continue
            s = e[body]
            ratio = s["duration_median_s"] / ref["cost"] if ref else float("nan")
            print(f"| {name} | {body} | {s['solved']}/{s['seeds']} | {s['cpu_median_s']:.3g} | "
                  f"{s['duration_median_s']:.3g} | {ref.get('cost', float('nan')):g} / "
                  f"{ref.get('time_stamp', float('nan')):g} | {rrt.get('cost', float('nan')):g}"
                  f" | {ratio:.2f} | {s['dynobench_in_collision']}/{s['exported_states']}, "
                  f"{s['dynobench_steps_in_collision']}/{s['steps']} | {s['replay_ok']} | "
                  f"{e['offline_cpu_s']:.0f} |")
    print("\n| problem | states | compiled us/step | shapely us/step | fcl (dynobench) us/step "
          "| disagreements shapely / fcl |")
    print("|---|---|---|---|---|---|")
    for name, c in report["collision_cost"].items():
        print(f"| {name} | {c['states']} | {c['compiled_us']:.3g} | "
              f"{c.get('shapely_us', float('nan')):.3g} | {c['fcl_us']:.3g} | "
              f"{c.get('shapely_disagree', '-')} / {c['fcl_disagree']} |")


if __name__ == "__main__":
    main()

"""dynobench's problems read as the package ships them, planned by RRT-CoLearn (docs/dynobench.md).

Per robot one offline model, `rrtcolearn run --dynobench <robot>/<first problem>` with the
robot's recommended settings (its summary.json gives the offline CPU; an existing run is
reused: ``--runs DIR``, the robot's run in DIR/<robot>). Per problem ``--seeds`` seeded plans
of at most ``--time-limit`` s of process CPU (and ``--wall-factor`` (3) times that of wall
time, so a loaded machine cannot stall the run): success, the median CPU to the first solution
and the median path duration, beside the durations and times of the reference solutions the
package ships (iDb-A* and RRT + trajectory optimisation, timed by dynobench's authors on
another machine: the ratios only indicate). Every solved path is exported in dynobench's
result format (`dynobench.result`, on the robot's time grid) and every exported state and
every RK4 step of it is checked by dynobench's own collision checker (its bindings, fcl; the
count in collision is recorded), and re-integrated from the start (`evaluate.replay`: valid,
reaches the goal). With ``--inflation PROBLEMS`` the same seeds plan a point among boxes grown
by the body's half-diagonal (`Workspace.inflated`), the conservative stand-in. Last, the
collision test's cost per RK4 step on the states of the solved paths, edge by edge (50 states
a call): compiled (`Workspace.contains`), shapely 2's vectorised ``intersects`` (if installed)
and dynobench's fcl checker (one call per state), process CPU.

    python bench/dynobench_bench.py [--models unicycle1_v0,...] [--problems ROBOT/ENV,...]
        [--seeds 10] [--time-limit 60] [--runs DIR] [--out FILE.json]
        [--inflation unicycle1_v0/parallelpark_0,...]

Default: every problem of every built model (`dynobench.shipped_problems`). Results are
written to ``--out`` (atomically) after every problem, and a problem already there with the
same seeds and limit is not planned again (a stopped run resumes). Prints the tables.
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
from rrtcolearn.data.store import atomic_write_text
from rrtcolearn.evaluate import replay, sample_path
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

TOLERANCE = 0.1


def model_for(robot: str, first: str, runs: Path) -> tuple[object, float]:
    """The robot's fitted run (made by the CLI if absent) and its offline CPU."""
    run_dir = runs / robot
    if not (run_dir / "model.json").is_file():
        subprocess.run([sys.executable, "-m", "rrtcolearn.cli", "run", "--dynobench", first,
                        "--out", str(run_dir)], check=True)
    summary = json.loads((run_dir / "summary.json").read_text())
    return pipeline.load_model(run_dir), float(summary["offline_cpu_s"])


def plan_seeds(fitted, read, seeds: int, limit: float, inflated: bool,
               wall_factor: float = 3.0) -> dict:
    """Plan ``seeds`` seeds; the solved paths checked by dynobench's checker and replay."""
    problem = db.planning_problem(read, fitted.system, TOLERANCE, inflated=inflated)
    exact = db.planning_problem(read, fitted.system, TOLERANCE)  # the check: exact body
    settings = fitted.planner_settings()
    rows = []
    for seed in range(seeds):
        plan = RRTCoLearn(problem, fitted.functions, settings).solve(
            TerminationCondition(time_limit=wall_factor * limit, cpu_time_limit=limit), seed)
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
        obstacles = np.array([shapely.Polygon(o.vertices()) for o in read.obstacles])
        body = db.body(read)
        local = [shape.vertices() for shape in body.shapes]

        def library(x):
            poses = body.poses(x)  # (N, B, 3)
            hit = np.zeros(len(x), dtype=bool)
            for b, v in enumerate(local):
                px, py, th = (poses[:, b, k][:, None] for k in range(3))
                c, s = np.cos(th), np.sin(th)
                corners = np.stack([px + c * v[:, 0] - s * v[:, 1],
                                    py + s * v[:, 0] + c * v[:, 1]], -1)
                hit |= shapely.intersects(shapely.polygons(corners)[:, None],
                                          obstacles[None]).any(1)
            return hit

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


def _json(obj):
    """NaN as null (strict JSON)."""
    if isinstance(obj, float) and obj != obj:
        return None
    if isinstance(obj, dict):
        return {k: _json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json(v) for v in obj]
    return obj


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=",".join(db.BUILT))
    ap.add_argument("--problems", default="", help="ROBOT/ENV,... (default: every problem "
                    "of --models)")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--time-limit", type=float, default=60.0, help="CPU s per seed")
    ap.add_argument("--runs", type=Path, default=Path("runs/dynobench"))
    ap.add_argument("--out", type=Path, default=Path("runs/dynobench/bench.json"))
    ap.add_argument("--inflation", default="unicycle1_v0/parallelpark_0,unicycle1_v0/kink_0")
    ap.add_argument("--wall-factor", type=float, default=3.0, help="wall cap per seed, as a "
                    "multiple of --time-limit (raise it on a loaded machine, where 3x cut "
                    "unsolved seeds at 13-24 s CPU)")
    ap.add_argument("--no-collision-cost", action="store_true")
    ap.add_argument("--tables", default="", help="A.json,B.json,...: print the tables of "
                    "these results (merged) and stop")
    args = ap.parse_args()
    if args.tables:
        print_tables(merge([json.loads(Path(f).read_text()) for f in args.tables.split(",")]))
        return
    problems = [p for p in args.problems.split(",") if p] or db.shipped_problems(
        tuple(m for m in args.models.split(",") if m))
    report = {"tolerance": TOLERANCE, "seeds": args.seeds, "time_limit_cpu_s": args.time_limit,
              "wall_factor": args.wall_factor, "w": {}, "offline_cpu_s": {}, "problems": {}}
    if args.out.is_file():
        old = json.loads(args.out.read_text())
        if (old.get("seeds"), old.get("time_limit_cpu_s")) == (args.seeds, args.time_limit):
            report = old | {"wall_factor": args.wall_factor}
    models, all_states = {}, {}
    for name in problems:
        read = db.read_problem(name)
        if read.robot not in models:
            models[read.robot] = model_for(read.robot, name, args.runs)
        fitted, offline = models[read.robot]
        report["w"][read.robot] = fitted.config.system.time_weight
        report["offline_cpu_s"][read.robot] = offline
        entry = report["problems"].get(name)
        variants = ["exact"] + (["inflated"] if name in args.inflation.split(",") else [])
        if entry is None or any(v not in entry for v in variants):
            entry = {"robot": read.robot, "offline_cpu_s": offline,
                     "references": db.references(read)}
            for variant in variants:
                got = plan_seeds(fitted, read, args.seeds, args.time_limit,
                                 variant == "inflated", args.wall_factor)
                entry[variant] = summarise(got["rows"])
                if variant == "exact":
                    entry["rows"] = [{k: v for k, v in r.items() if k != "states"}
                                     for r in got["rows"]]
                    solved = [r["states"] for r in got["rows"] if r["solved"]]
                    if solved:
                        all_states[name] = (read, np.concatenate(solved))
            report["problems"][name] = entry
            args.out.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(args.out, json.dumps(_json(report), indent=1))
        print(name, json.dumps(_json({k: entry[k] for k in variants})), flush=True)
    if not args.no_collision_cost:
        report["collision_cost"] = {n: collision_cost(r, s) for n, (r, s) in
                                    all_states.items() if r.obstacles}
        atomic_write_text(args.out, json.dumps(_json(report), indent=1))
    print_tables(report)


def merge(reports: list[dict]) -> dict:
    """Several runs' results as one (each problem from the last report holding it)."""
    out = {"tolerance": TOLERANCE, "w": {}, "offline_cpu_s": {}, "problems": {},
           "collision_cost": {}, "runs": [(r["seeds"], r["time_limit_cpu_s"]) for r in reports],
           "wall_factors": sorted({r.get("wall_factor") or 0 for r in reports})}
    for r in reports:
        for key in ("w", "offline_cpu_s", "problems", "collision_cost"):
            out[key].update(r.get(key) or {})
    return out


def _unsolved(entry: dict, body: str) -> str:
    cpu = [r["cpu_s"] for r in entry.get("rows", []) if not r["solved"]]
    return f"{min(cpu):.0f}-{max(cpu):.0f}" if body == "exact" and cpu else "-"


def _num(a) -> str:
    return f"{a:.3g}" if a is not None and a == a else "-"


def _ratio(a, b) -> str:
    return f"{a / b:.2f}" if a == a and b and b == b else "-"


def print_tables(report: dict) -> None:
    w = ", ".join(f"{r} {v:g}" for r, v in report["w"].items())
    runs = report.get("runs", [(report.get("seeds"), report.get("time_limit_cpu_s"))])
    factors = report.get("wall_factors", [report.get("wall_factor") or 0])
    cap = (" or ".join(f"{f:g}" for f in factors if f) or "the --wall-factor")
    print(f"\nw: {w}; goal tolerance {report['tolerance']} (weighted, angles wrapped); "
          f"(seeds, CPU limit s): {runs}; references timed by dynobench's authors on another "
          "machine; 'unsolved CPU' is the CPU the unsolved seeds got before the limit or "
          f"the wall cap ({cap} x the limit) stopped them")
    print("| problem | body | solved | CPU median s | duration median s | iDb-A* duration s "
          "/ time s | RRT+TO duration s | duration / iDb-A*'s | CPU / iDb-A*'s time | "
          "duration / RRT+TO's | dynobench: in collision (exported; RK4 steps) | replays "
          "| unsolved CPU s (min-max) | offline CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, e in report["problems"].items():
        ref = e["references"].get("idbastar_v0_solution_v0", {})
        rrt = e["references"].get("rrt_to_v0_solution_v0", {})
        nan = float("nan")
        cost, stamp = ref.get("cost", nan), ref.get("time_stamp", nan)
        stamp = stamp / 1000 if stamp is not None else nan  # shipped in ms
        for body in ("exact", "inflated"):
            if body not in e:
                continue
            s = e[body]
            cpu = s["cpu_median_s"] if s["cpu_median_s"] is not None else nan
            dur = s["duration_median_s"] if s["duration_median_s"] is not None else nan
            print(f"| {name} | {body} | {s['solved']}/{s['seeds']} | {_num(cpu)} | {_num(dur)} | "
                  f"{_num(cost)} / {_num(stamp)} | {_num(rrt.get('cost', nan))} | "
                  f"{_ratio(dur, cost)} | "
                  f"{_ratio(cpu, stamp)} | {_ratio(dur, rrt.get('cost', nan))} | "
                  f"{s['dynobench_in_collision']}/{s['exported_states']}; "
                  f"{s['dynobench_steps_in_collision']}/{s['steps']} | "
                  f"{s['replay_ok']}/{s['solved']} | {_unsolved(e, body)} | "
                  f"{e['offline_cpu_s']:.0f} |")
    if report.get("collision_cost"):
        print("\n| problem | states | compiled us/step | shapely us/step | fcl (dynobench) "
              "us/step | disagreements shapely / fcl |")
        print("|---|---|---|---|---|---|")
        for name, c in report["collision_cost"].items():
            print(f"| {name} | {c['states']} | {c['compiled_us']:.3g} | "
                  f"{c.get('shapely_us', float('nan')):.3g} | {c['fcl_us']:.3g} | "
                  f"{c.get('shapely_disagree', '-')} / {c['fcl_disagree']} |")


if __name__ == "__main__":
    main()

"""The ablation of issue 31: learned steering only, random controls only, and the default
planner, on every problem of the issue, each against that problem's optimum (docs/ablation.md).

Problems (typed in through the public API; the models are small k-NN fits with the hashed
cases' data settings, tests/tree_cases.py): the paper's pendulum from hanging to upright
(ball 0.1), unbounded and with |u| <= 1; the shipped cart-pole, acrobot and quadrotor and
sparse_rrt's cart-pole and acrobot (examples/) with their default queries; dynobench's
unicycle1_v0 parallelpark_0 and kink_0 (`rrtcolearn.dynobench`, exact body, ball 0.1).

Modes, one model per problem:
- ``learned``: the learned steering only: no random-control edges (``control_edges`` false),
  the goal connections as by default. On a system without an input box the default has no
  random controls either: the row is the default's (not run twice).
- ``random``: random controls only: the planner without learned functions (``model`` None,
  its random-control edges and LQR connection; `planning.rrt.RRTCoLearn`). Needs an input
  box: "n/a" on an unbounded system.
- ``default``: the planner as shipped.

Per problem and mode: success over ``--seeds`` seeds within ``--limit`` s of process CPU,
the median process CPU to the first solution (an unsolved seed counts as the limit), its
ratio to the default's, the median shares of the first path's duration made by learned edges
and by extremal edges of any kind (learned + shooting + funnel, `duration_shares`), the
median first-path cost over the optimum, the median cost after ``--anytime`` s of anytime
planning (`anytime.solve_with_restarts` with `planning.improve.shortcut`, what
``plan.anytime`` runs) over ``--anytime-seeds`` seeds, and the model's offline CPU
(generation + cleaning + fit, this process and its workers; recorded beside the model).

Optima (`OPTIMA`): collocation (`baselines.collocation.problem_optimum` on the very problem
planned) where it runs in seconds, the values of docs/collocation.md where its query is the
one planned, and for the unicycles the cheapest reference solution dynobench ships, priced
with our cost (`reference_cost`: the obstacles are not in the collocation).

Results go to ``--out`` (JSON, written atomically after every seed; a rerun with the same
settings resumes from it), the table is printed last.

    PYTHONPATH=src python bench/ablation.py [--models DIR] [--out FILE] [--seeds 5]
        [--anytime-seeds 3] [--limit 60] [--anytime 10] [--problems a,b] [--modes a,b]
        [--set plan_setting=value ...]
    python bench/ablation.py --table docs/ablation.json [--versus BASE.json]

``--versus BASE.json`` also prints the default mode side by side with another results file
(same settings, e.g. the parent commit's): success, CPU median and its ratio, first cost.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # examples.* systems and tests.tree_cases

MODES = ("learned", "random", "default")
# the extremal kinds of `PlannerData.kind`: edges that solve the state+costate ODEs (a held
# input is "control"; the LQR connection's chains are held inputs too)
EXTREMAL = ("learned", "shooting", "funnel")
DYNOBENCH_TOLERANCE = 0.1  # bench/dynobench_bench.py's


@dataclass(frozen=True)
class Problem:
    """One row group: the tree case whose model (data settings) it uses, the goal tolerance
    (None: the model's configured one), a dynobench problem (its query and workspace instead
    of the system's default query), and where its optimum comes from."""

    case: str
    tolerance: float | None = None
    dynobench: str | None = None
    optimum: float | str = "collocation"  # a value from docs/collocation.md, "collocation",
    # "reference" (dynobench's) or "n/a"
    optimum_note: str = ""


PROBLEMS = {
    "pendulum": Problem("pendulum_auto", 0.1),
    "pendulum_u1": Problem("pendulum_u1", 0.1),
    "cartpole": Problem("cartpole", optimum=129.503, optimum_note=(
        "best found, local (docs/collocation.md: tolerance 0.3 wrapped, unbounded, the "
        "system's box; N = 600 from the cheapest of ten 16-s anytime paths at 30b1d84, "
        "133.72 on seed 2; was 132.386 from seed 6's 137.06 at a683e65, and 223.448 from "
        "an older planner's path)")),
    "acrobot": Problem("acrobot", optimum=15.768, optimum_note=(
        "best found, local (docs/collocation.md: tolerance 0.3 wrapped, unbounded; N = 400 "
        "from the anytime path of seed 5 with piece_shortcuts, 19.017 in 6.73 s; was 19.564 "
        "from seed 7's 87.61 at a683e65, and 21.10 from straight lines)")),
    "quadrotor": Problem("quadrotor"),
    "sparse_rrt_cartpole": Problem("sparse_rrt_cartpole", optimum=48.005, optimum_note=(
        "docs/collocation.md: |F| <= 300, ball 1.5, every straight-line guess and the "
        "planner's path converged to it")),
    "sparse_rrt_acrobot": Problem("sparse_rrt_acrobot", optimum=29.59, optimum_note=(
        "best found, local (docs/collocation.md: |tau| <= 4, task-space goal 2, from the "
        "planner's path)")),
    "parallelpark": Problem("unicycle1_v0", DYNOBENCH_TOLERANCE, "unicycle1_v0/parallelpark_0",
                            "reference"),
    "kink": Problem("unicycle1_v0", DYNOBENCH_TOLERANCE, "unicycle1_v0/kink_0", "reference"),
}


def duration_shares(duration_by: dict[str, float]) -> tuple[float, float]:
    """(learned, extremal) shares of a path's duration from the plan's ``duration_by``
    (kind -> share): edges made by the learned steering, and edges that are extremals of any
    kind (learned, shooting, funnel); NaN for a path without duration (empty dict)."""
    if not duration_by:
        return float("nan"), float("nan")
    return (float(duration_by.get("learned", 0.0)),
            float(sum(duration_by.get(k, 0.0) for k in EXTREMAL)))


def reference_cost(actions: np.ndarray, dt: float, time_weight: float,
                   input_weight: np.ndarray) -> float:
    """Our running cost, w T + sum over steps of dt u^T R u / 2, of a path of held inputs
    ``actions`` (K, m), each held ``dt`` (dynobench's result format)."""
    u = np.asarray(actions, dtype=float)
    r = np.asarray(input_weight, dtype=float)
    return float(time_weight * len(u) * dt + dt * 0.5 * np.einsum("ki,ij,kj->", u, r, u))


def dynobench_reference(read, system, time_weight: float) -> tuple[float, str]:
    """The cheapest feasible reference solution dynobench ships for ``read``, priced by
    `reference_cost` with the system's R; (cost, note naming it and its duration)."""
    import yaml

    r = np.array(system.symbolic()[0].input_weight, dtype=float)  # (derivation, parametrisation)
    best = None
    for f in sorted((read.path.parent / read.path.stem).glob("*solution*.yaml")):
        d = yaml.safe_load(f.read_text())
        if d.get("feasible") != 1 or "actions" not in d:
            continue
        c = reference_cost(np.array(d["actions"]), read.dt, time_weight, r)
        if best is None or c < best[0]:
            best = (c, f"{f.stem}, {len(d['actions']) * read.dt:.1f} s")
    if best is None:
        return float("nan"), "no feasible reference shipped"
    return best[0], (f"reference, not an optimum: dynobench's {best[1]}, priced w T + "
                     "int u^T R u / 2 (its goal tolerance and body, not ours)")


def _cpu_with_children() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), \
        resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def model_for(problem: Problem, models: Path):
    """The problem's fitted model (fitted into ``models/<case>`` once, loaded afterwards)
    and its offline CPU (None for a model fitted before the figure was recorded)."""
    from tests.tree_cases import CASES, Case, fit_model, load_model

    if problem.case in {c.name for c in CASES}:
        case = next(c for c in CASES if c.name == problem.case)
    else:  # a dynobench robot, on the other small models' data settings
        small = next(c for c in CASES if c.name == "cartpole").fit[1:]
        case = Case(problem.case, (f'system.name="rrtcolearn.dynobench:{problem.case}"',
                                   *small))
    target = models / problem.case
    record = target / "offline.json"
    if (target / "model.json").exists():
        offline = json.loads(record.read_text())["offline_cpu_s"] if record.exists() else None
        return case, load_model(case, target), offline
    c0 = _cpu_with_children()
    model = fit_model(case, target)
    offline = _cpu_with_children() - c0
    _write_json(record, {"offline_cpu_s": offline})
    return case, model, offline


def planning_problem(name: str, problem: Problem, case, model):
    """The query the bench plans for ``name`` (`pipeline.make_problem`, or dynobench's)."""
    from rrtcolearn import dynobench as db
    from rrtcolearn import pipeline

    if problem.dynobench:
        return db.planning_problem(db.read_problem(problem.dynobench), model.system,
                                   problem.tolerance)
    cfg = model.config
    start, goal = pipeline.query_states(cfg, model.system)
    if case.start is not None:
        start, goal = list(case.start), list(case.goal)
    tol = problem.tolerance if problem.tolerance is not None else cfg.plan.goal_tolerance
    return pipeline.make_problem(model.system, cfg, start, goal, tol)


def optimum(problem: Problem, planning, model) -> dict:
    """The problem's optimum: {value, kind, note, cpu_s}."""
    w = model.config.system.time_weight
    if isinstance(problem.optimum, float):
        return {"value": problem.optimum, "note": problem.optimum_note, "cpu_s": 0.0}
    if problem.optimum == "reference":
        from rrtcolearn import dynobench as db

        value, note = dynobench_reference(db.read_problem(problem.dynobench), model.system, w)
        return {"value": value, "note": note, "cpu_s": 0.0}
    from rrtcolearn.baselines.collocation import problem_optimum

    c0 = time.process_time()
    durations = (2, 4, 6, 8, 10, 12)
    res = problem_optimum(planning, time_weight=w, durations=durations, t_max=30.0)
    s = res.summary()
    converged = sum(a["success"] for a in res.attempts)
    return {"value": float(s["cost"]), "cpu_s": time.process_time() - c0,
            "note": (f"collocation on the planned problem, best of {converged}/{len(res.attempts)}"
                     f" converged straight-line guesses (T = {durations} s; local optima "
                     f"possible), T* = {s['duration']:.3g} s, interval error "
                     f"{s['interval_error']:.1g}")}


def make_planner(planning, model, mode: str, overrides: dict | None = None):
    """The mode's planner, or None where the mode does not exist for the problem;
    ``overrides``: planner settings set in every mode (`PlannerSettings` field -> value)."""
    from rrtcolearn.errors import ConfigError
    from rrtcolearn.planning.rrt import RRTCoLearn

    settings = model.planner_settings()
    if overrides:
        settings = replace(settings, **overrides)
    if mode == "learned":
        return RRTCoLearn(planning, model.functions, replace(settings, control_edges=False))
    if mode == "random":
        try:
            return RRTCoLearn(planning, None, settings)
        except ConfigError:  # no input box to draw random controls from
            return None
    return RRTCoLearn(planning, model.functions, settings)


def first_solution(planner, seed: int, limit: float) -> dict:
    """One plan to the first solution within ``limit`` s of process CPU."""
    from rrtcolearn.planning.termination import TerminationCondition

    c0 = time.process_time()
    p = planner.solve(TerminationCondition(None, None, limit), seed)
    cpu = time.process_time() - c0
    learned, extremal = duration_shares(p.extra.get("duration_by", {})) if p.solved else \
        (float("nan"), float("nan"))
    return {"solved": bool(p.solved), "cpu_s": cpu, "iterations": int(p.iterations),
            "cost": float(p.path_cost) if p.solved else None,
            "duration": float(p.path_duration) if p.solved else None,
            "learned_share": learned, "extremal_share": extremal,
            "duration_by": p.extra.get("duration_by", {}) if p.solved else {}}


def anytime_plan(planner, seed: int, budget: float, resolved: bool = True):
    """The plan of ``budget`` s of process CPU of anytime planning (restarts + shortcuts),
    as `pipeline.plan` plans it: the cheapest path its step resolves kept (``resolved``;
    False: the cheapest path, as before `evaluate.step_check`)."""
    from rrtcolearn.anytime import solve_with_restarts
    from rrtcolearn.evaluate import is_resolved
    from rrtcolearn.planning.improve import multiple_shooting, shortcut
    from rrtcolearn.planning.termination import TerminationCondition

    accept = None if not resolved else partial(is_resolved, planner.problem)
    return solve_with_restarts(planner.solve, TerminationCondition(None, None, budget), seed,
                               improve=partial(shortcut, planner, accept=accept),
                               narrowest=planner.narrowest_control_scale(),
                               first=partial(multiple_shooting, planner), accept=accept)


def anytime(planner, seed: int, budget: float) -> dict:
    """``budget`` s of process CPU of anytime planning (`anytime_plan`): its figures."""
    p = anytime_plan(planner, seed, budget)
    a = p.extra["anytime"]
    return {"solved": bool(p.solved), "cost": float(p.path_cost) if p.solved else None,
            "first_cost": a["first_solution_cost"], "solves": a["solves"],
            "multiple_shooting": a.get("first")}


def _write_json(path: Path, data) -> None:
    """Write ``data`` to ``path`` atomically (a crash leaves the old file or the new)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=float))
    os.replace(tmp, path)


def run(args) -> dict:
    settings = {"seeds": args.seeds, "anytime_seeds": args.anytime_seeds,
                "limit": args.limit, "anytime": args.anytime}
    overrides = _overrides(args.set)
    if overrides:  # (absent without: older results files resume)
        settings["set"] = overrides
    results = {"settings": settings, "problems": {}}
    if args.out.exists():
        old = json.loads(args.out.read_text())
        if old.get("settings") == settings:
            results = old  # resume
    for name in args.problems.split(","):
        problem = PROBLEMS[name]
        entry = results["problems"].setdefault(name, {"modes": {}})
        case, model, offline = model_for(problem, args.models)
        if entry.get("offline_cpu_s") is None:
            entry["offline_cpu_s"] = offline
        planning = planning_problem(name, problem, case, model)
        if "optimum" not in entry:
            entry["optimum"] = optimum(problem, planning, model)
            print(f"{name}: optimum {entry['optimum']}", flush=True)
        for mode in args.modes.split(","):
            planner = make_planner(planning, model, mode, overrides)
            rows = entry["modes"].setdefault(mode, {"first": {}, "anytime": {}})
            if planner is None:
                rows["n/a"] = "no input box: random controls have nothing to draw from"
                continue
            if mode == "learned" and planner.controls is None:
                rows["same_as"] = "default"  # no input box: the default has no random controls
                continue
            from rrtcolearn.planning.termination import TerminationCondition

            planner.solve(TerminationCondition(None, 50), 10_000)  # kernels loaded: not timed
            for seed in range(args.seeds):
                if str(seed) not in rows["first"]:
                    rows["first"][str(seed)] = first_solution(planner, seed, args.limit)
                    print(name, mode, "first", seed, rows["first"][str(seed)], flush=True)
                    _write_json(args.out, results)
            for seed in range(args.anytime_seeds):
                if str(seed) not in rows["anytime"]:
                    rows["anytime"][str(seed)] = anytime(planner, seed, args.anytime)
                    print(name, mode, "anytime", seed, rows["anytime"][str(seed)], flush=True)
                    _write_json(args.out, results)
        _write_json(args.out, results)
    return results


def _overrides(pairs: list[str]) -> dict:
    """``--set`` pairs as {planner setting: value}: an unknown setting or a value that is
    not JSON is refused."""
    from dataclasses import fields

    from rrtcolearn.planning.settings import PlannerSettings

    known = {f.name for f in fields(PlannerSettings)}
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in known:
            raise SystemExit(f"--set {pair!r}: expected SETTING=VALUE with a planner setting "
                             f"({', '.join(sorted(known))})")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError as e:
            raise SystemExit(f"--set {pair!r}: the value is not JSON ({e})") from None
    return out


def _median(values) -> float:
    v = [x for x in values if x is not None and not np.isnan(x)]
    return float(statistics.median(v)) if v else float("nan")


def summarise(entry: dict, mode: str, limit: float) -> dict | str:
    """A mode's figures (medians over seeds), or why there are none."""
    rows = entry["modes"].get(mode, {})
    if "n/a" in rows:
        return "n/a"
    if "same_as" in rows:
        rows = entry["modes"][rows["same_as"]]
    first = list(rows.get("first", {}).values())
    if not first:
        return "not run"
    solved = [r for r in first if r["solved"]]
    opt = entry["optimum"]["value"]
    best = [r["cost"] for r in rows.get("anytime", {}).values() if r["solved"]]
    # an unsolved seed counts as the limit: a median at the limit means most failed
    cpu = statistics.median(r["cpu_s"] if r["solved"] else limit for r in first)
    return {"success": f"{len(solved)}/{len(first)}", "cpu_s": cpu,
            "learned_share": _median(r["learned_share"] for r in solved),
            "extremal_share": _median(r["extremal_share"] for r in solved),
            "first_ratio": _median(r["cost"] / opt for r in solved),
            "first_cost": _median(r["cost"] for r in solved),
            "anytime_ratio": _median(c / opt for c in best),
            "anytime_solved": f"{len(best)}/{len(rows.get('anytime', {}))}",
            "same_as": rows is not entry["modes"].get(mode)}


def table(results: dict) -> str:
    s = results["settings"]
    lines = [f"seeds {s['seeds']} (first solution, {s['limit']:g} s process CPU each), "
             f"{s['anytime_seeds']} (anytime, {s['anytime']:g} s each)", "",
             "| problem | mode | success | CPU median (s) | CPU / default's | learned share "
             "| extremal share | first cost / opt | anytime cost / opt (solved) | optimum | "
             "offline CPU (s) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, entry in results["problems"].items():
        opt = entry["optimum"]
        base = summarise(entry, "default", s["limit"])
        for mode in MODES:
            f = summarise(entry, mode, s["limit"])
            off = entry.get("offline_cpu_s")
            tail = f"{opt['value']:.4g} | {'-' if off is None else f'{off:.0f}'} |"
            if isinstance(f, str):
                lines.append(f"| {name} | {mode} | {f} |" + " |" * 6 + f" {tail}")
                continue
            ratio = f["cpu_s"] / base["cpu_s"] if isinstance(base, dict) else float("nan")
            label = f"{mode} (= default)" if f["same_as"] else mode
            lines.append(
                f"| {name} | {label} | {f['success']} | {f['cpu_s']:.3g} | {ratio:.2f} | "
                f"{f['learned_share']:.2f} | {f['extremal_share']:.2f} | "
                f"{f['first_ratio']:.3g} | {f['anytime_ratio']:.3g} ({f['anytime_solved']}) | "
                f"{tail}")
    lines += ["", "Issue 31's targets (medians as above; success: every seed run):", "",
              "| problem | mode | first cost <= 2x | anytime <= 1.2x | learned >= 60% | "
              "all solved | CPU <= default's |", "|---|---|---|---|---|---|---|"]
    for name, entry in results["problems"].items():
        base = summarise(entry, "default", s["limit"])
        for mode in MODES:
            f = summarise(entry, mode, s["limit"])
            if isinstance(f, str) or not isinstance(base, dict):
                continue
            solved, run = (int(v) for v in f["success"].split("/"))
            checks = (_met(f["first_ratio"] <= 2), _met(f["anytime_ratio"] <= 1.2),
                      _met(f["learned_share"] >= 0.6), _met(solved == run),
                      "-" if mode == "default" else _met(f["cpu_s"] <= base["cpu_s"]))
            label = f"{mode} (= default)" if f["same_as"] else mode
            lines.append(f"| {name} | {label} | " + " | ".join(checks) + " |")
    lines.append("")
    for name, entry in results["problems"].items():
        lines.append(f"- {name}: optimum {entry['optimum']['value']:.6g}: "
                     f"{entry['optimum']['note']}")
    return "\n".join(lines)


def versus(results: dict, base: dict, mode: str = "default") -> str:
    """A side-by-side table of ``mode`` in two results files (e.g. a commit and its parent,
    same models and seeds): success, CPU median to the first solution and its ratio
    (``results`` over ``base``), first cost over the optimum, per problem in both."""
    lines = [f"{mode}: base | this run (CPU ratio: this run / base)", "",
             "| problem | success | CPU median (s) | CPU ratio | first cost / opt |",
             "|---|---|---|---|---|"]
    for name, entry in results["problems"].items():
        old = base["problems"].get(name)
        f = summarise(entry, mode, results["settings"]["limit"])
        b = "not run" if old is None else summarise(old, mode, base["settings"]["limit"])
        if isinstance(f, str) or isinstance(b, str):  # one side not run (or n/a)
            lines.append(f"| {name} | {b if isinstance(b, str) else b['success']} -> "
                         f"{f if isinstance(f, str) else f['success']} | | | |")
            continue
        lines.append(f"| {name} | {b['success']} -> {f['success']} | "
                     f"{b['cpu_s']:.3g} -> {f['cpu_s']:.3g} | {f['cpu_s'] / b['cpu_s']:.2f} | "
                     f"{b['first_ratio']:.3g} -> {f['first_ratio']:.3g} |")
    return "\n".join(lines)


def _met(ok) -> str:
    return "met" if ok else "not met"  # a NaN (nothing solved) is not met


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("/tmp/rrtcolearn_ablation_models"))
    ap.add_argument("--out", type=Path, default=Path("runs/ablation.json"))
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--anytime-seeds", type=int, default=3)
    ap.add_argument("--limit", type=float, default=60.0, help="process CPU s per plan")
    ap.add_argument("--anytime", type=float, default=10.0, help="process CPU s per query")
    ap.add_argument("--problems", default=",".join(PROBLEMS))
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--set", action="append", default=[], metavar="SETTING=VALUE",
                    help="a planner setting in every mode, its value as JSON (e.g. "
                         "parent_cost_to_come=true, goal_parent_tries=0); repeatable")
    ap.add_argument("--table", type=Path, default=None, metavar="JSON",
                    help="print the tables of a results file (docs/ablation.json); run nothing")
    ap.add_argument("--versus", type=Path, default=None, metavar="JSON",
                    help="also print the default mode side by side with this results file's")
    args = ap.parse_args(argv)
    results = json.loads(args.table.read_text()) if args.table else run(args)
    print(table(results))
    if args.versus:
        print("\n" + versus(results, json.loads(args.versus.read_text())))
    return results


if __name__ == "__main__":
    main()

"""The experiment: epochs of freshly generated and cleaned data, planning runs on each, and
the peers on the same problems, seeds and limits.

Layout of the experiment directory::

    epoch-00/<dataset>/        run directories of RRT-CoLearn's data and models per epoch
    runs.csv                   one row per planning run
    ompl/<problem>.log         the runs in OMPL's benchmark log format, one file per problem
    benchmark.db               the same in OMPL's SQLite schema (Planner Arena opens it)
    offline.csv                offline CPU time per epoch and dataset
    d_grid.csv                 the grid search over the cleaning radius d
    report.md, *.png           the report and its figures
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rrtcolearn import pipeline
from rrtcolearn.baselines.base import path_metrics
from rrtcolearn.config import Config, ProblemSpec
from rrtcolearn.data.store import atomic_write_text
from rrtcolearn.parallel import ExecutionSettings, map_tasks
from rrtcolearn.planning.problem import PlanningProblem

ROW_FIELDS = ["epoch", "seed", "problem", "planner", "solved", "status", "time", "wall_s",
              "iterations", "nodes", "path_cost", "path_duration", "max_abs_u",
              "final_goal_distance", "u_max", "time_weight", "goal_tolerance"]
START = [-math.pi, 0.0]
GOAL = [0.0, 0.0]
QUICK = {"epochs": 2, "runs_per_epoch": 30, "direct_runs_per_epoch": 3, "direct_pairs": 400,
         "d_grid": [0.02, 0.05, 0.1], "d_grid_plans": 10}


def dataset_name(problem: ProblemSpec) -> str:
    """Problems with the same torque limit and time weight share a dataset."""
    u = "none" if problem.u_max is None else f"{problem.u_max:g}"
    return f"umax-{u}_w-{problem.time_weight:g}"


def epoch_seed(seed: int, epoch: int) -> int:
    """Seed of an epoch's dataset, independent of every other epoch's."""
    return int(np.random.SeedSequence(seed, spawn_key=(100, epoch)).generate_state(1)[0])


def run_seed(epoch: int, run: int) -> int:
    return 100_000 * epoch + run


def epoch_config(config: Config, problem: ProblemSpec, epoch: int) -> Config:
    system = config.system.model_copy(update={"u_max": problem.u_max,
                                              "time_weight": problem.time_weight})
    return config.model_copy(update={"system": system, "seed": epoch_seed(config.seed, epoch)})


@dataclass(frozen=True)
class RunTask:
    """A batch of planning runs of one planner on one problem in one epoch."""

    exp_dir: str
    config: Config
    epoch: int
    problem: ProblemSpec
    planner: str
    seeds: tuple[int, ...]


_MODELS: dict[str, pipeline.FittedModel] = {}


def _model(run_dir: Path) -> pipeline.FittedModel:
    key = str(run_dir)
    if key not in _MODELS:
        if len(_MODELS) > 4:  # bounded: a worker holds at most a few epochs' models
            _MODELS.pop(next(iter(_MODELS)))
        _MODELS[key] = pipeline.load_model(run_dir)
    return _MODELS[key]


def _rrtcolearn_row(task: RunTask, seed: int) -> dict:
    pr = task.problem
    model = _model(Path(task.exp_dir) / f"epoch-{task.epoch:02d}" / dataset_name(pr))
    plan = pipeline.plan(model, START, GOAL, pr.goal_tolerance, seed,
                         time_limit=task.config.experiment.time_limit, u_max=pr.u_max,
                         max_iterations=task.config.experiment.max_iterations, obstacles=[])
    check = resimulate_plan(model, plan)
    return {"solved": plan.solved and check["reaches_goal"], "status": plan.status,
            "time": plan.planning_cpu_s, "wall_s": plan.planning_time_s,
            "iterations": plan.iterations, "nodes": plan.nodes, **check}


def resimulate_plan(model: pipeline.FittedModel, plan) -> dict:
    """Re-integrate the path edge by edge from the start (not from the stored edge ends)."""
    from rrtcolearn.evaluate import edge_trajectory

    x = plan.start.copy()
    cost = duration = max_u = 0.0
    for e in plan.edges():
        t = edge_trajectory(model.system, {**e, "from": x}, plan.time_weight, plan.dt)
        max_u = max(max_u, float(np.abs(t.inputs).max()))
        cost += t.cost
        duration += (len(t.states) - 1) * plan.dt
        x = t.states[-1]
    gap = float(np.linalg.norm(x - plan.goal))
    return {"path_cost": cost, "path_duration": duration, "max_abs_u": max_u,
            "final_goal_distance": gap,
            "reaches_goal": bool(plan.path_nodes) and gap <= plan.goal_tolerance + 1e-9}


def _baseline_row(task: RunTask, seed: int) -> dict:
    pr = task.problem
    system = pipeline.build_system(task.config)
    limit = task.config.experiment.time_limit
    if task.planner == "random-rrt":
        from rrtcolearn.baselines.random_rrt import solve_random_rrt

        problem = PlanningProblem.create(system, START, GOAL, pr.goal_tolerance, u_max=pr.u_max)
        res = solve_random_rrt(problem, seed=seed, time_limit=limit,
                               max_iterations=task.config.experiment.max_iterations)
    elif task.planner.startswith("ompl-"):
        from rrtcolearn.baselines.ompl_planners import run_ompl_isolated

        res = run_ompl_isolated(task.planner.removeprefix("ompl-"), START, GOAL,
                                pr.goal_tolerance, u_max=pr.u_max, time_limit=limit,
                                seed=seed, time_weight=pr.time_weight)
    elif task.planner == "direct":
        from rrtcolearn.baselines.direct import solve_direct_rrt

        model = _direct_model(Path(task.exp_dir), task.epoch, pr, task.config)
        res = solve_direct_rrt(model, START, GOAL, pr.goal_tolerance, seed=seed,
                               time_limit=limit, u_max=pr.u_max, time_weight=pr.time_weight)
    else:
        raise ValueError(f"unknown planner {task.planner!r}")
    m = path_metrics(system, res.path, 0.01, pr.time_weight, np.array(GOAL), pr.goal_tolerance)
    return {"solved": res.solved and m["reaches_goal"], "status": res.status,
            "time": res.cpu_s, "wall_s": res.wall_s, "iterations": res.iterations,
            "nodes": res.nodes, **m}


_DIRECT: dict[str, object] = {}


def _direct_model(exp_dir: Path, epoch: int, pr: ProblemSpec, config: Config):
    from rrtcolearn.baselines.direct import fit_direct_model, load_direct_dataset

    path = exp_dir / f"epoch-{epoch:02d}" / f"direct_{dataset_name(pr)}.npz"
    if str(path) not in _DIRECT:
        _DIRECT.clear()
        _DIRECT[str(path)] = fit_direct_model(load_direct_dataset(path))
    return _DIRECT[str(path)]


def run_task(task: RunTask) -> list[dict]:
    """Rows of one task (top-level so that worker processes can import it)."""
    rows = []
    for seed in task.seeds:
        try:
            row = (_rrtcolearn_row(task, seed) if task.planner == "rrtcolearn"
                   else _baseline_row(task, seed))
        except Exception as exc:  # a crashing run is data, not the end of the experiment
            row = {"solved": False, "status": "crash", "time": float("nan"),
                   "error": f"{type(exc).__name__}: {exc}"}
        pr = task.problem
        row.pop("reaches_goal", None)
        rows.append({"epoch": task.epoch, "seed": seed, "problem": pr.name,
                     "planner": task.planner, "u_max": pr.u_max,
                     "time_weight": pr.time_weight, "goal_tolerance": pr.goal_tolerance, **row})
    return rows


def available_planners(names: list[str]) -> tuple[list[str], dict[str, str]]:
    """Planners that can run here, and why the others cannot."""
    ok, skipped = [], {}
    for name in names:
        if name.startswith("ompl-"):
            try:
                from rrtcolearn.baselines.ompl_planners import ompl_available
                if not ompl_available():
                    raise ImportError
            except ImportError:
                skipped[name] = "the ompl package is not installed (extra 'ompl')"
                continue
        if name == "direct":
            try:
                from rrtcolearn.baselines.direct import casadi_available
                if not casadi_available():
                    raise ImportError
            except ImportError:
                skipped[name] = "the casadi package is not installed (extra 'direct')"
                continue
        ok.append(name)
    return ok, skipped


def applies(planner: str, problem: ProblemSpec) -> bool:
    """OMPL's control planners need bounded controls: not the unbounded problem."""
    return not (planner.startswith("ompl-") and problem.u_max is None)


def make_tasks(exp_dir: Path, config: Config, planners: list[str]) -> list[RunTask]:
    e = config.experiment
    tasks = []
    for epoch in range(e.epochs):
        for pr in e.problems:
            for planner in planners:
                if not applies(planner, pr):
                    continue
                if planner == "rrtcolearn":
                    n = e.runs_per_epoch
                elif planner == "direct":
                    n = min(e.direct_runs_per_epoch, e.runs_per_epoch)
                else:
                    n = e.peer_runs_per_epoch or e.runs_per_epoch
                seeds = [run_seed(epoch, r) for r in range(n)]
                for i in range(0, n, e.runs_per_task):
                    tasks.append(RunTask(str(exp_dir), config, epoch, pr, planner,
                                         tuple(seeds[i: i + e.runs_per_task])))
    return tasks


@dataclass(frozen=True)
class OfflineTask:
    """Generate, clean and fit one dataset of one epoch (and the direct method's, if run)."""

    exp_dir: str
    config: Config
    epoch: int
    problem: ProblemSpec
    direct: bool


def run_offline_task(task: OfflineTask) -> list[dict]:
    """Offline work of one dataset; CPU times are this worker's own process time."""
    import time

    exp_dir, pr, epoch = Path(task.exp_dir), task.problem, task.epoch
    cfg = epoch_config(task.config, pr, epoch)
    name = dataset_name(pr)
    run_dir = exp_dir / f"epoch-{epoch:02d}" / name
    t0 = time.process_time()
    _, gen = pipeline.generate(cfg, run_dir)
    t1 = time.process_time()
    cleaned, _ = pipeline.clean(cfg, run_dir)
    t2 = time.process_time()
    pipeline.fit(cfg, run_dir)
    t3 = time.process_time()
    rows = [{"epoch": epoch, "dataset": name, "method": "indirect",
             "raw_points": gen.points, "kept_points": len(cleaned),
             "generate_cpu_s": t1 - t0, "clean_cpu_s": t2 - t1, "fit_cpu_s": t3 - t2,
             "offline_cpu_s": t3 - t0, "simulations": gen.simulations}]
    if task.direct:
        rows.append(_direct_offline(exp_dir, cfg, pr, epoch))
    return rows


def offline_phase(exp_dir: Path, config: Config, planners: list[str],
                  settings: ExecutionSettings | None,
                  progress: Callable[[str], None] | None = None) -> list[dict]:
    """Each epoch's datasets, one task per (epoch, dataset), run on the execution backend."""
    tasks = []
    for epoch in range(config.experiment.epochs):
        seen = set()
        for pr in config.experiment.problems:
            if dataset_name(pr) not in seen:
                seen.add(dataset_name(pr))
                tasks.append(OfflineTask(str(exp_dir), config, epoch, pr, "direct" in planners))
    results = map_tasks(run_offline_task, tasks, settings,
                        None if progress is None else lambda i, r: progress(
                            f"epoch {tasks[i].epoch}: {dataset_name(tasks[i].problem)}"))
    return [row for rows in results for row in rows]


def _direct_offline(exp_dir: Path, cfg: Config, pr: ProblemSpec, epoch: int) -> dict:
    import time

    from rrtcolearn.baselines.direct import generate_direct_dataset, save_direct_dataset

    path = exp_dir / f"epoch-{epoch:02d}" / f"direct_{dataset_name(pr)}.npz"
    t0 = time.process_time()
    data, stats = generate_direct_dataset(cfg.experiment.direct_pairs, cfg.seed,
                                          time_weight=pr.time_weight, u_max=pr.u_max)
    cpu = time.process_time() - t0
    save_direct_dataset(path, data, stats)
    return {"epoch": epoch, "dataset": dataset_name(pr), "method": "direct",
            "raw_points": int(stats.get("solved", 0)), "kept_points": int(stats.get("solved", 0)),
            "generate_cpu_s": cpu, "clean_cpu_s": 0.0, "fit_cpu_s": 0.0, "offline_cpu_s": cpu,
            "simulations": cfg.experiment.direct_pairs,
            "cpu_s_per_solve": stats.get("cpu_s_per_solve")}


def write_csv(path: Path, rows: list[dict], fields: list[str]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in fields})
    atomic_write_text(path, buf.getvalue())


def run_experiment(exp_dir: str | Path, config: Config, *,
                   settings: ExecutionSettings | None = None,
                   progress: Callable[[str, int, int], None] | None = None) -> dict:
    """The whole experiment; returns a summary (also written as summary.json)."""
    from rrtcolearn.experiment.report import write_outputs

    exp_dir = Path(exp_dir)
    planners, skipped = available_planners(config.experiment.planners)
    pipeline.save_config(config, exp_dir)
    offline = offline_phase(exp_dir, config, planners, settings,
                            None if progress is None else lambda s: progress(s, 0, 0))
    tasks = make_tasks(exp_dir, config, planners)
    done = [0]

    def finished(i: int, rows: list[dict]) -> None:
        done[0] += 1
        if progress is not None:
            progress("planning runs", done[0], len(tasks))

    results = map_tasks(run_task, tasks, settings, finished)
    rows = [r for batch in results for r in batch]
    rows.sort(key=lambda r: (r["problem"], r["planner"], r["epoch"], r["seed"]))
    return write_outputs(exp_dir, config, rows, offline, skipped)


def rows_digest(rows: list[dict]) -> str:
    """Digest of the results without timing columns: equal across worker counts."""
    import hashlib

    keep = [{k: v for k, v in r.items() if k not in ("time", "wall_s")} for r in rows]
    return hashlib.sha256(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()



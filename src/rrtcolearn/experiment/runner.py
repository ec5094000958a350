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

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rrtcolearn import pipeline, planners
from rrtcolearn.config import Config, ProblemSpec
from rrtcolearn.evaluate import replay
from rrtcolearn.experiment.layout import (
    dataset_name,
    epoch_config,
    experiment_problems,
    planning_problem,
    run_seed,
)
from rrtcolearn.experiment.report import write_outputs
from rrtcolearn.parallel import ExecutionSettings, map_tasks
from rrtcolearn.planning.termination import TerminationCondition

# the peers' failed runs take the whole limit: 10 runs each keep the pendulum's --quick short
QUICK = {"epochs": 2, "runs_per_epoch": 30, "peer_runs_per_epoch": 10,
         "direct_runs_per_epoch": 3, "direct_pairs": 400, "d_grid": [0.02, 0.05, 0.1],
         "d_grid_plans": 10}
# another system's offline phase alone takes minutes (cart-pole, acrobot: ~3 min CPU)
QUICK_OTHER = {"epochs": 1, "runs_per_epoch": 3, "runs_per_task": 1, "d_grid": [],
               "time_limit": 120.0, "cpu_time_limit": 30.0}


def quick_settings(system: str) -> dict:
    """The ``--quick`` experiment settings for ``system`` (a few minutes each)."""
    return QUICK if system == "pendulum" else QUICK_OTHER


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


def _model(task: RunTask) -> pipeline.FittedModel:
    key = str(Path(task.exp_dir) / f"epoch-{task.epoch:02d}" / dataset_name(task.problem))
    if key not in _MODELS:
        if len(_MODELS) > 4:  # bounded: a worker holds at most a few epochs' models
            _MODELS.pop(next(iter(_MODELS)))
        _MODELS[key] = pipeline.load_model(key)
    return _MODELS[key]


_DIRECT: dict[str, object] = {}


def _direct_model(task: RunTask):
    from rrtcolearn.baselines.direct import fit_direct_model, load_direct_dataset

    path = Path(task.exp_dir) / f"epoch-{task.epoch:02d}" / \
        f"direct_{dataset_name(task.problem)}.npz"
    if str(path) not in _DIRECT:
        _DIRECT.clear()
        _DIRECT[str(path)] = fit_direct_model(load_direct_dataset(path))
    return _DIRECT[str(path)]


# the learned planners' fitted models, made by the offline phase; every other planner is a
# random-control peer and gets the experiment's input bound for unbounded problems
_FITTED = {"rrtcolearn": _model, "direct": _direct_model}


def make_planner(task: RunTask, fitted: bool = True) -> planners.Planner:
    """The task's planner (`rrtcolearn.planners.make`) with the problem's time weight; with
    ``fitted`` a learned planner gets its epoch's model."""
    params = {"time_weight": task.problem.time_weight}
    load = _FITTED.get(task.planner)
    if load is None:
        params["u_max"] = task.config.experiment.peer_u_max
    elif fitted:
        params["model"] = load(task)
    return planners.make(task.planner, **params)


def run_row(task: RunTask, seed: int) -> dict:
    """One planning run: the plan, re-simulated and checked against the problem (`replay`)."""
    e = task.config.experiment
    problem = planning_problem(task.config, task.problem)
    limit = TerminationCondition(e.time_limit, e.max_iterations, e.cpu_time_limit)
    plan = make_planner(task).solve(problem, limit, seed)
    check = replay(problem, plan)
    return {"solved": plan.solved and check["reaches_goal"], "status": plan.status,
            "time": plan.planning_cpu_s, "wall_s": plan.planning_time_s,
            "iterations": plan.iterations, "nodes": plan.nodes,
            **{k: check[k] for k in ("path_cost", "path_duration", "max_abs_u",
                                     "final_goal_distance")}}


def run_task(task: RunTask) -> list[dict]:
    """Rows of one task (top-level so that worker processes can import it)."""
    rows = []
    for seed in task.seeds:
        try:
            row = run_row(task, seed)
        except Exception as exc:  # a crashing run is data, not the end of the experiment
            row = {"solved": False, "status": "crash", "time": float("nan"),
                   "error": f"{type(exc).__name__}: {exc}"}
        pr = task.problem
        rows.append({"epoch": task.epoch, "seed": seed, "problem": pr.name,
                     "planner": task.planner, "u_max": pr.u_max,
                     "time_weight": pr.time_weight, "goal_tolerance": pr.goal_tolerance, **row})
    return rows


def make_tasks(exp_dir: Path, config: Config) -> tuple[list[RunTask], dict[str, str]]:
    """The runs of every configured planner on every problem it supports, and why the
    others are not run (``"planner on problem": reason``)."""
    e = config.experiment
    tasks, skipped = [], {}
    for pr in experiment_problems(config):
        problem = planning_problem(config, pr)
        for planner in e.planners:
            probe = RunTask(str(exp_dir), config, 0, pr, planner, ())
            reason = make_planner(probe, fitted=False).supports(problem)
            if reason is not None:
                if planner not in _FITTED and config.experiment.peer_u_max is None and \
                        problem.u_max is None and not problem.system.input_limited:
                    # no input bound: the setting that gives the random-control peers one
                    reason += "; in an experiment: experiment.peer_u_max"
                skipped[f"{planner} on {pr.name}"] = reason
                continue
            if planner == "rrtcolearn":
                n = e.runs_per_epoch
            elif planner == "direct":
                n = min(e.direct_runs_per_epoch, e.runs_per_epoch)
            else:
                n = e.peer_runs_per_epoch or e.runs_per_epoch
            for epoch in range(e.epochs):
                seeds = [run_seed(epoch, r) for r in range(n)]
                for i in range(0, n, e.runs_per_task):
                    tasks.append(RunTask(str(exp_dir), config, epoch, pr, planner,
                                         tuple(seeds[i: i + e.runs_per_task])))
    tasks.sort(key=lambda t: t.epoch)
    return tasks, skipped


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


def offline_phase(exp_dir: Path, config: Config, direct: bool,
                  settings: ExecutionSettings | None,
                  progress: Callable[[str], None] | None = None) -> list[dict]:
    """Each epoch's datasets, one task per (epoch, dataset), run on the execution backend."""
    tasks = []
    for epoch in range(config.experiment.epochs):
        seen = set()
        for pr in experiment_problems(config):
            if dataset_name(pr) not in seen:
                seen.add(dataset_name(pr))
                tasks.append(OfflineTask(str(exp_dir), config, epoch, pr, direct))
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


def run_experiment(exp_dir: str | Path, config: Config, *,
                   settings: ExecutionSettings | None = None,
                   progress: Callable[[str, int, int], None] | None = None) -> dict:
    """The whole experiment; returns a summary (also written as summary.json)."""
    exp_dir = Path(exp_dir)
    tasks, skipped = make_tasks(exp_dir, config)
    pipeline.save_config(config, exp_dir)
    direct = any(t.planner == "direct" for t in tasks)
    offline = offline_phase(exp_dir, config, direct, settings,
                            None if progress is None else lambda s: progress(s, 0, 0))
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



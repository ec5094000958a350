"""The commands that run the pipeline: generate (Alg. 2), clean (Alg. 3), fit, run (all
three and a plan) and experiment."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from rrtcolearn.cli.common import (
    BudgetOpt,
    ConfigOpt,
    DaskLocalOpt,
    DynobenchOpt,
    ObstacleOpt,
    OutOpt,
    SchedulerOpt,
    SeedOpt,
    SetOpt,
    SystemOpt,
    UMaxOpt,
    WorkersOpt,
    command_config,
    guard,
    out_console,
    print_summary,
    progress_bar,
    run_directory,
    run_name,
)
from rrtcolearn.cli.planning import (
    plan_summary,
    read_dynobench,
    warn_unresolved,
    write_dynobench,
    write_plan,
)

if TYPE_CHECKING:
    from rrtcolearn.config import Config
    from rrtcolearn.pipeline import FittedModel


def _do_generate(cfg: Config, run_dir: Path, settings=None) -> dict:
    from rrtcolearn import pipeline

    # the settings left to the library first (a pilot of simulations for the cost bound)
    cfg, derive_cpu = pipeline.timed(pipeline.resolve, cfg)
    with progress_bar() as bar:
        task = bar.add_task("generate (Alg. 2)", total=cfg.generate.n_simulations)
        (_, stats), cpu = pipeline.timed(pipeline.generate, cfg, run_dir,
                                         progress=lambda k: bar.advance(task, k),
                                         settings=settings)
    if settings is not None and settings.backend != "serial":
        cpu += stats.worker_cpu_s  # the workers' own CPU, which this process does not see
    return {"simulations": stats.simulations, "invalid_costates": stats.invalid_costates,
            "raw_points": stats.points, "nonfinite_simulations": stats.nonfinite_simulations,
            "resumed_chunks": stats.resumed_chunks,
            "generate_cpu_s": round(cpu + derive_cpu, 3)}


def _print_derived(cfg: Config) -> None:
    """What the library derived for this run, and why (also in config.toml)."""
    if cfg.derived:
        from rich.table import Table

        table = Table(title="derived settings (set any of them to override)",
                      show_header=False)
        for key, line in sorted(cfg.derived.items()):
            table.add_row(key, line)
        out_console.print(table)


def _do_clean(cfg: Config, run_dir: Path) -> dict:
    from rrtcolearn import pipeline

    with progress_bar() as bar:
        task = bar.add_task("clean (Alg. 3): removed", total=None)
        (cleaned, result), cpu = pipeline.timed(
            pipeline.clean, cfg, run_dir,
            progress=lambda draws, removed: bar.update(task, completed=removed))
    return {"kept_points": len(cleaned), "removed_points": len(result.removed),
            "clean_draws": result.draws, "clean_cpu_s": round(cpu, 3)}


def _do_fit(cfg: Config, run_dir: Path) -> tuple[FittedModel, dict]:
    from rrtcolearn import pipeline

    model, cpu = pipeline.timed(pipeline.fit, cfg, run_dir)
    return model, {"fit_cpu_s": round(cpu, 3)}


def generate(config: ConfigOpt = None, seed: SeedOpt = None, out: OutOpt = None,
             set_: SetOpt = None, u_max: UMaxOpt = None, workers: WorkersOpt = None,
             scheduler: SchedulerOpt = None, dask_local: DaskLocalOpt = None,
             system: SystemOpt = None, offline_budget: BudgetOpt = None) -> None:
    """Generate a dataset of optimal trajectory segments (Alg. 2); resumable."""
    def body():
        from rrtcolearn import pipeline
        from rrtcolearn.parallel import ExecutionSettings

        settings = ExecutionSettings.from_options(workers, scheduler, dask_local)
        cfg = command_config(config, seed, set_, u_max=u_max, system=system,
                              offline_budget=offline_budget)
        run_dir = run_directory(out, cfg)
        figures = _do_generate(cfg, run_dir, settings)
        _print_derived(pipeline.read_run_config(run_dir))
        print_summary(f"generate -> {run_dir}", figures)
    guard(body)


def clean(config: ConfigOpt = None, seed: SeedOpt = None, out: OutOpt = None,
          system: SystemOpt = None,
          set_: SetOpt = None) -> None:
    """Remove the local-optimum bias from a run's dataset (Alg. 3)."""
    def body():
        cfg = command_config(config, seed, set_, out, system=system)
        run_dir = run_directory(out, cfg)
        print_summary(f"clean -> {run_dir}", _do_clean(cfg, run_dir))
    guard(body)


def fit(config: ConfigOpt = None, seed: SeedOpt = None, out: OutOpt = None,
        system: SystemOpt = None,
        set_: SetOpt = None) -> None:
    """Fit the cost-to-go, steering and validity learners on a run's cleaned dataset."""
    def body():
        cfg = command_config(config, seed, set_, out, system=system)
        run_dir = run_directory(out, cfg)
        fitted, figures = _do_fit(cfg, run_dir)
        _print_derived(fitted.config)
        print_summary(f"fit -> {run_dir}", figures)
    guard(body)


def run(config: ConfigOpt = None, seed: SeedOpt = None, out: OutOpt = None,
        set_: SetOpt = None, u_max: UMaxOpt = None, obstacle: ObstacleOpt = None,
        workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
        dask_local: DaskLocalOpt = None, system: SystemOpt = None,
        offline_budget: BudgetOpt = None, dynobench: DynobenchOpt = None) -> None:
    """The whole pipeline: generate, clean, fit, and plan the configured query (with
    --dynobench: a dynobench problem's robot and query)."""
    def body():
        from rrtcolearn import pipeline
        from rrtcolearn.data.store import write_json
        from rrtcolearn.parallel import ExecutionSettings

        settings = ExecutionSettings.from_options(workers, scheduler, dask_local)
        read, posed = read_dynobench(dynobench)
        cfg = command_config(config, seed, set_, u_max=u_max, obstacles=obstacle, system=system,
                              offline_budget=offline_budget, posed=posed)
        run_dir = run_directory(out, cfg)
        # the query checked before the offline steps (minutes), not after them
        built = pipeline.system_from_config(cfg)
        start, goal = pipeline.query_states(cfg, built)
        pipeline.make_problem(built, cfg, start, goal, cfg.plan.goal_tolerance)
        t0 = time.perf_counter()
        figures = {"run_dir": str(run_dir)}
        figures |= _do_generate(cfg, run_dir, settings)
        figures |= _do_clean(cfg, run_dir)
        fitted, fit_fig = _do_fit(cfg, run_dir)
        figures |= fit_fig
        figures["offline_cpu_s"] = round(figures["generate_cpu_s"] + figures["clean_cpu_s"]
                                         + figures["fit_cpu_s"], 3)
        p = pipeline.plan(fitted, start, goal, cfg.plan.goal_tolerance,
                          cfg.seed, config=fitted.config, time_limit=cfg.plan.time_limit,
                          max_iterations=cfg.plan.max_iterations)
        write_plan(p, run_dir / "plan.json", fitted.system.state_names)
        write_dynobench(read, p, fitted.system, run_dir / "plan.json")
        figures |= plan_summary(p)
        figures["wall_s"] = round(time.perf_counter() - t0, 2)
        figures["derived"] = dict(sorted(fitted.config.derived.items()))
        write_json(run_dir / "summary.json", figures)
        _print_derived(fitted.config)
        print_summary(f"run -> {run_dir}", {k: v for k, v in figures.items()
                                             if k != "derived"})
        warn_unresolved(p)
    guard(body)


def experiment(
    config: ConfigOpt = None, seed: SeedOpt = None,
    out: Annotated[Path | None, typer.Option("--out", help="experiment directory "
                                             "(default runs/<name>-experiment)")] = None,
    set_: SetOpt = None,
    quick: Annotated[bool, typer.Option(
        "--quick", help="a few minutes: 2 epochs x 30 runs (peers 10) for the pendulum, 1 x 3 "
        "runs for another system")] = False,
    workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    dask_local: DaskLocalOpt = None, system: SystemOpt = None,
) -> None:
    """RRT-CoLearn beside every peer that supports the problems (the paper's experiment,
    10 epochs x 300 runs, for the pendulum; another system's standard query); writes a
    report, runs.csv, OMPL logs and a Planner Arena database."""
    def body():
        from rrtcolearn import pipeline
        from rrtcolearn.experiment.runner import quick_settings, run_experiment
        from rrtcolearn.parallel import ExecutionSettings

        settings = ExecutionSettings.from_options(workers, scheduler, dask_local)
        cfg = command_config(config, seed, set_, system=system)
        if quick:
            overrides = [f"experiment.{k}={v!r}"
                         for k, v in quick_settings(cfg.system.name).items()]
            cfg = command_config(config, seed, overrides + list(set_ or []), system=system)
        pipeline.system_from_config(cfg)  # an unknown system is reported before any work
        exp_dir = out if out is not None else Path("runs") / f"{run_name(cfg)}-experiment"
        with progress_bar() as bar:
            task = bar.add_task("offline: generate, clean, fit", total=None)

            def progress(what: str, done: int, total: int) -> None:
                if total:
                    bar.update(task, description=what, completed=done, total=total)
                else:
                    bar.update(task, description=f"offline: {what}")

            summary = run_experiment(exp_dir, cfg, settings=settings, progress=progress)
        main = summary["planners"].get(summary["main_problem"], {})
        figures = {"experiment_dir": str(exp_dir), "report": str(exp_dir / "report.md")}
        for name, st in main.items():
            figures[f"{name} success / median ms"] = (
                f"{st['success_rate']:.2f} / {1e3 * (st['time_median'] or 0):.1f}")
        if summary["skipped_planners"]:
            figures["skipped"] = "; ".join(summary["skipped_planners"])
        print_summary("experiment", figures)
    guard(body)

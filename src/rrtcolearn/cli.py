"""Command-line interface: parse, validate, call the library, print.

Only typer, rich and the standard library are imported at start-up: the library (numpy,
numba, scipy, pydantic, sympy, matplotlib) is imported by the command that needs it, so
``--help`` and a single ``plan`` pay only for what they use.
"""

from __future__ import annotations

import gc
import os
import re
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperGroup

try:  # recent typer versions vendor click; older ones use it directly
    from typer._click import exceptions as _click_errors
except ImportError:  # pragma: no cover
    from click import exceptions as _click_errors

from rrtcolearn.errors import ArtefactError, ConfigError, RRTCoLearnError

if TYPE_CHECKING:
    from rich.progress import Progress

    from rrtcolearn.config import Config
    from rrtcolearn.pipeline import FittedModel


class _OneLineErrors(TyperGroup):
    """Usage errors (a malformed option value, an unknown option) as one line, exit 2."""

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except _click_errors.NoArgsIsHelpError as exc:
            print(exc.ctx.get_help() if exc.ctx else str(exc))
            sys.exit(0)
        except _click_errors.ClickException as exc:
            console.print(f"[bold red]error:[/] {_printable(exc.format_message())}",
                          highlight=False, soft_wrap=True)
            sys.exit(exc.exit_code)
        except typer.Abort:
            console.print(_INTERRUPTED)
            sys.exit(130)
        sys.exit(rv if isinstance(rv, int) else 0)


app = typer.Typer(
    cls=_OneLineErrors,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="RRT-CoLearn: kinodynamic planning with learned cost-to-go and learned steering.",
)
console = Console(stderr=True)
out_console = Console()
_state = {"debug": False}

ConfigOpt = Annotated[Path | None, typer.Option("--config", "-c", help="TOML config file")]
SeedOpt = Annotated[int | None, typer.Option("--seed", help="random seed (overrides config)")]
OutOpt = Annotated[Path | None, typer.Option("--out", help="run directory (default runs/<name>)")]
SetOpt = Annotated[list[str] | None, typer.Option("--set", help="override: section.key=value")]
SystemOpt = Annotated[str | None, typer.Option(
    "--system", help="registered system name, or module:attribute of your own")]
UMaxOpt = Annotated[float | None, typer.Option("--u-max", help="torque limit |u| <= U_MAX")]
BudgetOpt = Annotated[float | None, typer.Option(
    "--offline-budget", help="choose the number of simulations by a convergence test on "
    "held-out J error within this many CPU seconds (generate.offline_budget)")]
WorkersOpt = Annotated[int | None, typer.Option(
    "--workers", help="local worker processes (results do not depend on it)")]
SchedulerOpt = Annotated[str | None, typer.Option(
    "--scheduler", help="Dask scheduler address, e.g. tcp://host:8786")]
DaskLocalOpt = Annotated[int | None, typer.Option(
    "--dask-local", help="start a Dask LocalCluster with this many workers")]
ObstacleOpt = Annotated[list[str] | None, typer.Option(
    "--obstacle", help="forbidden region: box:lo1,lo2,hi1,hi2 or halfplane:n1,n2,offset in "
    "state space; rect:cx,cy,w,h[,angle], disc:cx,cy,r, polygon:x1,y1,... or sphere:cx,cy,cz,r "
    "in the workspace, for plan.body")]

DynobenchOpt = Annotated[str | None, typer.Option(
    "--dynobench", help="a dynobench problem (the optional extra): <robot>/<environment> as "
    "the package ships it, e.g. unicycle1_v0/parallelpark_0, or an environment file; poses "
    "its robot's system, query, body and obstacles, and writes the plan also in dynobench's "
    "result format (plan.dynobench.yaml)")]


def _dynobench(problem: str | None) -> tuple[object, dict]:
    """The dynobench problem named on the command line and the config sections posing it
    (None, {} without one)."""
    if problem is None:
        return None, {}
    from rrtcolearn import dynobench

    read = dynobench.read_problem(problem)
    return read, dynobench.config_options(read)


def _write_dynobench(read, p, system, plan_path: Path) -> None:
    """The solved plan beside ``plan_path`` in dynobench's result format."""
    if read is None or not p.solved:
        return
    from rrtcolearn import dynobench
    from rrtcolearn.evaluate import sample_path

    dynobench.write_result(plan_path.with_suffix(".dynobench.yaml"),
                           dynobench.result(read, sample_path(system, p)))


def _printable(message: str) -> str:
    """The message with control characters and rich markup escaped: one literal line."""
    return escape("".join(c if c.isprintable() else repr(c)[1:-1] for c in message))


def _fail(message: str, code: int) -> None:
    console.print(f"[bold red]error:[/] {_printable(message)}", highlight=False,
                  soft_wrap=True, markup=True)
    raise typer.Exit(code)


_INTERRUPTED = "interrupted; finished files are complete, unfinished ones were not written"


def _caused_by_interrupt(exc: BaseException) -> bool:
    """True when a signal landed inside compiled code and surfaced wrapped in another error."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (Interrupted, KeyboardInterrupt)):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _guard(fn):
    """Run a command body; user errors become one line and a non-zero exit, never a traceback."""
    try:
        return fn()
    except typer.Exit:
        raise
    except RRTCoLearnError as exc:
        if _state["debug"]:
            raise
        _fail(str(exc), exc.exit_code)
    except (Interrupted, KeyboardInterrupt):
        console.print(_INTERRUPTED)
        raise typer.Exit(130) from None
    except MemoryError:
        _fail("out of memory; reduce generate.n_simulations", 3)
    except OSError as exc:  # unwritable directory, disk full, ...: the environment, not a bug
        if _caused_by_interrupt(exc):
            console.print(_INTERRUPTED)
            raise typer.Exit(130) from None
        _fail(f"cannot read or write a file: {exc}", 3)
    except Exception as exc:  # an internal error: still one line unless --debug
        if _caused_by_interrupt(exc):
            console.print(_INTERRUPTED)
            raise typer.Exit(130) from None
        if _state["debug"]:
            raise
        _fail(f"internal error: {type(exc).__name__}: {exc} (rerun with --debug for details)", 1)


def _config(config: Path | None, seed: int | None, overrides: list[str] | None,
            run_dir: Path | None = None, u_max: float | None = None,
            obstacles: list[str] | None = None, system: str | None = None,
            offline_budget: float | None = None, posed: dict | None = None) -> Config:
    from rrtcolearn.config import add_obstacles, load_config, read_toml

    base = {}
    if run_dir is not None and (run_dir / "config.toml").is_file():
        base = read_toml(run_dir / "config.toml")
    options = _options({("system", "name"): system, ("system", "u_max"): u_max,
                        ("generate", "offline_budget"): offline_budget})
    for section, values in (posed or {}).items():  # a dynobench problem's, under the options
        options[section] = {**values, **options.get(section, {})}
    cfg = add_obstacles(load_config(config, overrides, base=base, options=options),
                        list(obstacles or []))
    if seed is not None:
        if seed < 0:
            raise ConfigError("--seed must be a non-negative integer")
        cfg = cfg.model_copy(update={"seed": seed})
    return cfg


def _options(given: dict[tuple[str, str], object]) -> dict[str, dict[str, object]]:
    """The typed command-line options that were given, nested by section as in a file."""
    nested: dict[str, dict[str, object]] = {}
    for (section, key), value in given.items():
        if value is not None:
            nested.setdefault(section, {})[key] = value
    return nested


def _run_name(cfg: Config) -> str:
    """The run's name: the configured one, or for another system than the pendulum under the
    default name, the system's (so a user system's run does not land in the pendulum's)."""
    from rrtcolearn.config import Config

    if cfg.name == Config().name and cfg.system.name != Config().system.name:
        return re.sub(r"[^A-Za-z0-9._-]", "-", cfg.system.name).lstrip("-._") or cfg.name
    return cfg.name


def _run_dir(out: Path | None, cfg: Config) -> Path:
    run_dir = out if out is not None else Path("runs") / _run_name(cfg)
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"--out {run_dir} exists and is not a directory")
    return run_dir


class _LineProgress:
    """Progress where no bar can be drawn (output to a log or a pipe): a plain line on
    stderr at most every ``every`` seconds, the first after ``every`` seconds, so that short
    work prints nothing and a long run in a batch job is not silent. The part of rich's
    ``Progress`` the commands use."""

    def __init__(self, every: float = 30.0):
        self.every = every
        self.tasks: list[list] = []  # [description, completed, total]
        self.t0 = self.last = time.monotonic()

    def __enter__(self) -> _LineProgress:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def add_task(self, description: str, total: float | None = None) -> int:
        self.tasks.append([description, 0, total])
        return len(self.tasks) - 1

    def update(self, task: int, description: str | None = None,
               completed: float | None = None, total: float | None = None) -> None:
        t = self.tasks[task]
        for i, v in ((0, description), (1, completed), (2, total)):
            if v is not None:
                t[i] = v
        self._line(task)

    def advance(self, task: int, advance: float = 1) -> None:
        self.tasks[task][1] += advance
        self._line(task)

    def _line(self, task: int) -> None:
        now = time.monotonic()
        if now - self.last < self.every:
            return
        self.last = now
        what, done, total = self.tasks[task]
        count = f": {done:g}/{total:g}" if total else ""
        print(f"[{now - self.t0:.0f} s] {what}{count}", file=sys.stderr, flush=True)


def _progress() -> Progress | _LineProgress:
    """A progress bar on a terminal, else `_LineProgress`'s occasional lines."""
    if not console.is_terminal and not _state.get("force_progress"):
        return _LineProgress()
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        SpinnerColumn,
        TextColumn,
        TimeElapsedColumn,
    )

    return Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                    MofNCompleteColumn(), TimeElapsedColumn(), console=console)


def _do_generate(cfg: Config, run_dir: Path, settings=None) -> dict:
    from rrtcolearn import pipeline

    # the settings left to the library first (a pilot of simulations for the cost bound)
    cfg, derive_cpu = pipeline.timed(pipeline.resolve, cfg)
    with _progress() as bar:
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

    with _progress() as bar:
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


def _write_plan(p, path: Path, state_names: tuple[str, ...] | None = None,
                plot: bool = True) -> None:
    """The plan file, and with ``plot`` the PNG of its tree beside it. Without ``plot`` a PNG
    left there by an earlier plot is removed: it would show another plan."""
    from rrtcolearn import pipeline

    pipeline.write_plan(p, path)
    png = path.with_suffix(".png")
    if plot:
        # matplotlib takes about half a second to import: only a plot pays for it
        from rrtcolearn.plotting import save_figure, tree_figure

        save_figure(tree_figure(p, state_names), png)
    else:
        png.unlink(missing_ok=True)


def _plan_summary(p) -> dict:
    return {"status": p.status, "solved": p.solved, "iterations": p.iterations,
            "nodes": p.nodes, "path_cost": round(p.path_cost, 4),
            "path_duration": round(p.path_duration, 3),
            "max_abs_u": round(p.max_abs_u, 4), "u_max": p.symmetric_limit,
            "limit_mode": p.limit_mode,
            "planning_cpu_s": round(p.planning_cpu_s, 4),
            **({"goal_connected": p.extra["connection"] or False}
               if "goal_connected" in p.extra else {}),
            **({"diagnosis": p.extra["diagnosis"]} if "diagnosis" in p.extra else {}),
            **({"iterations_spent_on": _outcome_shares(p.extra["outcomes"])}
               if "outcomes" in p.extra else {}),
            **({"edges_by": ", ".join(f"{k} {v}" for k, v in p.extra["edges_by"].items())}
               if "edges_by" in p.extra else {}),
            **({"path_duration_by": ", ".join(
                f"{k} {100 * v:.0f}%" for k, v in p.extra["duration_by"].items())}
               if p.extra.get("duration_by") else {}),
            **({"switched_on_at_iteration": ", ".join(
                f"{k} {v}" for k, v in p.extra["connections_switched_on"].items())}
               if "connections_switched_on" in p.extra else {}),
            **(_anytime_summary(p.extra["anytime"]) if "anytime" in p.extra else {})}


def _anytime_summary(a: dict) -> dict:
    """An anytime plan's solves and its cost at the first and the last improvement."""
    out = {"anytime_solves": a["solves"]}
    if a["progress"]:
        (t0, c0), (t1, c1) = a["progress"][0], a["progress"][-1]
        out["first_solution"] = f"cost {c0:.4g} at {t0:.3g} s CPU"
        out["best_solution"] = f"cost {c1:.4g} at {t1:.3g} s CPU"
    return out


def _outcome_shares(outcomes: dict) -> str:
    """What the iterations came to, largest share first (what limited a slow plan)."""
    total = sum(outcomes.values()) or 1
    parts = sorted(((v, k) for k, v in outcomes.items() if v), reverse=True)
    return ", ".join(f"{k.replace('_', ' ')} {v / total:.0%}" for v, k in parts)


def _print_summary(title: str, figures: dict) -> None:
    from rich.table import Table

    table = Table(title=title, show_header=False)
    for k, v in figures.items():
        table.add_row(k, str(v))
    out_console.print(table)


def _print_version(value: bool) -> None:
    if value:
        from rrtcolearn import __version__

        out_console.print(f"rrtcolearn {__version__}")
        raise typer.Exit(0)


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="show tracebacks on errors")] = False,
    version: Annotated[bool, typer.Option("--version", help="print the version",
                                          is_eager=True, callback=_print_version)] = False,
) -> None:
    _state["debug"] = debug


@app.command()
def systems() -> None:
    """List the registered systems."""
    from rrtcolearn.systems import list_systems, make

    for name in list_systems():  # plain lines: rich would wrap them at its console width
        typer.echo(f"{name}: {make(name).description}")


@app.command()
def generate(config: ConfigOpt = None, seed: SeedOpt = None, out: OutOpt = None,
             set_: SetOpt = None, u_max: UMaxOpt = None, workers: WorkersOpt = None,
             scheduler: SchedulerOpt = None, dask_local: DaskLocalOpt = None,
             system: SystemOpt = None, offline_budget: BudgetOpt = None) -> None:
    """Generate a dataset of optimal trajectory segments (Alg. 2); resumable."""
    def body():
        from rrtcolearn import pipeline
        from rrtcolearn.parallel import ExecutionSettings

        settings = ExecutionSettings.from_options(workers, scheduler, dask_local)
        cfg = _config(config, seed, set_, u_max=u_max, system=system,
                      offline_budget=offline_budget)
        run_dir = _run_dir(out, cfg)
        figures = _do_generate(cfg, run_dir, settings)
        _print_derived(pipeline.read_run_config(run_dir))
        _print_summary(f"generate -> {run_dir}", figures)
    _guard(body)


@app.command()
def clean(config: ConfigOpt = None, seed: SeedOpt = None, out: OutOpt = None,
          system: SystemOpt = None,
          set_: SetOpt = None) -> None:
    """Remove the local-optimum bias from a run's dataset (Alg. 3)."""
    def body():
        cfg = _config(config, seed, set_, out, system=system)
        run_dir = _run_dir(out, cfg)
        _print_summary(f"clean -> {run_dir}", _do_clean(cfg, run_dir))
    _guard(body)


@app.command()
def fit(config: ConfigOpt = None, seed: SeedOpt = None, out: OutOpt = None,
        system: SystemOpt = None,
        set_: SetOpt = None) -> None:
    """Fit the cost-to-go, steering and validity learners on a run's cleaned dataset."""
    def body():
        cfg = _config(config, seed, set_, out, system=system)
        run_dir = _run_dir(out, cfg)
        fitted, figures = _do_fit(cfg, run_dir)
        _print_derived(fitted.config)
        _print_summary(f"fit -> {run_dir}", figures)
    _guard(body)


def _one_blas_thread() -> None:
    """One BLAS thread, unless the environment says otherwise: a plan multiplies only small
    matrices, and starting the thread pools of numpy's and scipy's OpenBLAS costs about 0.1 s
    of a fresh process on two cores. Takes effect when numpy is not yet imported (this
    module does not import it)."""
    for var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS"):
        os.environ.setdefault(var, "1")


def _parse_state(value: str | None, what: str) -> list[float] | None:
    if value is None:
        return None
    try:
        return [float(v) for v in value.split(",")]
    except ValueError:
        raise ConfigError(f"{what} must be comma-separated numbers like -3.14,0, "
                          f"got {value!r}") from None


@app.command()
def plan(
    model: Annotated[Path | None, typer.Option("--model", help="fitted run directory")] = None,
    start: Annotated[str | None, typer.Option(help="start state, e.g. -3.14159,0")] = None,
    goal: Annotated[str | None, typer.Option(help="goal state, e.g. 0,0")] = None,
    goal_tolerance: Annotated[float | None, typer.Option(help="goal radius")] = None,
    seed: SeedOpt = None,
    time_limit: Annotated[float | None, typer.Option(help="seconds")] = None,
    max_iterations: Annotated[int | None, typer.Option(help="iteration limit")] = None,
    anytime: Annotated[bool | None, typer.Option(
        "--anytime/--first-solution", help="spend the whole limit, solving again with fresh "
        "seeds, shortcutting each path to the goal and keeping the cheapest (plan.anytime); "
        "default: the first solution")
    ] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", help="plan file (JSON); with --queries a directory (default "
        "<model>/queries)")] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    u_max: UMaxOpt = None,
    obstacle: ObstacleOpt = None,
    system_name: SystemOpt = None,
    queries: Annotated[Path | None, typer.Option(
        "--queries", help="plan every query of this file (CSV with start, goal[, "
        "goal_tolerance, seed] columns, or JSON lines) from one process")] = None,
    workers: WorkersOpt = None,
    plot: Annotated[bool, typer.Option(
        "--plot", help="also write a PNG of the tree beside the plan file (imports "
        "matplotlib: about half a second more)")] = False,
    dynobench: DynobenchOpt = None,
) -> None:
    """Plan one query with a fitted model; writes the plan JSON (with --plot also a PNG of
    the tree). With --queries, plans every query of a file into a directory of plan files."""
    _one_blas_thread()

    def body():
        from rrtcolearn import pipeline
        from rrtcolearn.config import Config, add_obstacles, load_config

        run_dir = model if model is not None else Path("runs") / _run_name(
            Config() if system_name is None else Config().model_copy(update={
                "system": Config().system.model_copy(update={"name": system_name})}))
        options = _options({("plan", "start"): _parse_state(start, "--start"),
                            ("plan", "goal"): _parse_state(goal, "--goal"),
                            ("plan", "goal_tolerance"): goal_tolerance,
                            ("plan", "time_limit"): time_limit,
                            ("plan", "max_iterations"): max_iterations,
                            ("plan", "anytime"): anytime,
                            ("system", "u_max"): u_max})
        # validate everything before the model is loaded: the query, the config, the files
        model_info = pipeline.read_model_info(run_dir, system_name)
        _, model_cfg, system = model_info
        if seed is not None and seed < 0:
            raise ConfigError("--seed must be a non-negative integer")
        read, posed = _dynobench(dynobench)
        if read is not None and posed["system"]["name"] != model_cfg.system.name:
            raise ConfigError(f"--dynobench {dynobench}: a {read.robot} problem; the model "
                              f"is of {model_cfg.system.name}")
        options["plan"] = {**posed.get("plan", {}), **options.get("plan", {})}
        # the model's own configuration is the base; only its plan section may change here
        cfg = load_config(config, list(set_ or []), base={
            "plan": model_cfg.plan.model_dump(),
            "system": model_cfg.system.model_dump(exclude_none=True)}, options=options)
        _plan_time_settings(config, list(set_ or []), model_cfg)
        cfg = add_obstacles(cfg, list(obstacle or []))
        if queries is not None:
            if plot:
                raise ConfigError("--plot draws one plan: drop it with --queries")
            _plan_queries(run_dir, cfg, system, queries, out, workers,
                          given=start is not None or goal is not None or seed is not None)
            return
        if workers is not None:
            raise ConfigError("--workers plans the queries of a file: give --queries")
        start_x, goal_x = pipeline.query_states(cfg, system)
        pipeline.make_problem(system, cfg, start_x, goal_x, cfg.plan.goal_tolerance)
        out_path = out if out is not None else run_dir / "plan.json"
        if out_path.is_dir():
            raise ConfigError(f"--out {out_path} is a directory; give a file name like "
                              "plan.json")
        fitted = pipeline.load_model(run_dir, model_info=model_info)
        p_cfg = fitted.config.model_copy(update={"plan": cfg.plan, "system": cfg.system})
        plan_seed = seed if seed is not None else fitted.config.seed
        p = pipeline.plan(fitted, start_x, goal_x, cfg.plan.goal_tolerance, plan_seed,
                          config=p_cfg, time_limit=cfg.plan.time_limit,
                          max_iterations=cfg.plan.max_iterations)
        _write_plan(p, out_path, fitted.system.state_names, plot=plot)
        _write_dynobench(read, p, fitted.system, out_path)
        _print_summary(f"plan -> {out_path}", _plan_summary(p))
    _guard(body)


def _plan_time_settings(path: Path | None, overrides: list[str], model: Config) -> None:
    """ConfigError for a setting `plan` cannot apply: the model fixes every section but
    [plan], and of the system only a plan-time input limit (u_max, by truncation) may
    change. A setting equal to the model's is fine (a file shared with `run`); another
    value would otherwise be recorded in the plan file and ignored."""
    from rrtcolearn.config import parse_override, read_toml

    # (section, key) -> value given: --set over the file
    given = {tuple(parts): value for parts, value in map(parse_override, overrides)}
    for section, values in (read_toml(path) if path is not None else {}).items():
        for key, value in (values.items() if isinstance(values, dict) else [(None, values)]):
            given.setdefault((section,) if key is None else (section, key), value)
    own = model.model_dump(mode="json")
    fixed = []
    for parts, value in given.items():
        if parts[0] == "plan" or parts == ("system", "u_max"):
            continue
        node = own
        for p in parts:
            node = node.get(p) if isinstance(node, dict) else None
        if node != value:
            fixed.append(".".join(parts))
    if fixed:
        raise ConfigError(f"{', '.join(fixed)}: a plan uses the model's settings; only [plan] "
                          "and system.u_max may change at plan time (refit the model to "
                          "change the others)")


def _plan_queries(run_dir: Path, cfg: Config, system, path: Path, out: Path | None,
                  workers: int | None, given: bool) -> None:
    """`plan --queries`: every query of the file, one plan file each, and a summary."""
    import numpy as np

    from rrtcolearn import pipeline
    from rrtcolearn.parallel import ExecutionSettings
    from rrtcolearn.queries import plan_query_file, read_queries

    if given:
        raise ConfigError("--queries takes start, goal and seed from the file: drop "
                          "--start, --goal and --seed")
    qs = read_queries(path, cfg.plan.goal_tolerance, system.n_states)
    for q in qs:  # every query checked before any is planned
        try:
            pipeline.make_problem(system, cfg, q.start, q.goal, q.goal_tolerance)
        except ValueError as exc:
            raise ConfigError(f"{path}, line {q.line}: {exc}") from None
    out_dir = out if out is not None else run_dir / "queries"
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"--out {out_dir} is a file; with --queries give a directory")
    settings = ExecutionSettings.from_options(workers, None, None)
    t0 = time.perf_counter()
    with _progress() as bar:
        task = bar.add_task("planning queries", total=len(qs))
        rows = plan_query_file(run_dir, qs, out_dir, config=cfg,
                               time_limit=cfg.plan.time_limit,
                               max_iterations=cfg.plan.max_iterations, settings=settings,
                               progress=lambda done: bar.update(task, completed=done))
    cpu = np.array([r["planning_cpu_s"] for r in rows])
    solved = sum(bool(r["solved"]) for r in rows)
    _print_summary(f"plan --queries -> {out_dir}", {
        "queries": len(rows), "solved": f"{solved}/{len(rows)}",
        "planning_cpu_s median": round(float(np.median(cpu)), 4),
        "planning_cpu_s mean": round(float(cpu.mean()), 4),
        "wall_s": round(time.perf_counter() - t0, 2),
        "summary": str(out_dir / "plans.csv")})


@app.command()
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
        read, posed = _dynobench(dynobench)
        cfg = _config(config, seed, set_, u_max=u_max, obstacles=obstacle, system=system,
                      offline_budget=offline_budget, posed=posed)
        run_dir = _run_dir(out, cfg)
        t0 = time.perf_counter()
        figures = {"run_dir": str(run_dir)}
        figures |= _do_generate(cfg, run_dir, settings)
        figures |= _do_clean(cfg, run_dir)
        fitted, fit_fig = _do_fit(cfg, run_dir)
        figures |= fit_fig
        figures["offline_cpu_s"] = round(figures["generate_cpu_s"] + figures["clean_cpu_s"]
                                         + figures["fit_cpu_s"], 3)
        start, goal = pipeline.query_states(cfg, fitted.system)
        p = pipeline.plan(fitted, start, goal, cfg.plan.goal_tolerance,
                          cfg.seed, config=fitted.config, time_limit=cfg.plan.time_limit,
                          max_iterations=cfg.plan.max_iterations)
        _write_plan(p, run_dir / "plan.json", fitted.system.state_names)
        _write_dynobench(read, p, fitted.system, run_dir / "plan.json")
        figures |= _plan_summary(p)
        figures["wall_s"] = round(time.perf_counter() - t0, 2)
        figures["derived"] = dict(sorted(fitted.config.derived.items()))
        write_json(run_dir / "summary.json", figures)
        _print_derived(fitted.config)
        _print_summary(f"run -> {run_dir}", {k: v for k, v in figures.items()
                                              if k != "derived"})
    _guard(body)


@app.command()
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
        cfg = _config(config, seed, set_, system=system)
        if quick:
            overrides = [f"experiment.{k}={v!r}"
                         for k, v in quick_settings(cfg.system.name).items()]
            cfg = _config(config, seed, overrides + list(set_ or []), system=system)
        pipeline.system_from_config(cfg)  # an unknown system is reported before any work
        exp_dir = out if out is not None else Path("runs") / f"{_run_name(cfg)}-experiment"
        with _progress() as bar:
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
        _print_summary("experiment", figures)
    _guard(body)


def _checked_plan(plan_file: Path, system_name: str | None):
    """(plan file content, its system), the file checked to be what it claims."""
    from rrtcolearn import pipeline
    from rrtcolearn.evaluate import PlanCheckError, check_plan

    d = pipeline.read_plan(plan_file)
    system = pipeline.plan_system(d, system_name)
    try:  # the file is what it claims before anything is made from it
        check_plan(system, d)
    except PlanCheckError as exc:
        raise ArtefactError(f"{plan_file}: {exc}") from None
    return d, system


def _write_table(target: Path, fmt: str, header: list[str], columns: list[str],
                 arrays: dict, table) -> None:
    """A CSV (``header`` lines as # comments, then the column names; whole numbers in an
    ``edge`` column) or an npz of ``arrays`` with ``columns``."""
    import numpy as np

    from rrtcolearn.data.store import atomic_write_bytes, atomic_write_text

    if fmt == "csv":
        whole = [c == "edge" for c in columns]
        lines = [f"# {h}" for h in header] + [",".join(columns)] + [
            ",".join(str(int(v)) if w else repr(float(v)) for v, w in zip(row, whole,
                                                                          strict=True))
            for row in table]
        atomic_write_text(target, "\n".join(lines) + "\n")
    else:
        import io

        buffer = io.BytesIO()
        np.savez(buffer, columns=np.array(columns), header=np.array(header), **arrays)
        atomic_write_bytes(target, buffer.getvalue())


@app.command()
def export(
    plan_file: Annotated[Path, typer.Argument(help="plan file (JSON) written by plan or run")],
    dt: Annotated[float | None, typer.Option(
        help="sample step (s), a whole multiple of the plan's integration step "
             "(default: that step)")] = None,
    fmt: Annotated[str, typer.Option("--format", help="csv or npz")] = "csv",
    out: Annotated[Path | None, typer.Option(
        "--out", help="output file (default: the plan file with .csv or .npz)")] = None,
    gains: Annotated[bool, typer.Option(
        "--gains", help="also write the tracking controller: the nominal at the plan's step "
        "and its time-varying LQR gains K(t), to OUT's name with -gains")] = False,
    system_name: SystemOpt = None,
) -> None:
    """Time, state, input and costate samples along a plan's path, re-simulated from its
    edges (the trajectory to execute); with --gains the tracking controller's gains."""
    def body():
        import numpy as np

        from rrtcolearn.evaluate import sample_path

        if fmt not in ("csv", "npz"):
            raise ConfigError(f"--format {fmt!r}: give csv or npz")
        if dt is not None and not dt > 0:
            raise ConfigError(f"--dt {dt}: give a positive step")
        d, system = _checked_plan(plan_file, system_name)
        try:
            samples = sample_path(system, d, dt)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        target = out if out is not None else plan_file.with_suffix(f".{fmt}")
        columns = ["t", *system.state_names, *system.input_names,
                   *(f"lambda_{name}" for name in system.state_names), "edge"]
        header = [
            f"rrtcolearn trajectory: system {system.name}, {system.n_states} states, "
            f"{system.n_inputs} inputs, integration step {d['dt']} s",
            "units: t in seconds; states, inputs and costates (lambda_, nan on "
            "random-control edges) in the units of the system's definition",
            "inputs between rows: continuous within an extremal edge (interpolate linearly), "
            "held within a random-control edge; where edges meet, two rows with the same t: "
            "the end of the one edge, then the start of the next (the input jumps there)"]
        table = np.column_stack([samples["t"], samples["state"], samples["input"],
                                 samples["costate"], samples["edge"]])
        _write_table(target, fmt, header, columns, samples, table)
        figures = {"samples": len(samples["t"]),
                   "duration_s": round(float(samples["t"][-1]), 4),
                   "edges": int(samples["edge"][-1]) + 1, "columns": ", ".join(columns)}
        if gains:
            from rrtcolearn.tracking import TrackingController

            c = TrackingController.build(system, d)
            nom = c.nominal
            gain_names = [f"K_{u}_{x}" for u in system.input_names for x in system.state_names]
            K = np.concatenate([c.K, c.K[-1:]]).reshape(len(nom.t), -1)
            g_target = target.with_name(f"{target.stem}-gains{target.suffix}")
            _write_table(g_target, fmt, [
                f"rrtcolearn tracking gains: system {system.name}, step {nom.dt} s, state "
                f"weight {c.state_weight:g} x Bryson's Q (the self-test's), terminal cost "
                f"{c.terminal}",
                "u = clip(u_nom - K (x - x_nom), input box) with K held from each row's t to "
                "the next (the last row's K: the last step's); angles of x - x_nom the short "
                "way round",
                "K_<input>_<state>: the gain of that input on that state's error; "
                f"input box low {c.u_low.tolist()} high {c.u_high.tolist()}"],
                ["t", *system.state_names, *system.input_names, *gain_names],
                {"t": nom.t, "state": nom.state, "input": nom.input,
                 "K": np.concatenate([c.K, c.K[-1:]]), "u_low": c.u_low, "u_high": c.u_high},
                np.column_stack([nom.t, nom.state, nom.input, K]))
            figures["gains"] = str(g_target)
        _print_summary(f"export -> {target}", figures)
    _guard(body)


@app.command()
def track(
    plan_file: Annotated[Path, typer.Argument(help="plan file (JSON) written by plan or run")],
    rollouts: Annotated[int, typer.Option(help="runs, open-loop and tracked each")] = 100,
    true_system: Annotated[str | None, typer.Option(
        "--true-system", help="the system the runs happen on (module:attribute or a "
        "registered name; the same states and inputs as the plan's, other parameters); "
        "default the plan's own model")] = None,
    noise: Annotated[float, typer.Option(
        help="process noise: standard deviation per sqrt(s), a fraction of each state's "
             "box width")] = 0.0,
    start_error: Annotated[float, typer.Option(
        "--start-error", help="start state off by a uniform draw within +- this fraction of "
        "each state's box width")] = 0.0,
    state_weight: Annotated[float, typer.Option(
        "--state-weight", help="multiplies the state weight Q the self-test picks (a multiple "
        "of Bryson's rule from the boxes, as the goal LQR)")] = 1.0,
    seed: SeedOpt = None,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="write the figure of the nominal and the runs' spread (PNG)")] = None,
    system_name: SystemOpt = None,
) -> None:
    """Run a plan open-loop and tracked by time-varying LQR, on the model or another
    system, with noise and a start error; goal reached, errors, inputs at the limit,
    obstacle entries."""
    def body():
        from rrtcolearn import tracking

        if rollouts < 1:
            raise ConfigError(f"--rollouts {rollouts}: give at least 1")
        if not (noise >= 0 and start_error >= 0):
            raise ConfigError("--noise and --start-error must not be negative")
        if not state_weight > 0:
            raise ConfigError(f"--state-weight {state_weight}: give a positive factor")
        d, system = _checked_plan(plan_file, system_name)
        truth = None
        if true_system is not None:
            from rrtcolearn.systems import make

            try:
                truth = make(true_system)
            except ValueError as exc:
                raise ConfigError(f"--true-system: {exc}") from None
            tracking.check_truth(system, truth)
        c = tracking.TrackingController.build(system, d, state_weight=state_weight)
        runs = tracking.rollouts(c, rollouts, truth=truth, noise=noise,
                                 start_error=start_error, seed=0 if seed is None else seed)
        rows = [tracking.summarise(c, r) for r in runs]
        from rich.table import Table

        table = Table(title=f"track {plan_file}: {rollouts} runs on "
                      f"{true_system or 'the model'}, noise {noise:g}, start error "
                      f"{start_error:g}, state weight {c.state_weight:g} x Bryson's, seed "
                      f"{0 if seed is None else seed}")
        table.add_column("")
        for name in ("open-loop", "tracked"):
            table.add_column(name, justify="right")
        tol = c.problem.goal_tolerance
        for key, label in (("reached", f"goal reached (<= {tol:g})"),
                           ("reached_2x", f"within 2x ({2 * tol:g})"),
                           ("final_error_median", "final error, median"),
                           ("final_error_max", "final error, largest"),
                           ("deviation_median", "largest deviation, median"),
                           ("deviation_max", "largest deviation, largest"),
                           ("time_at_limit", "time at the input limit"),
                           ("inputs_in_box", "inputs within the box"),
                           ("obstacle_entries", "runs entering an obstacle"),
                           ("constraint_exits", "runs leaving the state constraints")):
            table.add_row(label, *(_figure(r[key]) for r in rows))
        out_console.print(table)
        if plot is not None:
            from rrtcolearn.animation import tracking_figure
            from rrtcolearn.plotting import save_figure

            fig = tracking_figure(system, c.nominal.t, c.nominal.state,
                                  {"open-loop": runs[0].states, "tracked": runs[1].states},
                                  title=f"{plan_file.name}: {rollouts} runs")
            save_figure(fig, plot)
            typer.echo(f"figure -> {plot}")
    _guard(body)


def _figure(v) -> str:
    if isinstance(v, bool) or isinstance(v, int):
        return str(v)
    return f"{v:.3g}" if abs(v) >= 1 or v == 0 or v != v else f"{v:.3f}"


@app.command()
def animate(
    plan_file: Annotated[Path, typer.Argument(help="plan file (JSON) written by plan or run")],
    out: Annotated[Path, typer.Option("--out", help="animation file: .gif (pillow) or .mp4 "
                                      "(needs ffmpeg)")],
    fps: Annotated[float, typer.Option(help="frames per second (real time up to 120 "
                                       "frames)")] = 20.0,
    system_name: SystemOpt = None,
) -> None:
    """Animate a plan's motion: the bodies where the system declares them (pendulum,
    cart-pole, acrobot, quadrotor), else its states against time."""
    def body():
        from rrtcolearn.animation import animate as write
        from rrtcolearn.evaluate import sample_path

        if not fps > 0:
            raise ConfigError(f"--fps {fps}: give a positive rate")
        d, system = _checked_plan(plan_file, system_name)
        s = sample_path(system, d)
        frames = write(system, s["t"], s["state"], out, fps=fps,
                       title=f"{system.name}: {plan_file.name}")
        _print_summary(f"animate -> {out}", {"frames": frames,
                                             "duration_s": round(float(s["t"][-1]), 3),
                                             "bytes": out.stat().st_size})
    _guard(body)


@app.command()
def inspect(run_dir: Annotated[Path, typer.Argument(help="run directory")]) -> None:
    """Size and content digest (SHA-256) of every artefact of a run directory.

    Digests depend on content only (not on chunking, workers or file layout), so two labs can
    check that they hold the same dataset.
    """
    def body():
        from rrtcolearn import pipeline

        rows = pipeline.inspect_run(run_dir)
        width = max([len(r["file"]) for r in rows], default=4)
        for r in rows:
            typer.echo(f"{r['file']:<{width}}  {r['kind']:<7}  {r['bytes']:>11}  {r['sha256']}")
    _guard(body)


class Interrupted(BaseException):
    """SIGINT or SIGTERM: raised instead of KeyboardInterrupt, which click would swallow."""


def _interrupt(signum, frame) -> None:
    raise Interrupted


def main() -> None:
    """Console entry point."""
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        app()
    except (Interrupted, KeyboardInterrupt):
        console.print(_INTERRUPTED)
        sys.exit(130)
    finally:
        # the process ends here: the interpreter's shutdown would garbage-collect every object
        # that numba, scipy and the model created (0.2-0.3 s after a plan); frozen, they are
        # left to the operating system. atexit handlers (worker pools) still run.
        gc.freeze()


if __name__ == "__main__":
    main()

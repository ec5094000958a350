"""What the commands share: the consoles, the options several commands take, one-line
errors instead of tracebacks, the run's configuration and directory from the options, progress
and the summary table."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape

from rrtcolearn.errors import ConfigError, RRTCoLearnError

if TYPE_CHECKING:
    from collections.abc import Callable

    from rich.progress import Progress

    from rrtcolearn.config import Config


console = Console(stderr=True)
out_console = Console()
state = {"debug": False}  # the top-level options (--debug), set before any command runs

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
    "in the workspace, for plan.body; on plan they replace the run's obstacles")]

DynobenchOpt = Annotated[str | None, typer.Option(
    "--dynobench", help="a dynobench problem (the optional extra): <robot>/<environment> as "
    "the package ships it, e.g. unicycle1_v0/parallelpark_0, or an environment file; poses "
    "its robot's system, query, body and obstacles, and writes the plan also in dynobench's "
    "result format (plan.dynobench.yaml)")]


def printable(message: str) -> str:
    """The message with control characters and rich markup escaped: one literal line."""
    return escape("".join(c if c.isprintable() else repr(c)[1:-1] for c in message))


def fail(message: str, code: int) -> None:
    """The message as one error line on stderr, and exit with ``code``."""
    console.print(f"[bold red]error:[/] {printable(message)}", highlight=False,
                  soft_wrap=True, markup=True)
    raise typer.Exit(code)


INTERRUPTED = "interrupted; finished files are complete, unfinished ones were not written"


class Interrupted(BaseException):
    """SIGINT or SIGTERM: raised instead of KeyboardInterrupt, which click would swallow."""


def caused_by_interrupt(exc: BaseException) -> bool:
    """True when a signal landed inside compiled code and surfaced wrapped in another error."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (Interrupted, KeyboardInterrupt)):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def guard(fn: Callable[[], object]) -> object:
    """Run a command body; user errors become one line and a non-zero exit, never a traceback."""
    try:
        return fn()
    except typer.Exit:
        raise
    except RRTCoLearnError as exc:
        if state["debug"]:
            raise
        fail(str(exc), exc.exit_code)
    except (Interrupted, KeyboardInterrupt):
        console.print(INTERRUPTED)
        raise typer.Exit(130) from None
    except MemoryError:
        fail("out of memory; reduce generate.n_simulations", 3)
    except OSError as exc:  # unwritable directory, disk full, ...: the environment, not a bug
        if caused_by_interrupt(exc):
            console.print(INTERRUPTED)
            raise typer.Exit(130) from None
        fail(f"cannot read or write a file: {exc}", 3)
    except Exception as exc:  # an internal error: still one line unless --debug
        if caused_by_interrupt(exc):
            console.print(INTERRUPTED)
            raise typer.Exit(130) from None
        if state["debug"]:
            raise
        fail(f"internal error: {type(exc).__name__}: {exc} (rerun with --debug for details)", 1)


def command_config(config: Path | None, seed: int | None, overrides: list[str] | None,
                    run_dir: Path | None = None, u_max: float | None = None,
                    obstacles: list[str] | None = None, system: str | None = None,
                    offline_budget: float | None = None, posed: dict | None = None) -> Config:
    """The run's configuration from the command line: ``run_dir``'s config.toml (if any),
    then the file, the ``--set`` overrides, the typed options (over a dynobench problem's
    ``posed`` sections), the obstacles and the seed."""
    from rrtcolearn.config import add_obstacles, load_config, read_toml

    base = {}
    if run_dir is not None and (run_dir / "config.toml").is_file():
        base = read_toml(run_dir / "config.toml")
    options = nested_options({("system", "name"): system, ("system", "u_max"): u_max,
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


def nested_options(given: dict[tuple[str, str], object]) -> dict[str, dict[str, object]]:
    """The typed command-line options that were given, nested by section as in a file."""
    nested: dict[str, dict[str, object]] = {}
    for (section, key), value in given.items():
        if value is not None:
            nested.setdefault(section, {})[key] = value
    return nested


def run_name(cfg: Config) -> str:
    """The run's name: the configured one, or for another system than the pendulum under the
    default name, the system's (so a user system's run does not land in the pendulum's)."""
    from rrtcolearn.config import Config

    if cfg.name == Config().name and cfg.system.name != Config().system.name:
        return re.sub(r"[^A-Za-z0-9._-]", "-", cfg.system.name).lstrip("-._") or cfg.name
    return cfg.name


def run_directory(out: Path | None, cfg: Config) -> Path:
    """``--out``, else runs/<run name>; ConfigError if it is a file."""
    run_dir = out if out is not None else Path("runs") / run_name(cfg)
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"--out {run_dir} exists and is not a directory")
    return run_dir


class LineProgress:
    """Progress where no bar can be drawn (output to a log or a pipe): a plain line on
    stderr at most every ``every`` seconds, the first after ``every`` seconds, so that short
    work prints nothing and a long run in a batch job is not silent. The part of rich's
    ``Progress`` the commands use."""

    def __init__(self, every: float = 30.0):
        self.every = every
        self.tasks: list[list] = []  # [description, completed, total]
        self.t0 = self.last = time.monotonic()

    def __enter__(self) -> LineProgress:
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


def progress_bar() -> Progress | LineProgress:
    """A progress bar on a terminal, else `LineProgress`'s occasional lines."""
    if not console.is_terminal:
        return LineProgress()
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


def print_summary(title: str, figures: dict) -> None:
    """A command's figures as a two-column table on stdout."""
    from rich.table import Table

    table = Table(title=title, show_header=False)
    for k, v in figures.items():
        table.add_row(k, str(v))
    out_console.print(table)

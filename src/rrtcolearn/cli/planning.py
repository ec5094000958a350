"""The plan command (one query, or every query of a file with --queries), and the plan
file, summary and dynobench result that `run` writes too."""

from __future__ import annotations

import contextlib
import gc
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from rrtcolearn.cli.common import (
    ConfigOpt,
    DynobenchOpt,
    ObstacleOpt,
    SeedOpt,
    SetOpt,
    SystemOpt,
    UMaxOpt,
    WorkersOpt,
    console,
    guard,
    nested_options,
    print_summary,
    printable,
    progress_bar,
    run_name,
)
from rrtcolearn.errors import ConfigError

if TYPE_CHECKING:
    from rrtcolearn.config import Config
    from rrtcolearn.dynobench import DynobenchProblem
    from rrtcolearn.planning.tree import Plan
    from rrtcolearn.systems import System


def read_dynobench(problem: str | None) -> tuple[DynobenchProblem | None, dict]:
    """The dynobench problem named on the command line and the config sections posing it
    (None, {} without one)."""
    if problem is None:
        return None, {}
    from rrtcolearn import dynobench

    read = dynobench.read_problem(problem)
    return read, dynobench.config_options(read)


def write_dynobench(read: DynobenchProblem | None, p: Plan, system: System,
                    plan_path: Path) -> None:
    """The solved plan beside ``plan_path`` in dynobench's result format."""
    if read is None or not p.solved:
        return
    from rrtcolearn import dynobench
    from rrtcolearn.evaluate import sample_path

    dynobench.write_result(plan_path.with_suffix(".dynobench.yaml"),
                           dynobench.result(read, sample_path(system, p)))


def write_plan(p: Plan, path: Path, state_names: tuple[str, ...] | None = None,
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


def plan_summary(p: Plan) -> dict:
    """A plan's figures for the summary table (and `run`'s summary.json)."""
    return {"status": p.status, "solved": p.solved, "iterations": p.iterations,
            "nodes": p.nodes, "path_cost": round(p.path_cost, 4),
            "path_duration": round(p.path_duration, 3),
            "max_abs_u": round(p.max_abs_u, 4), "u_max": p.symmetric_limit,
            **({"input_limits": _input_limits(p)} if p.symmetric_limit is None
               and p.limit_mode is not None else {}),
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
            # (the solve's own path: with anytime or polish the path was improved since)
            **({"goal_parent": _goal_parent_summary(p.extra["goal_parent"])}
               if "goal_parent" in p.extra and "anytime" not in p.extra
               and "polish" not in p.extra else {}),
            **(_anytime_summary(p.extra["anytime"]) if "anytime" in p.extra else {}),
            **(_polish_summary(p.extra["polish"]) if "polish" in p.extra else {}),
            **({"half_step_check": step_summary(p)} if "step_check" in p.extra else {})}


def _input_limits(p: Plan) -> str:
    """The input box of a plan whose inputs have limits of their own, input by input
    (``u_max`` is the one bound they share, where they share one)."""
    return ", ".join(f"[{lo:g}, {hi:g}]" for lo, hi in zip(
        p.input_low.tolist(), p.input_high.tolist(), strict=True))


def _goal_parent_summary(r: dict) -> str:
    """Choose-parent for the goal in words (`connections.cheaper_goal_edge`'s record)."""
    tried = f"{r['tries']} nodes tried" + (f", {r['funnel_tries']} through the goal funnel"
                                           if r.get("funnel_tries") else "")
    if r["cost"] < r["cost_before"]:
        return f"{tried}: path cost {r['cost_before']:.4g} -> {r['cost']:.4g}"
    return f"{tried}: none gave a cheaper path"


def step_summary(p: Plan) -> str:
    """`evaluate.step_check`'s figures in words: the path at half the plan's step."""
    c = p.extra["step_check"]
    tol = p.goal_tolerance
    node_gap = c.get("node_gap", c["goal_gap"])  # (a plan file from before node gaps)
    where = (f"at dt/2 the end moves {c['goal_gap']:.2g} (goal tolerance {tol:.3g}) to "
             f"{c['goal_distance']:.3g} from the goal"
             + (f", a node on the way {node_gap:.2g}" if node_gap > c["goal_gap"] else "")
             + ("" if c["valid"] else "; a state grazes an obstacle or a state bound"))
    if not c["replays"]:
        return (f"the plan does NOT re-simulate to its own path at its step: an internal "
                f"error, please report it ({where})")
    if c["resolved"]:
        return f"resolved: {where}"
    return (f"NOT resolved by the step dt = {p.dt:g}: {where}: the plan's integration error "
            f"is as large as the goal region; plan with another seed, or fit the model with "
            f"a smaller generate.dt")


def warn_unresolved(p: Plan) -> None:
    """A warning on stderr for a solved plan whose step does not resolve it, or that does
    not re-simulate to its own path."""
    c = p.extra.get("step_check")
    if c is not None and not (c["resolved"] and c["replays"]):
        console.print(f"[bold yellow]warning:[/] {printable(step_summary(p))}", highlight=False)


def _polish_summary(r: dict) -> dict:
    """A polished plan's raw first cost and CPU beside its polished cost (plan.polish)."""
    def rounded(v: float | None) -> float | None:
        return None if v is None else round(v, 4)

    return {"first_solution_cost": rounded(r["first_cost"]),
            "first_solution_cpu_s": rounded(r["first_cpu_s"]),
            "polished_cost": rounded(r["cost"])}


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


def _one_blas_thread() -> None:
    """One BLAS thread, unless the environment says otherwise: a plan multiplies only small
    matrices, and starting the thread pools of numpy's and scipy's OpenBLAS costs about 0.1 s
    of a fresh process on two cores. Takes effect when numpy is not yet imported (no
    module of the command line imports it)."""
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

    def body(started: Callable[[], None]):
        from rrtcolearn import pipeline
        from rrtcolearn.config import Config, add_obstacles, load_config

        run_dir = model if model is not None else Path("runs") / run_name(
            Config() if system_name is None else Config().model_copy(update={
                "system": Config().system.model_copy(update={"name": system_name})}))
        options = nested_options({("plan", "start"): _parse_state(start, "--start"),
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
        read, posed = read_dynobench(dynobench)
        if read is not None and posed["system"]["name"] != model_cfg.system.name:
            raise ConfigError(f"--dynobench {dynobench}: a {read.robot} problem; the model "
                              f"is of {model_cfg.system.name}")
        options["plan"] = {**posed.get("plan", {}), **options.get("plan", {})}
        # the model's own configuration is the base; only its plan section may change here.
        # --obstacle gives this plan's obstacles: they replace the run's, not add to them
        base_plan = model_cfg.plan.model_dump()
        if obstacle:
            base_plan["obstacles"] = []
        cfg = load_config(config, list(set_ or []), base={
            "plan": base_plan,
            "system": model_cfg.system.model_dump(exclude_none=True)}, options=options)
        _plan_time_settings(config, list(set_ or []), model_cfg)
        cfg = add_obstacles(cfg, list(obstacle or []))
        if queries is not None:
            if plot:
                raise ConfigError("--plot draws one plan: drop it with --queries")
            started()
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
        started()
        p_cfg = fitted.config.model_copy(update={"plan": cfg.plan, "system": cfg.system})
        plan_seed = seed if seed is not None else fitted.config.seed
        p = pipeline.plan(fitted, start_x, goal_x, cfg.plan.goal_tolerance, plan_seed,
                          config=p_cfg, time_limit=cfg.plan.time_limit,
                          max_iterations=cfg.plan.max_iterations)
        write_plan(p, out_path, fitted.system.state_names, plot=plot)
        write_dynobench(read, p, fitted.system, out_path)
        print_summary(f"plan -> {out_path}", plan_summary(p))
        warn_unresolved(p)
    with _collector_paused() as started:
        guard(lambda: body(started))


@contextlib.contextmanager
def _collector_paused() -> Iterator[Callable[[], None]]:
    """The cyclic garbage collector paused for a command's start-up, until it calls the
    function this yields (before planning). Importing the library and loading a model make
    ~190 000 objects, nearly none of them garbage, which the collector's passes traversed
    again and again (0.2 s of a 4-state model's `plan`, two full passes among them). At
    that call they are frozen (`gc.freeze`: left out of later passes, so the plan's passes
    do not meet them either) and the collector runs again; at the end they are unfrozen.
    The start-up's own cyclic garbage (~2 000 small objects, no arrays) waits until then."""
    enabled = gc.isenabled()
    gc.disable()

    def started() -> None:
        gc.freeze()
        if enabled:
            gc.enable()

    try:
        yield started
    finally:
        if enabled:
            gc.enable()
        gc.unfreeze()


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
    with progress_bar() as bar:
        task = bar.add_task("planning queries", total=len(qs))
        rows = plan_query_file(run_dir, qs, out_dir, config=cfg,
                               time_limit=cfg.plan.time_limit,
                               max_iterations=cfg.plan.max_iterations, settings=settings,
                               progress=lambda done: bar.update(task, completed=done))
    cpu = np.array([r["planning_cpu_s"] for r in rows])
    solved = sum(bool(r["solved"]) for r in rows)
    # solved plans whose step does not resolve the path (`evaluate.step_check`)
    unresolved = sum(bool(r["solved"]) and r["resolved"] is False for r in rows)
    print_summary(f"plan --queries -> {out_dir}", {
        "queries": len(rows), "solved": f"{solved}/{len(rows)}",
        **({"solved, not resolved by the step": f"{unresolved} (column resolved)"}
           if unresolved else {}),
        "planning_cpu_s median": round(float(np.median(cpu)), 4),
        "planning_cpu_s mean": round(float(cpu.mean()), 4),
        "wall_s": round(time.perf_counter() - t0, 2),
        "summary": str(out_dir / "plans.csv")})

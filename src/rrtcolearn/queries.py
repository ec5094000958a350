"""Many queries from one process: read a query file, plan every query with one loaded model.

A query file is CSV (a header with ``start`` and ``goal``, and optionally ``goal_tolerance``
and ``seed``; a state is comma-separated numbers, quoted: ``"-3.14159,0"``) or JSON lines
(``{"start": [...], "goal": [...], "goal_tolerance": 0.1, "seed": 3}`` per line). A query
without a tolerance takes the configured one; without a seed, its line's index (from 0), so
the same file gives the same plans. Planning loads the model once per process: the start-up
(imports, model load, compiled kernels from the disk cache) is paid once for all queries.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn import __version__
from rrtcolearn.data.store import atomic_write_text
from rrtcolearn.errors import ConfigError

if TYPE_CHECKING:
    from rrtcolearn.planning.tree import Plan

__all__ = ["Query", "iter_plans", "plan_query_file", "read_queries"]

_COLUMNS = ("start", "goal", "goal_tolerance", "seed")


@dataclass(frozen=True)
class Query:
    """One planning query: start and goal states, goal tolerance and seed."""

    start: tuple[float, ...]
    goal: tuple[float, ...]
    goal_tolerance: float
    seed: int


def _state(value, where: str, key: str, n: int | None) -> tuple[float, ...]:
    if isinstance(value, str):
        try:
            value = [float(v) for v in value.replace(";", ",").split(",") if v.strip()]
        except ValueError:
            raise ConfigError(f"{where}: {key} must be comma-separated numbers, got "
                              f"{value!r}") from None
    if not isinstance(value, list) or not value or \
            not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise ConfigError(f"{where}: {key} must be a list of numbers, got {value!r}")
    out = tuple(float(v) for v in value)
    if not all(math.isfinite(v) for v in out):
        raise ConfigError(f"{where}: {key} must be finite, got {list(out)}")
    if n is not None and len(out) != n:
        raise ConfigError(f"{where}: {key} needs {n} values (the system's states), got "
                          f"{len(out)}")
    return out


def _query(row: dict, where: str, index: int, tolerance: float, n: int | None) -> Query:
    unknown = sorted(set(row) - set(_COLUMNS))
    if unknown:
        raise ConfigError(f"{where}: unknown field{'s' if len(unknown) > 1 else ''} "
                          f"{', '.join(map(repr, unknown))} (known: {', '.join(_COLUMNS)})")
    for key in ("start", "goal"):
        if row.get(key) in (None, ""):
            raise ConfigError(f"{where}: {key} is missing")
    tol, seed = row.get("goal_tolerance"), row.get("seed")
    try:
        tol = tolerance if tol in (None, "") else float(tol)
        seed = index if seed in (None, "") else int(seed)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: goal_tolerance must be a number and seed an integer, "
                          f"got {row.get('goal_tolerance')!r} and {row.get('seed')!r}") from None
    if not (math.isfinite(tol) and tol > 0):
        raise ConfigError(f"{where}: goal_tolerance must be positive, got {tol}")
    if seed < 0:
        raise ConfigError(f"{where}: seed must be a non-negative integer, got {seed}")
    return Query(_state(row["start"], where, "start", n), _state(row["goal"], where, "goal", n),
                 tol, seed)


def read_queries(path: str | Path, goal_tolerance: float, n_states: int | None = None
                 ) -> list[Query]:
    """The queries of a CSV or JSON-lines file (by its suffix: ``.csv``, else JSON lines);
    ConfigError naming the line for anything malformed."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"query file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file") from None
    queries = []
    if path.suffix.lower() == ".csv":
        reader = csv.DictReader(text.splitlines())
        missing = [c for c in ("start", "goal") if c not in (reader.fieldnames or ())]
        if missing:
            raise ConfigError(f"{path}: the header needs the columns start and goal (got "
                              f"{reader.fieldnames})")
        for row in reader:
            if None in row:
                raise ConfigError(f"{path}, line {reader.line_num}: more fields than the "
                                  "header has (quote states: \"-3.14,0\")")
            queries.append(_query(row, f"{path}, line {reader.line_num}", len(queries),
                                  goal_tolerance, n_states))
    else:
        for number, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            where = f"{path}, line {number}"
            try:
                row = json.loads(line)
            except json.JSONDecodeError as exc:
                raise ConfigError(f"{where}: not JSON ({exc.msg})") from None
            if not isinstance(row, dict):
                raise ConfigError(f"{where}: a query is a JSON object")
            queries.append(_query(row, where, len(queries), goal_tolerance, n_states))
    if not queries:
        raise ConfigError(f"{path}: no queries")
    return queries


def iter_plans(model, queries: Sequence[Query], *, config=None,
               time_limit: float | None = 10.0, max_iterations: int | None = None
               ) -> Iterator[tuple[int, Plan]]:
    """(index, plan) for every query, in order, planned with one fitted model
    (`pipeline.plan`); a plan can be written and dropped before the next is made."""
    from rrtcolearn import pipeline

    config = config or model.config
    for i, q in enumerate(queries):
        # each plan records its own query in its configuration, as `rrtcolearn plan` does
        query = config.plan.model_copy(update={"start": list(q.start), "goal": list(q.goal),
                                               "goal_tolerance": q.goal_tolerance})
        yield i, pipeline.plan(model, np.asarray(q.start), np.asarray(q.goal),
                               q.goal_tolerance, q.seed,
                               config=config.model_copy(update={"plan": query}),
                               time_limit=time_limit, max_iterations=max_iterations)


_MODELS: dict[str, object] = {}  # per worker process: the model of a run directory


def _plan_chunk(task: tuple) -> list[tuple[int, dict]]:
    """A worker's share of the queries: the model loaded once per process."""
    from rrtcolearn import pipeline
    from rrtcolearn.config import Config

    run_dir, config, queries, first, time_limit, max_iterations = task
    if run_dir not in _MODELS:
        _MODELS[run_dir] = pipeline.load_model(run_dir)
    model = _MODELS[run_dir]
    return [(first + i, p.to_dict()) for i, p in iter_plans(
        model, queries, config=_with_plan(model, Config.model_validate(config)),
        time_limit=time_limit, max_iterations=max_iterations)]


def _with_plan(model, config):
    """The model's configuration with the plan and system sections of ``config`` (what a
    plan command may change), as `rrtcolearn plan` records it."""
    return model.config.model_copy(update={"plan": config.plan, "system": config.system})


def plan_query_file(run_dir: str | Path, queries: Sequence[Query], out_dir: str | Path, *,
                    config, time_limit: float | None = 10.0,
                    max_iterations: int | None = None, settings=None,
                    progress: Callable[[int], None] | None = None) -> list[dict]:
    """Plan ``queries`` with the model of ``run_dir`` into ``out_dir``: one plan file per
    query (``plan-00000.json``, ...) and ``plans.csv`` (one row per query: its seed,
    status, CPU time, nodes, cost). With ``settings`` (`parallel.ExecutionSettings`) the
    queries are shared among worker processes, each loading the model once; the plans do
    not depend on how they are shared. Returns the rows of ``plans.csv``."""
    from rrtcolearn import pipeline
    from rrtcolearn.data.store import write_checked_json
    from rrtcolearn.parallel import map_tasks

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict | None] = [None] * len(queries)

    def write(i: int, d: dict) -> None:
        name = f"plan-{i:05d}.json"
        write_checked_json(out_dir / name, {"format": pipeline.PLAN_FORMAT,
                                            "schema_version": pipeline.PLAN_SCHEMA,
                                            "package_version": __version__, **d})
        rows[i] = {"query": i, "seed": queries[i].seed, "status": d["status"],
                   "solved": d["solved"], "planning_cpu_s": d["planning_cpu_s"],
                   "nodes": d["nodes"], "iterations": d["iterations"],
                   "path_cost": d["path_cost"], "final_goal_distance":
                   d["final_goal_distance"], "file": name}
        if progress is not None:
            progress(sum(r is not None for r in rows))

    workers = 1 if settings is None or settings.backend == "serial" else settings.workers
    if workers <= 1:
        model = pipeline.load_model(run_dir)
        for i, p in iter_plans(model, queries, config=_with_plan(model, config),
                               time_limit=time_limit, max_iterations=max_iterations):
            write(i, p.to_dict())
    else:
        size = -(-len(queries) // (4 * workers))  # a few chunks per worker: balanced
        tasks = [(str(run_dir), config.model_dump(mode="json"), list(queries[k : k + size]),
                  k, time_limit, max_iterations) for k in range(0, len(queries), size)]
        map_tasks(_plan_chunk, tasks, settings,
                  on_result=lambda _, done: [write(i, d) for i, d in done])
    fields = list(rows[0])
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(out_dir / "plans.csv", buf.getvalue())
    return rows

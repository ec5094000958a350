"""Many queries from one process: read a query file, plan every query with one loaded model.

A query file is CSV (a header with ``start`` and ``goal``, and optionally ``goal_tolerance``
and ``seed``; a state is comma-separated numbers, quoted: ``"-3.14159,0"``) or JSON lines
(``{"start": [...], "goal": [...], "goal_tolerance": 0.1, "seed": 3}`` per line), UTF-8 with
or without a byte-order mark. A query without a tolerance takes the configured one; without
a seed, its index among the file's queries (from 0), so the same file gives the same plans.
A seed is a non-negative integer (``2.0``, ``2.5`` and ``true`` are refused), a repeated
key or column is refused, and every error names the file's line. Planning loads the model
once per process: the start-up (imports, model load, compiled kernels from the disk cache)
is paid once for all queries.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
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
_SUMMARY = ("query", "seed", "status", "solved", "resolved", "planning_cpu_s", "nodes",
            "iterations", "path_cost", "final_goal_distance", "file")
NOT_PLANNED = "not planned"  # plans.csv status of a query a batch that ended early left


@dataclass(frozen=True)
class Query:
    """One planning query: start and goal states, goal tolerance and seed. ``line`` is its
    1-based line in the query file (None when not read from one), for error messages; it
    is not part of the query's identity (equality)."""

    start: tuple[float, ...]
    goal: tuple[float, ...]
    goal_tolerance: float
    seed: int
    line: int | None = field(default=None, compare=False)


class _DuplicateKey(Exception):
    """A JSON object with a key twice (json keeps the last silently)."""


def _object(pairs: list[tuple[str, object]]) -> dict:
    """`json.loads` object hook: a dict, refusing a repeated key."""
    row: dict = {}
    for key, value in pairs:
        if key in row:
            raise _DuplicateKey(key)
        row[key] = value
    return row


def _show(value: object) -> str:
    """A value as the user wrote it: a CSV cell quoted, a JSON value as JSON (``true``)."""
    return repr(value) if isinstance(value, str) else json.dumps(value)


def _number(value: object) -> float | None:
    """A number from a CSV cell or a JSON number (not ``true``/``false``); None if neither."""
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        return None
    try:
        return float(value)
    except ValueError:
        return None


def _seed(value: object) -> int | None:
    """A non-negative integer from a CSV cell or a JSON integer (not ``2.0``, ``2.5`` or
    ``true``: a seed that is not the integer written would silently change the plan)."""
    if isinstance(value, str):
        with contextlib.suppress(ValueError):
            value = int(value)
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 \
        else None


def _state(value, where: str, key: str, n: int | None, csv_file: bool) -> tuple[float, ...]:
    """A state from a CSV cell (``"-3.14,0"``) or a JSON list of numbers, of ``n`` values."""
    if isinstance(value, str):
        try:
            value = [float(v) for v in value.replace(";", ",").split(",") if v.strip()]
        except ValueError:
            raise ConfigError(f"{where}: {key} must be comma-separated numbers, got "
                              f"{value!r}") from None
    if not isinstance(value, list) or not value or \
            not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise ConfigError(f"{where}: {key} must be a list of numbers, got {_show(value)}")
    out = tuple(float(v) for v in value)
    if not all(math.isfinite(v) for v in out):
        raise ConfigError(f"{where}: {key} must be finite, got {list(out)}")
    if n is not None and len(out) != n:
        # a CSV state split at its commas leaves a value per column: say how to quote it
        hint = "; in CSV quote a state with commas: \"-3.14,0\"" if csv_file and len(out) < n \
            else ""
        raise ConfigError(f"{where}: {key} needs {n} values (the system's states), got "
                          f"{len(out)}{hint}")
    return out


def _query(row: dict, where: str, line: int, index: int, tolerance: float, n: int | None,
           csv_file: bool) -> Query:
    """The query of one row (CSV cells or a JSON object); the states are checked first, as
    a misquoted CSV state shifts the later columns."""
    unknown = sorted(set(row) - set(_COLUMNS))
    if unknown:
        raise ConfigError(f"{where}: unknown field{'s' if len(unknown) > 1 else ''} "
                          f"{', '.join(map(repr, unknown))} (known: {', '.join(_COLUMNS)})")
    for key in ("start", "goal"):
        if row.get(key) in (None, ""):
            raise ConfigError(f"{where}: {key} is missing")
    start = _state(row["start"], where, "start", n, csv_file)
    goal = _state(row["goal"], where, "goal", n, csv_file)
    raw_tol, raw_seed = row.get("goal_tolerance"), row.get("seed")
    tol = tolerance if raw_tol in (None, "") else _number(raw_tol)
    if tol is None or not (math.isfinite(tol) and tol > 0):
        raise ConfigError(f"{where}: goal_tolerance must be a positive number, got "
                          f"{_show(raw_tol)}")
    seed = index if raw_seed in (None, "") else _seed(raw_seed)
    if seed is None:
        raise ConfigError(f"{where}: seed must be a non-negative integer, got "
                          f"{_show(raw_seed)}")
    return Query(start, goal, tol, seed, line)


def read_queries(path: str | Path, goal_tolerance: float, n_states: int | None = None
                 ) -> list[Query]:
    """The queries of a CSV or JSON-lines file (by its suffix: ``.csv``, else JSON lines);
    ConfigError naming the line for anything malformed."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"query file not found: {path}")
    try:  # utf-8-sig: Excel's CSV starts with a byte-order mark
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file") from None
    lines = text.split("\n")  # newlines are translated on reading; the file's lines exactly
    queries: list[Query] = []
    if path.suffix.lower() == ".csv":
        reader = csv.DictReader(lines)
        header = reader.fieldnames or []
        missing = [c for c in ("start", "goal") if c not in header]
        if missing:
            raise ConfigError(f"{path}: the header needs the columns start and goal (got "
                              f"{header})")
        repeated = sorted({c for c in header if header.count(c) > 1})
        if repeated:
            raise ConfigError(f"{path}, line {reader.line_num}: the header repeats the column"
                              f"{'s' if len(repeated) > 1 else ''} "
                              f"{', '.join(map(repr, repeated))}")
        for row in reader:
            where = f"{path}, line {reader.line_num}"
            if None in row:
                raise ConfigError(f"{where}: more fields than the header has (quote states: "
                                  "\"-3.14,0\")")
            queries.append(_query(row, where, reader.line_num, len(queries), goal_tolerance,
                                  n_states, True))
    else:
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            where = f"{path}, line {number}"
            try:
                row = json.loads(line, object_pairs_hook=_object)
            except json.JSONDecodeError as exc:
                raise ConfigError(f"{where}: not JSON ({exc.msg})") from None
            except _DuplicateKey as exc:
                raise ConfigError(f"{where}: the key {exc.args[0]!r} appears twice") from None
            if not isinstance(row, dict):
                raise ConfigError(f"{where}: a query is a JSON object")
            queries.append(_query(row, where, number, len(queries), goal_tolerance, n_states,
                                  False))
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
    not depend on how they are shared. Returns the rows of ``plans.csv``.

    An ``out_dir`` that holds another batch's ``plans.csv`` or plan files is refused
    (ConfigError) before anything is planned: a summary beside stale plans would mislead,
    and the user's files are never deleted. A batch that ends early (an interrupt, a failed
    write) still leaves ``plans.csv``, written atomically, once a plan is written: a row per
    query, those not planned with status ``"not planned"`` and their other fields empty;
    then the error is raised again."""
    from rrtcolearn import pipeline
    from rrtcolearn.data.store import write_checked_json
    from rrtcolearn.parallel import map_tasks

    out_dir = Path(out_dir)
    stale = sorted(p.name for p in (*out_dir.glob("plan-*.json"), out_dir / "plans.csv")
                   if p.is_file())
    if stale:
        raise ConfigError(f"{out_dir} holds the results of another batch ({', '.join(stale[:3])}"
                          f"{', ...' if len(stale) > 3 else ''}): give a new output directory "
                          "or remove them")
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict | None] = [None] * len(queries)

    def write(i: int, d: dict) -> None:
        name = f"plan-{i:05d}.json"
        write_checked_json(out_dir / name, {"format": pipeline.PLAN_FORMAT,
                                            "schema_version": pipeline.PLAN_SCHEMA,
                                            "package_version": __version__, **d})
        rows[i] = {"query": i, "seed": queries[i].seed, "status": d["status"],
                   "solved": d["solved"],
                   # whether the plan's step resolves its path (`evaluate.step_check`): a
                   # solved plan that is not resolved misses the goal when replayed at dt/2
                   "resolved": d.get("step_check", {}).get("resolved", ""),
                   "planning_cpu_s": d["planning_cpu_s"],
                   "nodes": d["nodes"], "iterations": d["iterations"],
                   "path_cost": d["path_cost"], "final_goal_distance":
                   d["final_goal_distance"], "file": name}
        if progress is not None:
            progress(sum(r is not None for r in rows))

    workers = 1 if settings is None or settings.backend == "serial" else settings.workers
    try:
        if workers <= 1:
            model = pipeline.load_model(run_dir)
            for i, p in iter_plans(model, queries, config=_with_plan(model, config),
                                   time_limit=time_limit, max_iterations=max_iterations):
                write(i, p.to_dict())
        else:
            size = -(-len(queries) // (4 * workers))  # a few chunks per worker: balanced
            tasks = [(str(run_dir), config.model_dump(mode="json"),
                      list(queries[k : k + size]), k, time_limit, max_iterations)
                     for k in range(0, len(queries), size)]
            map_tasks(_plan_chunk, tasks, settings,
                      on_result=lambda _, done: [write(i, d) for i, d in done])
    except BaseException:
        if any(rows):  # the plans written so far; the original error is the one to raise
            with contextlib.suppress(Exception):
                _write_summary(out_dir / "plans.csv", queries, rows)
        raise
    _write_summary(out_dir / "plans.csv", queries, rows)
    return rows


def _write_summary(path: Path, queries: Sequence[Query], rows: list[dict | None]) -> None:
    """``plans.csv``, atomically: a row per query, ``"not planned"`` where ``rows`` has none."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=_SUMMARY, restval="", lineterminator="\n")
    writer.writeheader()
    writer.writerows(r if r is not None else {"query": i, "seed": q.seed, "status": NOT_PLANNED}
                     for i, (q, r) in enumerate(zip(queries, rows, strict=True)))
    atomic_write_text(path, buf.getvalue())

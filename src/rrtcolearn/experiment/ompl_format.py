"""OMPL's benchmark log format and SQLite schema, so OMPL's tools (Planner Arena,
``ompl_benchmark_statistics.py``) can read our runs.

The log follows the EBNF of OMPL's "benchmark logfile format"; the database has the five
documented tables: experiments, plannerConfigs, enums, runs and progress, with one column in
``runs`` per run property.
"""

from __future__ import annotations

import math
import platform
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rrtcolearn import __version__
from rrtcolearn.data.store import atomic_write_bytes, atomic_write_text

# ompl::base::PlannerStatus, in its numeric order
STATUS_VALUES = ["Unknown status", "Invalid start", "Invalid goal", "Unrecognized goal type",
                 "Timeout", "Approximate solution", "Exact solution", "Crash", "Abort",
                 "Infeasible"]
STATUS_CODE = {"timeout": 4, "approximate": 5, "exact": 6, "crash": 7}

# (log property name, type, row key)
RUN_PROPERTIES = [
    ("time", "REAL", "time"),
    ("solved", "BOOLEAN", "solved"),
    ("approximate solution", "BOOLEAN", "approximate"),
    ("solution difference", "REAL", "final_goal_distance"),
    ("status", "ENUM", "status_code"),
    ("graph states", "INTEGER", "nodes"),
    ("iterations", "INTEGER", "iterations"),
    ("path cost", "REAL", "path_cost"),
    ("path duration", "REAL", "path_duration"),
    ("max abs u", "REAL", "max_abs_u"),
    ("wall time", "REAL", "wall_s"),
    ("epoch", "INTEGER", "epoch"),
    ("seed", "INTEGER", "seed"),
]


@dataclass
class LogExperiment:
    """One OMPL experiment: a problem, and every planner's runs on it."""

    name: str
    time_limit: float
    total_time: float
    seed: int
    setup: str
    properties: dict[str, tuple[str, str]] = field(default_factory=dict)  # name -> (type, value)
    planners: dict[str, list[dict]] = field(default_factory=dict)  # planner -> rows


def _value(row: dict, key: str) -> str:
    if key == "approximate":
        return "1" if row.get("status") == "approximate" else "0"
    if key == "status_code":
        return str(STATUS_CODE.get(row.get("status", ""), 0))
    v = row.get(key)
    if v is None or v == "":
        return ""
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float) and not math.isfinite(v):
        return "inf" if v > 0 else "nan"
    return str(v)


def format_log(exp: LogExperiment, date: str) -> str:
    """The benchmark log of one experiment."""
    lines = [f"rrtcolearn version {__version__}", f"Experiment {exp.name}"]
    if exp.properties:
        lines.append(f"{len(exp.properties)} experiment properties")
        for name, (typ, value) in exp.properties.items():
            lines.append(f"{name} {typ} = {value}")
    lines += [f"Running on {platform.node() or 'localhost'}", f"Starting at {date}",
              "<<<|", *exp.setup.rstrip("\n").split("\n"), "|>>>",
              "<<<|", f"{platform.processor() or platform.machine()}", "|>>>",
              f"{exp.seed} is the random seed", f"{exp.time_limit} seconds per run",
              "0 MB per run"]
    runs = max((len(r) for r in exp.planners.values()), default=0)
    lines += [f"{runs} runs per planner", f"{exp.total_time} seconds spent to collect the data",
              "1 enum type", "status|" + "|".join(STATUS_VALUES),
              f"{len(exp.planners)} planners"]
    for planner, rows in exp.planners.items():
        lines += [planner, "0 common properties", f"{len(RUN_PROPERTIES)} properties for each run"]
        lines += [f"{name} {typ}" for name, typ, _ in RUN_PROPERTIES]
        lines.append(f"{len(rows)} runs")
        for row in rows:
            lines.append("".join(f"{_value(row, key)}; " for _, _, key in RUN_PROPERTIES))
        lines.append(".")
    return "\n".join(lines) + "\n"


_SCHEMA = """
CREATE TABLE IF NOT EXISTS experiments
    (id INTEGER PRIMARY KEY AUTOINCREMENT, name VARCHAR(512), totaltime REAL, timelimit REAL,
     memorylimit REAL, runcount INTEGER, version VARCHAR(128), hostname VARCHAR(1024),
     cpuinfo TEXT, date DATETIME, seed VARCHAR(24), setup TEXT);
CREATE TABLE IF NOT EXISTS plannerConfigs
    (id INTEGER PRIMARY KEY AUTOINCREMENT, name VARCHAR(512) NOT NULL, settings TEXT);
CREATE TABLE IF NOT EXISTS enums
    (name VARCHAR(512), value INTEGER, description TEXT, PRIMARY KEY (name, value));
CREATE TABLE IF NOT EXISTS runs
    (id INTEGER PRIMARY KEY AUTOINCREMENT, experimentid INTEGER, plannerid INTEGER,
     FOREIGN KEY (experimentid) REFERENCES experiments(id) ON DELETE CASCADE,
     FOREIGN KEY (plannerid) REFERENCES plannerConfigs(id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS progress
    (runid INTEGER, time REAL, PRIMARY KEY (runid, time),
     FOREIGN KEY (runid) REFERENCES runs(id) ON DELETE CASCADE);
"""


def _column(name: str) -> str:
    return name.replace(" ", "_")


def write_database(path: str | Path, experiments: Sequence[LogExperiment], date: str) -> None:
    """A SQLite database in OMPL's documented benchmark schema, written atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.building")
    tmp.unlink(missing_ok=True)
    conn = sqlite3.connect(tmp)
    try:
        c = conn.cursor()
        c.execute("PRAGMA FOREIGN_KEYS = ON")
        c.executescript(_SCHEMA)
        for value, description in enumerate(STATUS_VALUES):
            c.execute("INSERT INTO enums VALUES (?, ?, ?)", ("status", value, description))
        for name, typ, _ in RUN_PROPERTIES:
            c.execute(f"ALTER TABLE runs ADD {_column(name)} {typ}")
        planner_ids: dict[str, int] = {}
        for exp in experiments:
            runcount = max((len(r) for r in exp.planners.values()), default=0)
            c.execute("INSERT INTO experiments (name, totaltime, timelimit, memorylimit, "
                      "runcount, version, hostname, cpuinfo, date, seed, setup) "
                      "VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                      (exp.name, exp.total_time, exp.time_limit, 0.0, runcount,
                       f"rrtcolearn {__version__}", platform.node() or "localhost",
                       platform.processor() or platform.machine(), date, str(exp.seed),
                       exp.setup))
            exp_id = c.lastrowid
            for planner, rows in exp.planners.items():
                if planner not in planner_ids:
                    c.execute("INSERT INTO plannerConfigs (name, settings) VALUES (?, ?)",
                              (planner, ""))
                    planner_ids[planner] = c.lastrowid
                cols = ["experimentid", "plannerid"] + [_column(n) for n, _, _ in RUN_PROPERTIES]
                sql = f"INSERT INTO runs ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})"
                for row in rows:
                    values = []
                    for _, typ, key in RUN_PROPERTIES:
                        v = _value(row, key)
                        values.append(None if v in ("", "nan", "inf") else
                                      (float(v) if typ == "REAL" else int(float(v))))
                    c.execute(sql, [exp_id, planner_ids[planner], *values])
        conn.commit()
    finally:
        conn.close()
    atomic_write_bytes(path, tmp.read_bytes())
    tmp.unlink()


def write_log(path: str | Path, experiments: Sequence[LogExperiment], date: str) -> None:
    atomic_write_text(path, "".join(format_log(e, date) for e in experiments))

"""What the experiment's runner and report share: its problems, seeds, dataset names and
result schema (so the report needs nothing from the runner, and the runner imports the report).
"""

from __future__ import annotations

import csv
import io
import json

import numpy as np

from rrtcolearn import pipeline
from rrtcolearn.config import Config, ProblemSpec, pendulum_problems
from rrtcolearn.data.store import atomic_write_text
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.systems.base import System

ROW_FIELDS = ["epoch", "seed", "problem", "planner", "solved", "status", "time", "wall_s",
              "iterations", "nodes", "path_cost", "path_duration", "max_abs_u",
              "final_goal_distance", "u_max", "time_weight", "goal_tolerance"]


def experiment_problems(config: Config) -> list[ProblemSpec]:
    """The configured problems; by default the paper's five for the pendulum, else the
    system's standard query (its start, goal and the configured tolerance, time weight and
    scalar ``u_max``) as the one problem "standard"."""
    if config.experiment.problems is not None:
        return list(config.experiment.problems)
    if config.system.name == "pendulum":
        return pendulum_problems()
    u_max = config.system.u_max if isinstance(config.system.u_max, float) else None
    return [ProblemSpec(name="standard", u_max=u_max, time_weight=config.system.time_weight,
                        goal_tolerance=config.plan.goal_tolerance)]


def dataset_name(problem: ProblemSpec) -> str:
    """Problems with the same torque limit and time weight share a dataset."""
    u = "none" if problem.u_max is None else f"{problem.u_max:g}"
    return f"umax-{u}_w-{problem.time_weight:g}"


def epoch_seed(seed: int, epoch: int) -> int:
    """Seed of an epoch's dataset, independent of every other epoch's."""
    return int(np.random.SeedSequence(seed, spawn_key=(100, epoch)).generate_state(1)[0])


def run_seed(epoch: int, run: int) -> int:
    """Seed of one planning run; every planner gets the same seeds."""
    return 100_000 * epoch + run


def epoch_config(config: Config, problem: ProblemSpec, epoch: int) -> Config:
    """The configuration of one epoch's dataset for ``problem`` (its limit and time weight)."""
    system = config.system.model_copy(update={"u_max": problem.u_max,
                                              "time_weight": problem.time_weight})
    return config.model_copy(update={"system": system, "seed": epoch_seed(config.seed, epoch)})


_SYSTEMS: dict[str, System] = {}


def problem_system(config: Config, problem: ProblemSpec) -> System:
    """The system of ``problem`` (with its input limits), built once per process."""
    cfg = epoch_config(config, problem, 0)
    key = json.dumps(cfg.system.model_dump(mode="json"), sort_keys=True) + \
        json.dumps(cfg.generate.model_dump(mode="json"), sort_keys=True)
    if key not in _SYSTEMS:
        if len(_SYSTEMS) > 8:
            _SYSTEMS.pop(next(iter(_SYSTEMS)))
        _SYSTEMS[key] = pipeline.system_from_config(cfg)
    return _SYSTEMS[key]


def planning_problem(config: Config, problem: ProblemSpec,
                     system: System | None = None) -> PlanningProblem:
    """The `PlanningProblem` every planner gets for ``problem``: the configured query (or
    the system's standard one, with its goal region), as `pipeline.make_problem` makes it
    with the problem's tolerance and torque limit (carried by a saturating system itself)."""
    system = problem_system(config, problem) if system is None else system
    start, goal = pipeline.query_states(config, system)
    return pipeline.make_problem(system, config, start, goal, problem.goal_tolerance,
                                 u_max=problem.u_max)


def write_csv(path, rows: list[dict], fields: list[str]) -> None:
    """``rows`` as CSV with the columns ``fields`` (None as empty), written atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in fields})
    atomic_write_text(path, buf.getvalue())

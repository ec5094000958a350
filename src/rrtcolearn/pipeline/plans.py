"""Planning with a fitted model: the query every planner gets (`make_problem`), one plan
(`plan`, Alg. 1 with the optional anytime and polish rounds), and the plan file (its writing,
reading and the system it was planned on)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rrtcolearn import __version__
from rrtcolearn.config import Config, plan_obstacles, validate
from rrtcolearn.data.store import read_checked_json, write_checked_json
from rrtcolearn.errors import ConfigError
from rrtcolearn.evaluate import StepChecks
from rrtcolearn.pipeline.configure import recorded_system
from rrtcolearn.pipeline.model import FittedModel
from rrtcolearn.planning.problem import PlanningProblem, ProblemError, is_own_limit
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan
from rrtcolearn.systems.base import System

_FROM_CONFIG = object()


def make_problem(system: System, config: Config, start, goal, goal_tolerance: float, *,
                 u_max=_FROM_CONFIG, obstacles=_FROM_CONFIG, is_valid=None, goal_fn=None,
                 goal_sampler=None) -> PlanningProblem:
    """The query as every planner gets it (`plan` and the experiment's peers alike): the
    configuration's state constraints, goal weights and angle wrapping, its ``u_max`` and
    obstacles unless given, and the system's goal region for its standard goal.

    ``is_valid(states) -> bool array`` adds a user state validity checker; ``goal_fn(states)
    -> distances`` and ``goal_sampler(rng) -> state`` a user goal region (reached where the
    distance is at most ``goal_tolerance``); a system whose ``defaults`` hold them plans to
    that region when ``goal`` is its default goal. A system that saturates its inputs plans
    within its own limits (a different ``u_max`` needs a model trained for it:
    ConfigError); an unbounded one plans under ``u_max`` by truncation (edges whose input
    exceeds it are rejected or cut, plan.input_limit).
    """
    if u_max is _FROM_CONFIG:
        u_max = config.system.u_max
    if system.input_limited:
        low, high = system.input_limits()
        if u_max is not None:
            if not is_own_limit(system, u_max):
                box = ", ".join(f"{lo:g} <= {name} <= {hi:g}" for name, lo, hi in
                                zip(system.input_names, low.tolist(), high.tolist(),
                                    strict=True))
                raise ConfigError(
                    f"u_max {u_max}: the model's inputs saturate at its own limits ({box}), "
                    "which its plans keep: omit u_max, or train a model with the limit you "
                    "want (system.u_max)")
        u_max = None
    elif isinstance(u_max, list):
        raise ConfigError("a model of the unbounded system can plan under a single u_max "
                          "only (by truncation); train a model with the limits instead")
    if obstacles is _FROM_CONFIG:
        obstacles = plan_obstacles(config.plan)
    defaults = system.defaults
    if goal_fn is None and "goal_fn" in defaults and defaults.get("goal") is not None \
            and np.array_equal(np.asarray(goal, dtype=float),
                               np.asarray(defaults["goal"], dtype=float)):
        # the system's standard query comes with its goal region
        goal_fn, goal_sampler = defaults["goal_fn"], defaults.get("goal_sampler")
    p = config.plan
    return PlanningProblem.create(system, start, goal, goal_tolerance, u_max=u_max,
                                  obstacles=obstacles, is_valid=is_valid,
                                  wrap_goal=p.wrap_goal, state_low=p.state_low,
                                  state_high=p.state_high, goal_weights=p.goal_weights,
                                  goal_fn=goal_fn, goal_sampler=goal_sampler)


# ``plan.polish``: each of the round's two improvements within this share of the first
# solve's iterations, in improvement steps (deterministic under a time budget too). On the
# nine problems of bench/ablation.py (5 seeds, bench/polish.py --steps) 0.25 and 1 gave the
# same polished cost on all nine (the improvements end before the allowance); 0.25 cost less
# CPU on sparse_rrt's cart-pole (1.45 s against 2.34 s), where neither gained (docs/anytime.md)
POLISH_ALLOWANCE = 0.25


def _polish_record(result: Plan) -> dict:
    """``plan.polish``'s record for ``extra["polish"]`` (the one-solve anytime record, moved):
    the raw first path's cost and CPU, the polished cost, the CPU of both together, the
    improvement steps spent and whether multiple shooting replaced the path."""
    a = result.extra.pop("anytime")
    return {"first_cost": a["first_solution_cost"], "first_cpu_s": a["first_solution_cpu_s"],
            "cost": float(result.path_cost) if result.solved else None,
            "planning_cpu_s": a["planning_cpu_s"],
            "steps": a["iterations"] - max(1, result.iterations),
            "multiple_shooting": result.extra.get("multiple_shooting", {}).get("kept")}


def plan(model: FittedModel, start, goal, goal_tolerance: float, seed: int = 0, *,
         config: Config | None = None, time_limit: float | None = 10.0,
         max_iterations: int | None = None, u_max=_FROM_CONFIG, obstacles=_FROM_CONFIG,
         is_valid=None, goal_fn=None, goal_sampler=None) -> Plan:
    """Plan one query with a fitted model (Alg. 1): the query `make_problem` makes of the
    arguments (``config`` defaults to the model's), grown into a tree by `RRTCoLearn`; with
    ``plan.anytime`` the whole limit is spent on restarts whose paths are shortcut, inside
    and to the goal (`anytime.solve_with_restarts`, `planning.improve.shortcut`), each new
    best path first by multiple shooting on an allowance of its own
    (`planning.improve.multiple_shooting`), the cheapest path its step resolves kept
    (`evaluate.step_check`); with ``plan.polish`` (and not anytime) the first
    solution gets one such round (`POLISH_ALLOWANCE`), its raw and polished costs in
    ``extra["polish"]``."""
    cfg = config or model.config
    _check_limits(seed, time_limit, max_iterations)
    problem = make_problem(model.system, cfg, start, goal, goal_tolerance, u_max=u_max,
                           obstacles=obstacles, is_valid=is_valid, goal_fn=goal_fn,
                           goal_sampler=goal_sampler)
    planner = RRTCoLearn(problem, model.functions, model.planner_settings(config))
    termination = TerminationCondition(time_limit, max_iterations)
    # the plan's step against half of it (`evaluate.step_check`): whether the step resolves
    # the path, anytime planning's verdict and the plan's record, each path replayed once
    checks = StepChecks(problem)
    if cfg.plan.anytime or cfg.plan.polish:
        # anytime: the whole budget, restarts, each path shortcut, the cheapest kept;
        # polish: the first solve and its one improvement round only
        from functools import partial

        from rrtcolearn.anytime import solve_with_restarts
        from rrtcolearn.planning.improve import multiple_shooting, shortcut

        polish = not cfg.plan.anytime
        result = solve_with_restarts(planner.solve, termination, seed,
                                     improve=partial(shortcut, planner, accept=checks),
                                     narrowest=planner.narrowest_control_scale(),
                                     first=partial(multiple_shooting, planner),
                                     accept=checks,
                                     **({"solves": 1, "allowance": POLISH_ALLOWANCE,
                                         "in_steps": True} if polish else {}))
        if polish:
            result.extra["polish"] = _polish_record(result)
    else:
        result = planner.solve(termination, seed)
    if result.solved:  # reported and warned about, never silently trusted
        result.extra["step_check"] = checks.check(result)
    result.extra["seed"] = int(seed) if isinstance(seed, (int, np.integer)) else None
    result.extra["config"] = cfg.model_dump(mode="json")
    return result


def _check_limits(seed, time_limit, max_iterations) -> None:
    """`plan`'s seed and limits as the command line checks them: a ProblemError for a
    negative or non-integer seed, a time limit that is not a positive number, or an
    iteration limit that is not a positive integer (each would otherwise end in numpy's
    own error or in a plan that stops before its first iteration)."""
    if isinstance(seed, (bool, float)) or (isinstance(seed, (int, np.integer)) and seed < 0):
        raise ProblemError(f"seed must be a non-negative integer, got {seed!r}")
    if time_limit is not None and (isinstance(time_limit, bool) or not isinstance(
            time_limit, (int, float, np.integer, np.floating)) or not time_limit > 0
            or not np.isfinite(time_limit)):
        raise ProblemError(f"time_limit must be a positive number of seconds (or None), "
                           f"got {time_limit!r}")
    if max_iterations is not None and (isinstance(max_iterations, bool) or not isinstance(
            max_iterations, (int, np.integer)) or max_iterations < 1):
        raise ProblemError(f"max_iterations must be a positive integer (or None), got "
                           f"{max_iterations!r}")


PLAN_FORMAT = "rrtcolearn.plan"
PLAN_SCHEMA = 1


def write_plan(p: Plan, path: str | Path) -> None:
    """Write the plan file (JSON, see docs/formats.md) with its checksum."""
    write_checked_json(path, {"format": PLAN_FORMAT, "schema_version": PLAN_SCHEMA,
                              "package_version": __version__, **p.to_dict()})


def _recorded_limits(d: dict) -> dict:
    """The system section's input limits of a plan that saturated its inputs, from the box
    the plan file records (a plan without its configuration)."""
    low, high = d.get("input_low"), d.get("input_high")
    if d.get("limit_mode") != "saturate" or not isinstance(low, list) or \
            not isinstance(high, list) or None in low or None in high:
        return {}
    if all(lo == -hi for lo, hi in zip(low, high, strict=False)):
        return {"u_max": high[0] if len(high) == 1 else high}
    return {"u_low": low, "u_high": high}


def plan_system(d: dict, system: str | None = None) -> System:
    """The system a plan file's content (`read_plan`) was planned on, rebuilt from the
    configuration the plan records (a registered name or module:attribute, its limits), or
    by ``system`` (`recorded_system`)."""
    if not isinstance(d.get("config"), dict):
        # a plan of the Planner API written as it is: only its system's name is recorded
        if system is None:
            raise ConfigError("the plan file records no configuration: it cannot say which "
                              "system to re-simulate it on (give it: --system NAME or "
                              "module:attribute)")
        d = {**d, "config": {"system": {"name": system, **_recorded_limits(d)}}}
    _, system = recorded_system(validate(d["config"]), d.get("system"), system, "the plan")
    if system.name != d.get("system"):
        raise ConfigError(f"the plan is for system {d.get('system')!r}, its configuration "
                          f"builds {system.name!r}")
    return system


def read_plan(path: str | Path) -> dict:
    """A checked plan file."""
    return read_checked_json(path, PLAN_FORMAT, PLAN_SCHEMA, "plan file")

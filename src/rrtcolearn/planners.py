"""The `Planner` contract and its registry: ``make("random-rrt")``, ``register(name, factory)``,
``list_planners()`` (Gymnasium's registry, OMPL's ``Planner::solve``).

A planner is built with its hyper-parameters only (a learned planner also takes its fitted
model) and answers any `PlanningProblem` it supports:
``planner.solve(problem, termination, seed) -> Plan``. Every planner returns the same `Plan`
(`rrtcolearn.planning.tree.Plan`), whose path `rrtcolearn.evaluate.replay` re-simulates from
its recorded costates or controls, and ``planner.supports(problem)`` says why it cannot take
a problem (None when it can), e.g. the direct method's collocation is written for the
pendulum, OMPL's planners need ompl installed and, like every random-control planner, an
input box.

Registered: "rrtcolearn" (needs ``model``, a `rrtcolearn.pipeline.FittedModel`),
"random-rrt", "ompl-RRT", "ompl-KPIECE1", "ompl-EST" and "direct" (needs ``model``, a
`rrtcolearn.baselines.direct.DirectModel`). Factories import their modules on use: OMPL and
CasADi are optional.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from rrtcolearn.planning.problem import PlanningProblem, is_own_limit
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan

if TYPE_CHECKING:
    from rrtcolearn.pipeline import FittedModel


@runtime_checkable
class Planner(Protocol):
    """What every planner implements."""

    name: str

    def supports(self, problem: PlanningProblem) -> str | None:
        """None if the planner can plan ``problem``, else the reason it cannot."""

    def solve(self, problem: PlanningProblem, termination: TerminationCondition,
              seed: int = 0) -> Plan:
        """Plan ``problem`` until its goal region is reached or ``termination`` says stop;
        the same ``seed`` gives the same plan."""


_REGISTRY: dict[str, Callable[..., Planner]] = {}


def register(name: str, factory: Callable[..., Planner]) -> None:
    """Make ``factory(**params)`` available as ``make(name, **params)``."""
    _REGISTRY[name] = factory


def list_planners() -> list[str]:
    """Names of the registered planners, in registration order."""
    return list(_REGISTRY)


def make(name: str, **params) -> Planner:
    """Build planner ``name`` with ``params``; ValueError with the known names otherwise."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown planner {name!r}; known planners: "
                         f"{', '.join(_REGISTRY)}") from None
    return factory(**params)


class RRTCoLearnPlanner:
    """RRT-CoLearn (`rrtcolearn.planning.rrt.RRTCoLearn`) with a fitted ``model``, planning
    with the model's configuration (time weight, derived planner settings)."""

    name = "rrtcolearn"

    def __init__(self, model: FittedModel | None = None, *, time_weight: float | None = None):
        if model is not None and time_weight is not None and \
                abs(time_weight - model.config.system.time_weight) > 1e-12:
            raise ValueError(f"the model was fitted with time weight "
                             f"{model.config.system.time_weight:g}, not {time_weight:g}")
        self.model = model
        self.time_weight = time_weight

    def supports(self, problem: PlanningProblem) -> str | None:
        """None, or why the model cannot plan ``problem`` (another system, or a u_max that
        is not the limits the model saturates at)."""
        if self.model is None:
            return None
        system = self.model.system
        if problem.system.name != system.name or problem.system.n_states != system.n_states:
            return f"the model is for system {system.name!r}, not {problem.system.name!r}"
        if system.input_limited and problem.u_max is not None and \
                not is_own_limit(system, problem.u_max):
            return (f"the model saturates its inputs at the limits it learned with; plan with "
                    f"u_max None (or those limits), not {problem.u_max}")
        return None

    def solve(self, problem: PlanningProblem, termination: TerminationCondition,
              seed: int = 0) -> Plan:
        """Alg. 1 on ``problem`` (`RRTCoLearn.solve`)."""
        from rrtcolearn.planning.rrt import RRTCoLearn

        if self.model is None:
            raise ValueError("the rrtcolearn planner needs a fitted model (pipeline.fit or "
                             "pipeline.load_model)")
        reason = self.supports(problem)
        if reason is not None:
            raise ValueError(reason)
        plan = RRTCoLearn(problem, self.model.functions,
                          self.model.planner_settings()).solve(termination, seed)
        plan.extra["planner"] = self.name
        return plan


class PlannerCheckError(AssertionError):
    """A planner broke the `Planner` contract (`check_planner`)."""


def check_planner(planner: Planner, problem: PlanningProblem, *, time_limit: float = 30.0,
                  max_iterations: int | None = None, seed: int = 0,
                  require_solution: bool = True) -> Plan:
    """Check ``planner`` against the contract on ``problem`` (OMPL's PlannerTest, scikit-learn's
    check_estimator); returns its plan, raises `PlannerCheckError` naming the broken clause.

    The plan is a `Plan` that solves ``problem`` (with ``require_solution``); re-simulated
    from the start (`rrtcolearn.evaluate.replay`) its path keeps the inputs in the box, the
    states in the constraints and out of obstacles, ends where the plan says, costs what it
    says and reaches the goal exactly when the plan claims so; every edge re-simulated from
    its stored start ends at its stored end; and the same seed gives the same plan.
    ``max_iterations`` makes the check independent of the machine's speed for planners that
    count iterations; ``time_limit`` stays as the backstop for those that do not (OMPL's).
    """
    from rrtcolearn.evaluate import replay, resimulate

    def require(cond: bool, what: str) -> None:
        if not cond:
            raise PlannerCheckError(f"planner {planner.name!r} on {problem.system.name!r}: "
                                    f"{what}")

    reason = planner.supports(problem)
    require(reason is None, f"does not support the problem: {reason}")
    plan = planner.solve(problem, TerminationCondition(time_limit, max_iterations), seed)
    require(isinstance(plan, Plan), f"solve returned a {type(plan).__name__}, not a Plan")
    require(plan.solved or not require_solution, f"no solution ({plan.status})")
    check = replay(problem, plan)
    require(check["inputs_in_box"], "an input outside the input box")
    require(check["valid"], "a re-simulated state outside the constraints or in an obstacle")
    require(check["reaches_goal"] == plan.solved,
            f"claims solved={plan.solved}, the re-simulation says {check['reaches_goal']}")
    scale = max(1.0, abs(plan.path_cost))
    require(abs(check["path_cost"] - plan.path_cost) <= 1e-6 * scale,
            f"path cost {plan.path_cost} but re-simulated {check['path_cost']}")
    if plan.final_goal_distance is not None:
        require(abs(check["final_goal_distance"] - plan.final_goal_distance) <= 1e-6,
                f"ends {plan.final_goal_distance} from the goal, re-simulated "
                f"{check['final_goal_distance']}")
    gaps = resimulate(problem.system, plan)
    require(gaps["max_gap"] <= 1e-6, f"an edge ends {gaps['max_gap']} from its stored end")
    again = planner.solve(problem, TerminationCondition(time_limit, max_iterations), seed)
    same = again.nodes == plan.nodes and again.path_nodes == plan.path_nodes and all(
        a == b for a, b in zip(again.edges(), plan.edges(), strict=True))
    require(same, f"seed {seed} gave two different plans")
    return plan


def _random_rrt(**params) -> Planner:
    from rrtcolearn.baselines.random_rrt import RandomControlRRT

    return RandomControlRRT(**params)


def _ompl(planner: str) -> Callable[..., Planner]:
    def factory(**params) -> Planner:
        from rrtcolearn.baselines.ompl_planners import OMPLPlanner

        return OMPLPlanner(planner, **params)

    return factory


def _direct(**params) -> Planner:
    from rrtcolearn.baselines.direct import DirectPlanner

    return DirectPlanner(**params)


register("rrtcolearn", RRTCoLearnPlanner)
register("random-rrt", _random_rrt)
for _name in ("RRT", "KPIECE1", "EST"):
    register(f"ompl-{_name}", _ompl(_name))
register("direct", _direct)

__all__ = ["Planner", "PlannerCheckError", "RRTCoLearnPlanner", "check_planner", "list_planners",
           "make", "register"]

"""Online planning: problem definition, termination, tree data and RRT-CoLearn (Alg. 1)."""

from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import PlannerSettings, RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan, PlannerData

__all__ = [
    "Plan",
    "PlannerData",
    "PlannerSettings",
    "PlanningProblem",
    "RRTCoLearn",
    "TerminationCondition",
]

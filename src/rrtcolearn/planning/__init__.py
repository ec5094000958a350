"""Online planning: problem definition, termination, tree data and RRT-CoLearn (Alg. 1).

The planner is one loop (`rrt.RRTCoLearn`) over strategies behind two small contracts
(`contracts.Steering`: the learned steering, random controls; `contracts.Connection`:
shooting, the goal funnel, the LQR loop, or your own), switched on by one schedule
(`schedule`). docs/architecture.md shows the loop and the contracts in one picture.
"""

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

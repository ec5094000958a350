"""Planners users compare RRT-CoLearn with (its peers), run on the same problems; each is a
`rrtcolearn.planners.Planner` (``rrtcolearn.planners.make("random-rrt")``)."""

from rrtcolearn.baselines.base import control_plan, in_goal, input_box

__all__ = ["control_plan", "in_goal", "input_box"]

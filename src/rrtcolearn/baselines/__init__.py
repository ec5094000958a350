"""Planners users compare RRT-CoLearn with, run in the same harness on the same problems."""

from rrtcolearn.baselines.base import BaselineResult, ControlPath, path_metrics, simulate_controls

__all__ = ["BaselineResult", "ControlPath", "path_metrics", "simulate_controls"]

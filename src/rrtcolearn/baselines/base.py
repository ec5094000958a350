"""Common result type of baseline planners and an independent re-simulation of their paths.

Baselines choose inputs directly: their paths are piecewise-constant controls, re-simulated
here with RK4 on the plain dynamics f(x, u) so every planner's figures come from one check.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rrtcolearn.integrate import propagate_controls
from rrtcolearn.systems.base import System


@dataclass
class ControlPath:
    """Piecewise-constant inputs from ``start``: ``controls[k]`` (m,) held for ``durations[k]``."""

    start: np.ndarray  # (n,)
    controls: np.ndarray  # (K, m)
    durations: np.ndarray  # (K,) seconds, multiples of the propagation step


@dataclass
class BaselineResult:
    """One planning run of a baseline planner."""

    planner: str
    solved: bool
    status: str  # "exact", "approximate" or "timeout"
    cpu_s: float
    wall_s: float
    iterations: int
    nodes: int
    path: ControlPath | None
    extra: dict = field(default_factory=dict)


def simulate_controls(system: System, path: ControlPath, dt: float) -> np.ndarray:
    """States (S+1, n) at every RK4 step of ``dt`` along the path."""
    steps = np.round(np.asarray(path.durations, dtype=np.float64) / dt).astype(np.int64)
    return propagate_controls(system, path.start, path.controls, steps, dt)


def path_metrics(system: System, path: ControlPath | None, dt: float, time_weight: float,
                 goal: np.ndarray, goal_tolerance: float) -> dict:
    """Cost (integral of w + u^2/2), duration, max |u| and end-to-goal distance, re-simulated."""
    if path is None or len(path.durations) == 0:
        return {"path_cost": 0.0, "path_duration": 0.0, "max_abs_u": 0.0,
                "final_goal_distance": None, "reaches_goal": False}
    states = simulate_controls(system, path, dt)
    u2 = np.sum(np.asarray(path.controls, dtype=np.float64) ** 2, axis=1)
    cost = float(np.sum((time_weight + 0.5 * u2) * path.durations))
    gap = float(np.linalg.norm(states[-1] - goal))
    return {
        "path_cost": cost,
        "path_duration": float(np.sum(path.durations)),
        "max_abs_u": float(np.abs(path.controls).max()),
        "final_goal_distance": gap,
        "reaches_goal": gap <= goal_tolerance + 1e-9,
    }

"""A planning query: start state, goal region, and the state box it must lie in."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from rrtcolearn.errors import RRTCoLearnError
from rrtcolearn.planning.validity import (
    Obstacle,
    ObstacleChecker,
    StateValidityChecker,
    obstacle_from_dict,
)
from rrtcolearn.systems.base import System


class ProblemError(RRTCoLearnError, ValueError):
    """A planning query that cannot be planned (bad start, goal or tolerance)."""


def check_state(system: System, value, what: str) -> np.ndarray:
    """Validate a state: the right length, finite, inside the system's sampling box."""
    try:
        x = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ProblemError(f"{what} must be {system.n_states} numbers, got {value!r}") from None
    if x.shape != (system.n_states,):
        raise ProblemError(f"{what} must have {system.n_states} coordinates "
                           f"({', '.join(system.state_names)}), got {x.size}")
    if not np.all(np.isfinite(x)):
        raise ProblemError(f"{what} must be finite, got {x.tolist()}")
    outside = (x < system.state_low) | (x > system.state_high)
    if outside.any():
        j = int(np.flatnonzero(outside)[0])
        raise ProblemError(
            f"{what} {system.state_names[j]}={x[j]:g} is outside the state box "
            f"[{system.state_low[j]:g}, {system.state_high[j]:g}]")
    return x


@dataclass(frozen=True)
class PlanningProblem:
    """Plan from ``start`` to the ball of radius ``goal_tolerance`` around ``goal``.

    The goal test is the Euclidean distance in state coordinates (paper Experiments); with
    ``wrap_goal`` angle coordinates are compared modulo a turn (upright is upright, whichever
    way round the tree got there).
    ``u_max`` bounds |u| along every edge (None: unbounded, the paper's setting);
    ``validity`` is the state validity checker (obstacles), checked at every RK4 step.
    """

    system: System
    start: np.ndarray
    goal: np.ndarray
    goal_tolerance: float = 0.1
    u_max: float | None = None
    validity: ObstacleChecker = field(default_factory=ObstacleChecker)
    wrap_goal: bool = False

    @classmethod
    def create(cls, system: System, start, goal, goal_tolerance: float = 0.1, *,
               u_max: float | None = None,
               obstacles: Sequence[Obstacle | dict] = (),
               is_valid: StateValidityChecker | None = None,
               wrap_goal: bool = False) -> PlanningProblem:
        """Validated problem; raises ProblemError with a one-line reason."""
        start = check_state(system, start, "start")
        goal = check_state(system, goal, "goal")
        try:
            tol = float(goal_tolerance)
        except (TypeError, ValueError):
            tol = float("nan")
        if not np.isfinite(tol) or tol <= 0:
            raise ProblemError(f"goal tolerance must be a positive number, got {goal_tolerance!r}")
        if u_max is not None and not (np.isfinite(u_max) and u_max > 0):
            raise ProblemError(f"u_max must be a positive number, got {u_max!r}")
        try:
            built = [o if isinstance(o, Obstacle) else obstacle_from_dict(o, system.n_states)
                     for o in obstacles]
        except (KeyError, TypeError, ValueError) as exc:
            raise ProblemError(f"invalid obstacle: {exc}") from None

        def wrap(x: np.ndarray) -> np.ndarray:
            return x + system.wrap_shift(x)

        validity = ObstacleChecker(built, is_valid, wrap)
        if validity:
            for what, x in (("start", start), ("goal", goal)):
                if not validity(x[None])[0]:
                    raise ProblemError(f"the {what} {x.tolist()} lies inside an obstacle")
        return cls(system, start, goal, tol, None if u_max is None else float(u_max),
                   validity, bool(wrap_goal))

    def within_bounds(self, x: np.ndarray) -> np.ndarray:
        """(N,) True where states (N, n) lie inside the state box in its non-angle coordinates.

        Angles are unbounded: the dynamics are periodic in them.
        """
        x = np.atleast_2d(x)
        dims = self.system.bounded_dims
        return np.all((x[:, dims] >= self.system.state_low[dims])
                      & (x[:, dims] <= self.system.state_high[dims]), axis=1)

    @property
    def goal_angles(self) -> tuple[int, ...]:
        """Coordinates compared modulo a turn in the goal test."""
        return tuple(self.system.angle_dims) if self.wrap_goal else ()

    def goal_offset(self, x: np.ndarray) -> np.ndarray:
        """x - goal (N, n), angle coordinates the short way round when ``wrap_goal``."""
        diff = np.atleast_2d(x) - self.goal
        angles = list(self.goal_angles)
        if angles:
            diff[:, angles] = np.mod(diff[:, angles] + np.pi, 2.0 * np.pi) - np.pi
        return diff

    def goal_distance(self, x: np.ndarray) -> np.ndarray:
        """Euclidean distance of states (N, n) to the goal (see ``wrap_goal``)."""
        return np.linalg.norm(self.goal_offset(x), axis=1)

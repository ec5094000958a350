"""A planning query: start state, goal region, and the state box it must lie in."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from rrtcolearn.errors import RRTCoLearnError
from rrtcolearn.planning.validity import (
    Obstacle,
    ObstacleChecker,
    StateValidityChecker,
    in_turn,
    obstacle_from_dict,
)
from rrtcolearn.systems.base import System


class ProblemError(RRTCoLearnError, ValueError):
    """A planning query that cannot be planned (bad start, goal or tolerance)."""


def check_state(system: System, value, what: str, low: np.ndarray | None = None,
                high: np.ndarray | None = None) -> np.ndarray:
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
    low = system.state_low if low is None else low
    high = system.state_high if high is None else high
    outside = (x < low) | (x > high)
    if outside.any():
        j = int(np.flatnonzero(outside)[0])
        hint = ""
        if j in system.angle_dims:  # the same angle inside the box, where there is one
            same = low[j] + np.mod(x[j] - low[j], 2.0 * np.pi)
            if same <= high[j]:
                hint = f" (an angle: give it within the box, e.g. {same:.6g})"
        raise ProblemError(
            f"{what} {system.state_names[j]}={x[j]:g} is outside the state box "
            f"[{low[j]:g}, {high[j]:g}]{hint}")
    return x


def obstacle_checker(system: System, obstacles: Sequence[Obstacle],
                     is_valid: StateValidityChecker | None = None) -> ObstacleChecker:
    """The validity test of ``obstacles`` (and a user's ``is_valid``) on ``system``: states
    wrapped by whole turns into the sampling box's turn of each angle, and the boxes moved
    into that turn (`validity.in_turn`), so an obstacle covers its region on every turn.
    A problem and `evaluate.check_plan` test obstacles by this one checker."""
    def wrap(x: np.ndarray) -> np.ndarray:
        return x + system.wrap_shift(x)

    return ObstacleChecker(in_turn(obstacles, {j: float(system.state_low[j])
                                                for j in system.angle_dims}), is_valid, wrap)


def is_own_limit(system: System, u_max) -> bool:
    """Whether ``u_max`` (a number or one per input) is the symmetric input box ``system``
    saturates at: a model of it plans under that limit as it is (none other)."""
    if not system.input_limited:
        return False
    low, high = system.input_limits()
    wanted = np.broadcast_to(np.asarray(u_max, dtype=float), low.shape)
    return bool(np.array_equal(-low, high) and np.array_equal(high, wanted))


def state_bounds(system: System, low=None, high=None) -> tuple[np.ndarray, np.ndarray]:
    """The planner's state constraints: ``low``/``high`` (n values, None entries or None for
    the system's sampling box) over the box; ProblemError if malformed. Angle coordinates keep
    the box (the dynamics are periodic in them): a value there that would narrow it (a joint
    limit, which the planner does not enforce on an angle) is a ProblemError, not ignored."""
    out = []
    for value, box, what, sign in ((low, system.state_low, "state_low", 1.0),
                                   (high, system.state_high, "state_high", -1.0)):
        b = np.array(box, dtype=np.float64)
        if value is not None:
            if len(value) != system.n_states:
                raise ProblemError(f"{what} needs {system.n_states} values (None keeps the "
                                   f"sampling box), got {len(value)}")
            for j, v in enumerate(value):
                if v is not None and j in system.angle_dims and sign * (float(v) - b[j]) > 0:
                    name = system.state_names[j]
                    raise ProblemError(
                        f"{what}: {name}={float(v):g} narrows the box [{system.state_low[j]:g}"
                        f", {system.state_high[j]:g}] of an angle, which the planner wraps and "
                        f"does not bound: give None there (a joint limit needs {name} declared "
                        "without angle_dims)")
                if v is not None and j not in system.angle_dims:
                    if not np.isfinite(v):
                        raise ProblemError(f"{what} must be finite numbers or None")
                    b[j] = float(v)
        out.append(b)
    if np.any(out[0] >= out[1]):
        raise ProblemError(f"state constraints need state_low < state_high, got "
                           f"{out[0].tolist()} and {out[1].tolist()}")
    return out[0], out[1]


GoalDistance = Callable[[np.ndarray], np.ndarray]
"""A user goal: states (N, n) -> distance (N,) to the goal region; the goal is reached where
it is at most the goal tolerance (OMPL's GoalRegion::distanceGoal)."""
GoalSampler = Callable[[np.random.Generator], np.ndarray]
"""Draws one goal state (n,) (OMPL's GoalSampleableRegion::sampleGoal)."""


def _goal_weights(system: System, weights) -> np.ndarray | None:
    """(n,) non-negative goal weights with a positive one, or None (all 1)."""
    if weights is None:
        return None
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError):
        raise ProblemError(f"goal_weights must be {system.n_states} numbers") from None
    if w.shape != (system.n_states,) or not np.all(np.isfinite(w)) or np.any(w < 0) \
            or not np.any(w > 0):
        raise ProblemError(f"goal_weights needs {system.n_states} finite non-negative "
                           f"numbers, not all zero (0: a free coordinate), got {weights!r}")
    return None if np.all(w == 1) else w


@dataclass(frozen=True)
class PlanningProblem:
    """Plan from ``start`` to the ball of radius ``goal_tolerance`` around ``goal``.

    The goal test is the Euclidean distance in state coordinates (paper Experiments); with
    ``wrap_goal`` angle coordinates are compared modulo a turn (upright is upright, whichever
    way round the tree got there). ``goal_weights`` (n,) weight the coordinates in that
    distance (0: a free coordinate, e.g. velocities free). A user goal region replaces the
    ball: ``goal_fn`` gives the distance to it and ``goal_sampler`` draws states in it (the
    targets of goal-biased iterations); ``goal`` is then a state in the region, where the goal
    connections aim.
    ``u_max`` bounds |u| along every edge (None: unbounded, the paper's setting);
    ``validity`` is the state validity checker (obstacles), checked at every RK4 step.
    ``state_low``/``state_high`` are the state constraints: an edge that leaves them in a
    non-angle coordinate is invalid. They default to the system's sampling box and may differ
    from it (`state_bounds`): a user states "|omega| <= 7" without changing the data.
    """

    system: System
    start: np.ndarray
    goal: np.ndarray
    goal_tolerance: float = 0.1
    u_max: float | None = None
    validity: ObstacleChecker = field(default_factory=ObstacleChecker)
    wrap_goal: bool = False
    state_low: np.ndarray | None = None
    state_high: np.ndarray | None = None
    goal_weights: np.ndarray | None = None
    goal_fn: GoalDistance | None = None
    goal_sampler: GoalSampler | None = None

    def __post_init__(self) -> None:
        if self.state_low is None or self.state_high is None:
            low, high = state_bounds(self.system)
            object.__setattr__(self, "state_low", low)
            object.__setattr__(self, "state_high", high)

    @classmethod
    def create(cls, system: System, start, goal, goal_tolerance: float = 0.1, *,
               u_max: float | None = None,
               obstacles: Sequence[Obstacle | dict] = (),
               is_valid: StateValidityChecker | None = None,
               wrap_goal: bool = False, state_low=None, state_high=None,
               goal_weights=None, goal_fn: GoalDistance | None = None,
               goal_sampler: GoalSampler | None = None) -> PlanningProblem:
        """Validated problem; raises ProblemError with a one-line reason."""
        low, high = state_bounds(system, state_low, state_high)
        start = check_state(system, start, "start", low, high)
        goal = check_state(system, goal, "goal", low, high)
        weights = _goal_weights(system, goal_weights)
        if goal_sampler is not None and goal_fn is None:
            raise ProblemError("a goal sampler needs its goal function (goal_fn)")
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
        validity = obstacle_checker(system, built, is_valid)
        if validity:
            for what, x in (("start", start), ("goal", goal)):
                if not validity(x[None])[0]:
                    raise ProblemError(f"the {what} {x.tolist()} lies inside an obstacle")
        problem = cls(system, start, goal, tol, None if u_max is None else float(u_max),
                      validity, bool(wrap_goal), low, high, weights, goal_fn, goal_sampler)
        if goal_fn is not None:
            problem._check_goal_region()
        return problem

    def _check_goal_region(self) -> None:
        """The user goal function and sampler answer in the right shapes, and ``goal`` and the
        sampler's states lie in the region."""
        try:
            d = np.asarray(self.goal_fn(np.stack([self.goal, self.start])), dtype=np.float64)
        except Exception as exc:
            raise ProblemError(f"the goal function failed on (goal, start): {exc}") from None
        if d.shape != (2,) or not np.all(np.isfinite(d)):
            raise ProblemError(f"the goal function must map states (N, n) to N finite "
                               f"distances, got {d!r} for 2 states")
        if d[0] > self.goal_tolerance:
            raise ProblemError(f"the goal state {self.goal.tolist()} is not in the goal region "
                               f"(distance {d[0]:g} > tolerance {self.goal_tolerance:g})")
        if self.goal_sampler is not None:
            rng = np.random.default_rng(0)
            x = np.asarray(self.goal_sampler(rng), dtype=np.float64)
            if x.shape != self.goal.shape or not np.all(np.isfinite(x)):
                raise ProblemError(f"the goal sampler must return one finite state of "
                                   f"{self.goal.size} numbers, got {x!r}")
            if self.goal_distance(x)[0] > self.goal_tolerance:
                raise ProblemError(f"the goal sampler drew {x.tolist()}, outside the goal "
                                   "region")

    @property
    def constraint_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) (n,) of the state constraints, +-inf in the angle coordinates (the
        box `within_bounds` tests, as arrays a compiled loop can compare against)."""
        n = self.system.n_states
        low, high = np.full(n, -np.inf), np.full(n, np.inf)
        dims = self.system.bounded_dims
        low[dims], high[dims] = self.state_low[dims], self.state_high[dims]
        return low, high

    def within_bounds(self, x: np.ndarray) -> np.ndarray:
        """(N,) True where states (N, n) lie inside the state box in its non-angle coordinates.

        Angles are unbounded: the dynamics are periodic in them.
        """
        x = np.atleast_2d(x)
        dims = self.system.bounded_dims
        return np.all((x[:, dims] >= self.state_low[dims])
                      & (x[:, dims] <= self.state_high[dims]), axis=1)

    @property
    def goal_angles(self) -> tuple[int, ...]:
        """Coordinates compared modulo a turn in the goal test."""
        return tuple(self.system.angle_dims) if self.wrap_goal else ()

    def goal_offset(self, x: np.ndarray) -> np.ndarray:
        """x - goal (N, n), angle coordinates the short way round when ``wrap_goal``."""
        return self.offset_to(x, self.goal)

    def offset_to(self, x: np.ndarray, target: np.ndarray) -> np.ndarray:
        """x - target (N, n), angles as in `goal_offset`."""
        diff = np.atleast_2d(x) - target
        angles = list(self.goal_angles)
        if angles:
            diff[:, angles] = np.mod(diff[:, angles] + np.pi, 2.0 * np.pi) - np.pi
        return diff

    def goal_residual(self, x: np.ndarray) -> np.ndarray:
        """``goal_offset`` weighted by ``goal_weights`` (N, n): the equations a goal
        connection solves (free coordinates give none)."""
        diff = self.goal_offset(x)
        return diff if self.goal_weights is None else diff * self.goal_weights

    @property
    def goal_test(self) -> str:
        """How the goal is tested, as a plan file records it (`evaluate.check_plan`): "ball"
        (the weighted, wrapped ball around ``goal``), "system" (the system's own goal region
        from its ``defaults``) or "function" (a user's, which the file cannot hold)."""
        if self.goal_fn is None:
            return "ball"
        return "system" if self.goal_fn is self.system.defaults.get("goal_fn") else "function"

    def goal_distance(self, x: np.ndarray) -> np.ndarray:
        """Distance of states (N, n) to the goal region: the user's ``goal_fn``, else the
        weighted Euclidean distance to ``goal`` (see ``wrap_goal``, ``goal_weights``)."""
        if self.goal_fn is not None:
            # checked on every call, as the validity checker's answers are: a wrong shape or
            # a NaN later in a plan would otherwise cut edges wrongly or end the path there
            x = np.atleast_2d(x)
            d = np.asarray(self.goal_fn(x), dtype=np.float64)
            if d.shape != (len(x),) or not np.all(np.isfinite(d)):
                bad = "" if d.shape != (len(x),) else \
                    f"; not finite at {x[int(np.flatnonzero(~np.isfinite(d))[0])].tolist()}"
                raise ProblemError(f"the goal function must map states (N, n) to N finite "
                                   f"distances: got shape {d.shape} for {len(x)} states{bad}")
            return d
        return np.linalg.norm(self.goal_residual(x), axis=1)

    def sample_goal(self, rng: np.random.Generator) -> np.ndarray:
        """A goal-biased iteration's target: the user sampler's draw; with free coordinates
        (weight 0) the goal with those drawn uniformly from the state constraints; else the
        goal itself (drawing nothing: the paper's planner)."""
        if self.goal_sampler is not None:
            x = np.asarray(self.goal_sampler(rng), dtype=np.float64)
            if x.shape != self.goal.shape or not np.all(np.isfinite(x)):
                raise ProblemError(f"the goal sampler must return one finite state of "
                                   f"{self.goal.size} values, got {x.tolist()}")
            return x
        if self.goal_weights is None or np.all(self.goal_weights > 0):
            return self.goal
        free = self.goal_weights == 0
        x = self.goal.copy()
        x[free] = rng.uniform(self.state_low[free], self.state_high[free])
        return x

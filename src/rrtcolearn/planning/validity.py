"""State validity: obstacles in state space (OMPL's StateValidityChecker, batched).

A checker maps states (N, n) to a (N,) bool array, True where the state is allowed. The
library ships axis-aligned boxes and half-planes, and a robot's body among workspace shapes
(`rrtcolearn.geometry.Workspace`); any callable with that signature works too.
Obstacles are an online concern: the same dataset and models serve any set of them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from rrtcolearn.geometry import Workspace

StateValidityChecker = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Box:
    """Forbidden closed box ``low <= x <= high`` (every coordinate)."""

    low: np.ndarray
    high: np.ndarray

    def contains(self, x: np.ndarray) -> np.ndarray:
        return np.all((x >= self.low) & (x <= self.high), axis=1)

    def to_dict(self) -> dict:
        return {"type": "box", "low": self.low.tolist(), "high": self.high.tolist()}


@dataclass(frozen=True)
class HalfPlane:
    """Forbidden half-space ``normal . x > offset``."""

    normal: np.ndarray
    offset: float

    def contains(self, x: np.ndarray) -> np.ndarray:
        return x @ self.normal > self.offset

    def to_dict(self) -> dict:
        return {"type": "halfplane", "normal": self.normal.tolist(), "offset": self.offset}


Obstacle = Box | HalfPlane | Workspace


def obstacle_from_dict(spec: dict, n_states: int) -> Obstacle:
    """Build an obstacle from its config form; ValueError on a malformed one."""
    if not isinstance(spec, Mapping):
        raise TypeError(f"an obstacle is an Obstacle or a dict such as {{'type': 'box', "
                        f"'low': [...], 'high': [...]}} or {{'type': 'halfplane', 'normal': "
                        f"[...], 'offset': ...}}, not {spec!r:.60} ({type(spec).__name__})")
    kind = spec.get("type")
    if kind == "box":
        low = np.asarray(spec["low"], dtype=np.float64)
        high = np.asarray(spec["high"], dtype=np.float64)
        if low.shape != (n_states,) or high.shape != (n_states,):
            raise ValueError(f"a box needs {n_states} low and {n_states} high values")
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError("box bounds must be finite")
        if np.any(low > high):
            raise ValueError("box low must not exceed high")
        return Box(low, high)
    if kind == "halfplane":
        normal = np.asarray(spec["normal"], dtype=np.float64)
        offset = float(spec["offset"])
        if normal.shape != (n_states,) or not np.all(np.isfinite(normal)):
            raise ValueError(f"a half-plane needs a finite normal of {n_states} values")
        if not np.any(normal) or not np.isfinite(offset):
            raise ValueError("a half-plane needs a non-zero normal and a finite offset")
        return HalfPlane(normal, offset)
    if kind == "workspace":
        return Workspace.from_dict(spec, n_states)
    raise ValueError(f"unknown obstacle type {kind!r}; use 'box', 'halfplane' or 'workspace'")


def in_turn(obstacles: Sequence[Obstacle], angle_low: dict[int, float]) -> list[Obstacle]:
    """The obstacles with every box moved, on each angle coordinate ``j`` (``angle_low``: j
    -> the state box's low there), by whole turns into the turn [low, low + 2 pi) the
    checker wraps states into, split in two where it crosses that turn's end and the whole
    turn where it spans one: an obstacle covers its region on every turn, wherever it was
    given. Half-planes are tested on the wrapped states as they are."""
    two_pi = 2.0 * np.pi
    out: list[Obstacle] = []
    for ob in obstacles:
        pieces = [ob]
        if isinstance(ob, Box):
            for j, low in angle_low.items():
                split = []
                for b in pieces:
                    lo, hi = float(b.low[j]), float(b.high[j])
                    if hi - lo >= two_pi:  # the whole turn
                        lo, hi = low, low + two_pi
                    else:
                        shift = two_pi * np.floor((lo - low) / two_pi)
                        lo, hi = lo - shift, hi - shift
                    parts = [(lo, min(hi, low + two_pi))]
                    if hi > low + two_pi:  # across the turn's end: the rest at its start
                        parts.append((low, hi - two_pi))
                    for a, c in parts:
                        b_low, b_high = b.low.copy(), b.high.copy()
                        b_low[j], b_high[j] = a, c
                        split.append(Box(b_low, b_high))
                pieces = split
        out.extend(pieces)
    return out


class ObstacleChecker:
    """Valid where no obstacle contains the state and the user's checker (if any) agrees.

    ``wrap`` maps states before the test; the planner passes the system's shift of angle
    coordinates into the state box, and its boxes moved into that turn (`in_turn`), so an
    obstacle covers its region on every turn.
    """

    def __init__(self, obstacles: Sequence[Obstacle] = (),
                 user_checker: StateValidityChecker | None = None,
                 wrap: Callable[[np.ndarray], np.ndarray] | None = None):
        self.obstacles = tuple(obstacles)
        self.user_checker = user_checker
        self.wrap = wrap

    def __bool__(self) -> bool:
        return bool(self.obstacles) or self.user_checker is not None

    def __call__(self, states: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(states, dtype=np.float64))
        if self.wrap is not None:
            x = self.wrap(x)
        ok = np.ones(len(x), dtype=bool)
        for ob in self.obstacles:
            ok &= ~ob.contains(x)
        if self.user_checker is not None:
            user = np.asarray(self.user_checker(x))
            if user.shape != (len(x),) or user.dtype != bool:
                raise TypeError("a state validity checker must return one bool per state "
                                f"(shape ({len(x)},)), got {user.dtype} {user.shape}")
            ok &= user
        return ok
